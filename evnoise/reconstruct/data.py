"""Training pairs for the reconstructor (NumPy only; no torch needed here).

The trainer consumes any *pair dataset*: an object with ``__len__`` and ``__getitem__(i)``
returning a dict with

``"counts"``    uint16 ``(2, h, w)`` noise-event counts ``[ON, OFF]``, already binned
``"image"``     float32 ``(h, w)`` in ``[0, 1]``, display-encoded (sRGB of ``lux / max_lux``)
``"window_s"``  float, the integration window in seconds
``"source"``    str, the id of the source image (validation splits are made by source)

(the protocol of :class:`evnoise.generators.PairDataset`). A dataset may also have a
``sources`` attribute (one id per item, so splitting need not load items), ``max_lux`` and
``params`` (for the model-based baseline), and a method ``sample(i, rng, crop)`` that draws a
fresh pair (the trainer then uses it instead of cropping ``__getitem__``'s item).

Here: :class:`PairList` (pairs in memory), :class:`NpzPairs` (pairs in one ``.npz`` file),
:class:`ResampledPairs` (illuminance images whose counts are re-drawn on the fly, per item and
per epoch, as the paper did for synthetic training), :func:`open_pairs` and helpers.
"""

from __future__ import annotations

import hashlib
import math
import zipfile
from pathlib import Path

import numpy as np

from .._atomic import atomic_output
from ..errors import InputError, ParameterError
from ..params import NoiseParams
from .imaging import bin_counts, bin_mean, lux_to_display, srgb_decode

__all__ = [
    "PairList",
    "NpzPairs",
    "ResampledPairs",
    "Subset",
    "open_pairs",
    "dataset_sources",
    "split_by_source",
    "random_crop",
    "item_seed",
    "skimage_photos",
    "save_pairs_npz",
]

DISTRIBUTIONS = ("exact", "poisson", "sample_counts")


def item_seed(seed: int, *keys: int) -> np.random.Generator:
    """A generator for ``(seed, *keys)`` (e.g. epoch, index): independent streams, reproducible."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), *(int(k) for k in keys)]))


def _check_item(item, where: str):
    if not isinstance(item, dict):
        raise InputError(f"{where}: a pair must be a dict, got {type(item).__name__}")
    for key in ("counts", "image", "window_s"):
        if key not in item:
            raise InputError(f"{where}: pair has no {key!r}")
    counts = np.asarray(item["counts"])
    image = np.asarray(item["image"])
    if counts.ndim != 3 or counts.shape[0] != 2:
        raise InputError(f"{where}: counts must have shape (2, h, w), got {counts.shape}")
    if image.shape != counts.shape[1:]:
        raise InputError(f"{where}: image shape {image.shape} does not match counts {counts.shape[1:]}")
    window = float(item["window_s"])
    if not (math.isfinite(window) and window > 0):
        raise InputError(f"{where}: window_s must be > 0, got {item['window_s']!r}")
    return counts, image, window


def _uint16_counts(counts, where: str) -> np.ndarray:
    """``counts`` as uint16, or an :class:`InputError` when a value is not a whole number in ``[0, 65535]``
    (a cast would wrap or truncate it; NaN fails the range)."""
    c = np.asarray(counts)
    if not (np.issubdtype(c.dtype, np.number) and np.all((c >= 0) & (c <= np.iinfo(np.uint16).max))
            and np.array_equal(c, np.round(c))):
        raise InputError(f"{where}: counts must be whole numbers in [0, 65535] to be stored as uint16")
    return c.astype(np.uint16)


class PairList:
    """Pairs held in memory (protocol-compatible with :class:`evnoise.generators.PairDataset`).

    Parameters
    ----------
    counts : sequence of array (2, h, w)
        Binned counts ``[ON, OFF]`` (non-negative integers).
    images : sequence of array (h, w)
        Display-encoded targets in ``[0, 1]``.
    window_s : float or sequence of float
        Integration window(s), seconds.
    sources : sequence of str, optional
        Source-image id per pair (default: the index).
    max_lux, params : optional
        White level in lux and the noise parameters (used by the model-based baseline).
    """

    def __init__(self, counts, images, *, window_s, sources=None, max_lux=None, params=None):
        if len(counts) != len(images):
            raise InputError(f"{len(counts)} count arrays but {len(images)} images")
        n = len(counts)
        windows = np.asarray(window_s, dtype=np.float64)
        if windows.ndim > 1 or (windows.ndim == 1 and windows.size != n):
            raise InputError(f"{windows.size} values of window_s for {n} pairs (give one, or one per pair)")
        windows = np.broadcast_to(windows, (n,))
        self.sources = [str(s) for s in (sources if sources is not None else range(n))]
        if len(self.sources) != n:
            raise InputError(f"{len(self.sources)} sources for {n} pairs")
        self._items = []
        for i in range(n):
            item = {"counts": counts[i], "image": images[i], "window_s": float(windows[i]),
                    "source": self.sources[i]}
            c, im, w = _check_item(item, f"pair {i}")
            c = _uint16_counts(c, f"pair {i}")
            if not np.all((im >= 0) & (im <= 1)):  # NaN too; the metrics take a data range of 1
                bad = im[~((im >= 0) & (im <= 1))]
                hint = " (8-bit values? divide by 255)" if np.nanmax(im, initial=0) > 1.5 else ""
                raise InputError(f"pair {i}: images must be display values in [0, 1], found "
                                 f"{float(bad.flat[0]):g}{hint}")
            self._items.append({"counts": c, "image": im.astype(np.float32),
                                "window_s": w, "source": self.sources[i]})
        self.max_lux = max_lux
        self.params = params

    def __len__(self):
        return len(self._items)

    def __getitem__(self, i):
        return dict(self._items[int(i)])


class NpzPairs(PairList):
    """Pairs stored in one ``.npz`` (arrays ``counts`` (N, 2, h, w), ``images`` (N, h, w),
    ``window_s`` (N,), ``sources`` (N,) str; optional ``max_lux`` and ``params_json``).

    Loaded with ``allow_pickle=False``. Meant for small experiments and tests; the dataset
    generator writes its own sharded format.
    """

    def __init__(self, path):
        path = Path(path)
        if not path.is_file():
            raise InputError(f"pairs file not found: {path}")
        if not zipfile.is_zipfile(path):
            raise InputError(f"{path} is not a readable .npz pairs file (not a NumPy .npz archive)")
        try:
            with np.load(path, allow_pickle=False) as z:
                _check_npz_members(z, path)
                # only the arrays a pairs file has (another member, however large, is not decompressed)
                data = {k: z[k] for k in NPZ_KEYS if k in z.files}
        except InputError:
            raise
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
            # numpy's own words point at allow_pickle / pickle.load, which evnoise never uses on user files
            why = "it holds Python objects, not plain arrays" if "pickle" in str(exc) else str(exc)
            raise InputError(f"{path} is not a readable .npz pairs file ({why})") from None
        for key in ("counts", "images", "window_s"):
            if key not in data:
                raise InputError(f"{path} has no array {key!r}: not a pairs file")
        counts = data["counts"]
        if counts.ndim != 4 or counts.shape[1] != 2 or data["images"].ndim != 3:
            raise InputError(f"{path}: counts must be (N, 2, h, w) and images (N, h, w), got {counts.shape} and "
                             f"{data['images'].shape}")
        if counts.dtype.kind not in "iuf" or (counts.dtype.kind == "f" and not np.all(
                np.isfinite(counts) & (counts >= 0) & (counts == np.floor(counts)))) or (
                counts.dtype.kind == "i" and counts.size and counts.min() < 0):
            raise InputError(f"{path}: counts must be whole numbers >= 0 (dtype {counts.dtype})")
        params = None
        try:
            if "params_json" in data:
                import json

                params = NoiseParams.from_dict(json.loads(str(data["params_json"][()])))
            max_lux = float(data["max_lux"]) if "max_lux" in data else None
            window_s = np.asarray(data["window_s"], dtype=np.float64)
        except (TypeError, ValueError, RecursionError, AttributeError) as exc:
            raise InputError(f"{path}: params_json, max_lux or window_s is not what a pairs file holds "
                             f"({str(exc)[:200]})") from None
        sources = data["sources"].astype(str).tolist() if "sources" in data else None
        try:
            super().__init__(list(counts), list(data["images"]), window_s=window_s,
                             sources=sources, max_lux=max_lux, params=params)
        except InputError as exc:
            raise InputError(f"{path}: {exc}") from None
        self.path = path


#: The arrays of a :class:`NpzPairs` file (others are not read).
NPZ_KEYS = ("counts", "images", "window_s", "sources", "max_lux", "params_json")


#: The arrays every pairs file has.
NPZ_REQUIRED = ("counts", "images", "window_s")

#: Memory a pairs file takes per byte of its arrays while loading (the arrays, their per-pair copies converted to
#: uint16 / float32, the checks' temporaries).
NPZ_LOAD_FACTOR = 3


def _npy_header(z, info) -> tuple:
    """``(shape, dtype)`` from the ``.npy`` header of archive member ``info`` (only the header is decompressed)."""
    with z.zip.open(info) as fh:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
        elif version in ((2, 0), (3, 0)):  # 3.0 is 2.0 with a UTF-8 header: its ASCII part reads alike
            shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
        else:
            raise ValueError(f"{info.filename} has .npy format version {version}, which evnoise does not read")
    return shape, dtype


def _check_npz_members(z, path) -> None:
    """Check a pairs file from its directory and ``.npy`` headers before any array is read.

    Refused (``InputError``): a missing required array; counts / images whose shapes do not make pairs;
    arrays that together need more than the memory budget (a few MB of deflated zeros may inflate to
    gigabytes); a member whose header declares more data than the archive holds for it (a header of shape
    ``(10**12,)`` made ``np.load`` ask for 7 TiB); Python objects.
    """
    from .._budget import check_allocation

    names = z.zip.namelist()
    headers, total = {}, 0
    for key in NPZ_KEYS:
        name = f"{key}.npy"
        if name not in names:
            continue
        info = z.zip.getinfo(name)
        shape, dtype = _npy_header(z, info)
        if dtype.hasobject:
            raise ValueError(f"{key} holds Python objects, not plain arrays")
        declared = math.prod(shape) * dtype.itemsize
        if declared > info.file_size:
            raise ValueError(f"{key} declares shape {shape} of {dtype} ({declared:,} bytes) but the archive holds "
                             f"{info.file_size:,} bytes for it")
        headers[key] = shape
        total += max(declared, info.file_size)
    missing = [key for key in NPZ_REQUIRED if key not in headers]
    if missing:
        raise InputError(f"{path} has no array {missing[0]!r}: not a pairs file")
    counts, images = headers["counts"], headers["images"]
    if len(counts) != 4 or counts[1] != 2 or len(images) != 3:
        raise InputError(f"{path}: counts must be (N, 2, h, w) and images (N, h, w), got {counts} and {images}")
    if images != (counts[0], *counts[2:]):
        raise InputError(f"{path}: images of shape {images} do not match counts of shape {counts}")
    check_allocation(total * NPZ_LOAD_FACTOR, f"{path}: loading its pairs (counts {counts}, images {images})")


def save_pairs_npz(path, dataset) -> Path:
    """Write the items of a pair dataset (all of the same size) to a :class:`NpzPairs` file.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.npz`` file to write (compressed, atomically; an existing file is replaced).
    dataset : pair dataset
        Any object of the pair protocol (module docstring) with at least one item; its ``max_lux``
        and ``params`` (a :class:`~evnoise.NoiseParams`) are saved when present. Counts are stored as
        uint16 and images as float32.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    items = [dataset[i] for i in range(len(dataset))]
    if not items:
        raise InputError("cannot save an empty dataset")
    shapes = {np.asarray(it["counts"]).shape for it in items}
    if len(shapes) != 1:
        raise InputError(f"all pairs must have the same size to be saved together, got {sorted(shapes)}")
    arrays = {
        "counts": _uint16_counts(np.stack([np.asarray(it["counts"]) for it in items]), str(path)),
        "images": np.stack([np.asarray(it["image"], dtype=np.float32) for it in items]),
        "window_s": np.array([float(it["window_s"]) for it in items]),
        "sources": np.array([str(it.get("source", i)) for i, it in enumerate(items)]),
    }
    if getattr(dataset, "max_lux", None) is not None:
        arrays["max_lux"] = np.array(float(dataset.max_lux))
    if getattr(dataset, "params", None) is not None:
        arrays["params_json"] = np.array(dataset.params.to_json())
    path = Path(path)
    with atomic_output(path, what="pairs file") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
    return path


class ResampledPairs:
    """Illuminance images whose noise counts are drawn afresh for every item and epoch.

    Parameters
    ----------
    lux_images : sequence of array (H, W)
        Illuminance at the sensor in lux, full sensor resolution (before binning).
    params : NoiseParams
        Noise model.
    window_s : float
        Integration window, seconds.
    max_lux : float
        Illuminance shown as white: targets are ``srgb_encode(bin_mean(lux) / max_lux)``.
    binning : int
        Counts are summed over ``binning x binning`` blocks (paper: 2).
    sources : sequence of str, optional
        Source id of each image (default ``"0"``, ``"1"``, ...).
    seed : int
        Base seed; item ``i`` of the fixed view (``ds[i]``) uses ``(seed, 0, i)``; the trainer
        draws with ``(seed, epoch, step, slot)`` through :meth:`sample`.
    distribution : {"exact", "poisson", "sample_counts"}
        ``"exact"``: the count distribution of the event process (drawn directly from precomputed
        per-trial probabilities when every pixel's trials are i.i.d. and alike — no dead time, threshold
        mismatch, background spread, hot pixels, regular timer or reset memory —, which is exact and
        fast; otherwise through :func:`evnoise.sample_counts`). ``"poisson"``: Poisson with each pixel's
        expected count (the paper's synthetic data; from precomputed rates when all pixels at one
        illuminance are alike, else through ``sample_counts(..., distribution="poisson")``, which draws
        each pixel's thresholds and background). ``"sample_counts"``: always call
        :func:`evnoise.sample_counts` (slow: it evaluates the closed form per call).
    """

    def __init__(self, lux_images, params: NoiseParams, *, window_s: float = 1.0, max_lux: float,
                 binning: int = 2, sources=None, seed: int = 0, distribution: str = "exact"):
        if not isinstance(params, NoiseParams):
            raise ParameterError(f"params must be a NoiseParams, got {type(params).__name__}")
        if distribution not in DISTRIBUTIONS:
            raise ParameterError(f"distribution must be one of {DISTRIBUTIONS}, got {distribution!r}")
        if not (isinstance(window_s, (int, float)) and math.isfinite(window_s) and window_s > 0):
            raise ParameterError(f"window_s must be finite and > 0 seconds, got {window_s!r}")
        self.lux = []
        for i, lux in enumerate(lux_images):
            arr = np.asarray(lux, dtype=np.float64)
            if arr.ndim != 2 or arr.shape[0] < binning or arr.shape[1] < binning:
                raise InputError(f"lux image {i} must be 2-D and at least {binning}x{binning}, got {arr.shape}")
            if not np.isfinite(arr).all() or (arr < 0).any():
                raise InputError(f"lux image {i} must be finite and >= 0")
            h, w = (arr.shape[0] // binning) * binning, (arr.shape[1] // binning) * binning
            self.lux.append(np.ascontiguousarray(arr[:h, :w]))
        if not self.lux:
            raise InputError("ResampledPairs needs at least one image")
        self.params = params
        self.window_s = float(window_s)
        self.max_lux = float(max_lux)
        self.binning = int(binning)
        self.seed = int(seed)
        self.distribution = distribution
        self.windows_s = (self.window_s,)
        self.sources = [str(s) for s in (sources if sources is not None else range(len(self.lux)))]
        if len(self.sources) != len(self.lux):
            raise InputError(f"{len(self.sources)} sources for {len(self.lux)} images")
        self._targets = [lux_to_display(bin_mean(lux, self.binning), self.max_lux).astype(np.float32)
                         for lux in self.lux]
        self._probs = {}
        from ..terms import maps_needed, regular_timer
        from ..terms.memory import memory_on

        # every pixel at one illuminance is the nominal pixel: per-value rates describe them all
        self._alike = params.eps_sigma == 0 and not maps_needed(params)
        # ... and its trials are i.i.d.: counts are binomial in the per-trial probabilities
        self._fast = (self._alike and params.refractory_s == 0 and not regular_timer(params)
                      and not memory_on(params))
        if distribution == "poisson" and memory_on(params) and not self._alike:
            raise ParameterError("distribution='poisson' with reset_memory > 0 is known for the nominal pixel only, "
                                 "not with thresholds or a background that differ between pixels (eps_sigma, "
                                 "leak_sigma, hot pixels); use distribution='exact'")

    def __len__(self):
        return len(self.lux)

    def __getitem__(self, i):
        return self.sample(int(i), item_seed(self.seed, 0, int(i)))

    def _per_value(self, i):
        """Image ``i``'s per-pixel ``(a_on, a_off)``, evaluated once per distinct illuminance: the per-trial
        probabilities (``"exact"``) or the expected counts over the window (``"poisson"``)."""
        if i not in self._probs:
            from ..rates import expected_rate, trial_probabilities

            values, inverse = np.unique(self.lux[i], return_inverse=True)
            if self.distribution == "poisson":  # dead time, timer and memory included
                a_on, a_off = expected_rate(values, self.params) * self.window_s
            else:
                a_on, a_off = trial_probabilities(self.params.photons_per_trial(values), self.params)
            shape = self.lux[i].shape
            self._probs[i] = (np.asarray(a_on)[inverse].reshape(shape), np.asarray(a_off)[inverse].reshape(shape))
        return self._probs[i]

    def _draw(self, i, rows, cols, rng) -> np.ndarray:
        """Full-resolution counts (2, h, w) of image ``i`` over the window ``rows x cols``."""
        params = self.params
        if (self.distribution == "sample_counts" or (self.distribution == "exact" and not self._fast)
                or (self.distribution == "poisson" and not self._alike)):
            from ..simulate import sample_counts

            how = "poisson" if self.distribution == "poisson" else "exact"
            return sample_counts(self.lux[i][rows, cols], params, self.window_s,
                                 int(rng.integers(2**63 - 1)), threads=1, distribution=how)
        a_on, a_off = self._per_value(i)
        a_on, a_off = a_on[rows, cols], a_off[rows, cols]
        if self.distribution == "poisson":
            return rng.poisson(np.stack([a_on, a_off])).astype(np.int64)
        p_on, p_off = a_on, a_off
        duration_us = max(1, int(round(self.window_s * 1e6)))
        trials = duration_us / params.trial_us  # trials whose events can land in the window
        # exact, no dead time: i.i.d. trials, each ON (p_on), OFF (p_off) or nothing; event
        # times are uniform within their trial, so the last, partial trial counts with
        # probability frac
        n_full = math.floor(trials)
        frac = trials - n_full
        on = rng.binomial(n_full, p_on)
        q_off = np.where(p_on < 1.0, p_off / np.maximum(1.0 - p_on, 1e-300), 0.0)
        off = rng.binomial(n_full - on, np.clip(q_off, 0.0, 1.0))
        if frac > 0:
            u = rng.random(p_on.shape)
            on = on + (u < p_on * frac)
            off = off + ((u >= p_on * frac) & (u < (p_on + p_off) * frac))
        return np.stack([on, off]).astype(np.int64)

    def sample(self, i: int, rng, crop: int | None = None) -> dict:
        """A fresh pair from image ``i``; with ``crop`` a random ``crop x crop`` (binned) window.

        Parameters
        ----------
        i : int
            Index of the image.
        rng : numpy.random.Generator
            Draws the crop's position and the counts.
        crop : int, optional
            Side of the window in binned pixels, at most the binned image's height and width; by
            default the whole image.

        Returns
        -------
        dict
            ``"counts"`` uint16 ``(2, h, w)`` binned ``[ON, OFF]`` counts (capped at 65535), ``"image"``
            float32 ``(h, w)`` display-encoded target, ``"window_s"`` and ``"source"``.
        """
        b = self.binning
        target = self._targets[i]
        h, w = target.shape
        if crop is None:
            r0, c0, ch, cw = 0, 0, h, w
        else:
            if crop > h or crop > w:
                raise InputError(f"crop {crop} is larger than image {self.sources[i]} ({h}x{w} binned pixels)")
            r0 = int(rng.integers(0, h - crop + 1))
            c0 = int(rng.integers(0, w - crop + 1))
            ch = cw = crop
        counts = self._draw(i, slice(r0 * b, (r0 + ch) * b), slice(c0 * b, (c0 + cw) * b), rng)
        binned = bin_counts(counts, b)
        return {"counts": np.minimum(binned, np.iinfo(np.uint16).max).astype(np.uint16),
                "image": target[r0:r0 + ch, c0:c0 + cw].copy(), "window_s": self.window_s,
                "source": self.sources[i]}


class Subset:
    """Items ``indices`` of a pair dataset (keeps ``sample`` and metadata of the parent)."""

    def __init__(self, dataset, indices):
        self.dataset = dataset
        self.indices = [int(i) for i in indices]
        parent_sources = dataset_sources(dataset)
        self.sources = [parent_sources[i] for i in self.indices]
        self.max_lux = getattr(dataset, "max_lux", None)
        self.params = getattr(dataset, "params", None)
        self.binning = getattr(dataset, "binning", 2)
        self.windows_s = getattr(dataset, "windows_s", None)
        if hasattr(dataset, "sample"):
            self.sample = lambda i, rng, crop=None: dataset.sample(self.indices[i], rng, crop)

    def __len__(self):
        return len(self.indices)

    def __getitem__(self, i):
        return self.dataset[self.indices[int(i)]]


def dataset_sources(dataset) -> list:
    """Source id of every item (from ``dataset.sources`` when present, else by loading items)."""
    sources = getattr(dataset, "sources", None)
    if sources is not None:
        sources = [str(s) for s in sources]
        if len(sources) != len(dataset):
            raise InputError(f"dataset lists {len(sources)} sources for {len(dataset)} items")
        return sources
    return [str(dataset[i].get("source", i)) for i in range(len(dataset))]


def split_by_source(dataset, *, val_fraction: float = 0.15, seed: int = 0):
    """Indices ``(train, val)`` with no source image in both; at least one source in each.

    Sources are ordered by a hash of ``(seed, source)``, so the split is reproducible and does
    not depend on the order of items.

    Parameters
    ----------
    dataset : pair dataset
        Any object of the pair protocol with at least two source ids (see :func:`dataset_sources`).
    val_fraction : float, default 0.15
        Fraction of the source images (not of the items) put in the validation set, in ``(0, 1)``;
        rounded to a whole number of sources, at least one and leaving at least one for training.
    seed : int, default 0
        Seed of the hash that orders the sources.

    Returns
    -------
    train : list of int
        Indices of the training items, in order.
    val : list of int
        Indices of the validation items, in order.
    """
    if not 0 < val_fraction < 1:
        raise ParameterError(f"val_fraction must be in (0, 1), got {val_fraction!r}")
    sources = dataset_sources(dataset)
    unique = sorted(set(sources))
    if len(unique) < 2:
        raise InputError(
            f"cannot split by source: the dataset has {len(unique)} source image(s); give a "
            "separate validation set"
        )

    def key(s):
        return hashlib.sha256(f"{seed}:{s}".encode()).hexdigest()

    ordered = sorted(unique, key=key)
    n_val = min(len(unique) - 1, max(1, round(val_fraction * len(unique))))
    val_sources = set(ordered[:n_val])
    train = [i for i, s in enumerate(sources) if s not in val_sources]
    val = [i for i, s in enumerate(sources) if s in val_sources]
    return train, val


def random_crop(item: dict, crop: int, rng) -> dict:
    """A random ``crop x crop`` window of a pair (counts and image alike)."""
    counts, image, window = _check_item(item, "pair")
    h, w = image.shape
    if crop > h or crop > w:
        raise InputError(f"crop {crop} is larger than a pair of {h}x{w} binned pixels; use a smaller crop "
                         "(training crops count binned pixels, a dataset's crop_shape sensor pixels)")
    r0 = int(rng.integers(0, h - crop + 1))
    c0 = int(rng.integers(0, w - crop + 1))
    out = dict(item)
    out["counts"] = counts[:, r0:r0 + crop, c0:c0 + crop]
    out["image"] = image[r0:r0 + crop, c0:c0 + crop]
    return out


def open_pairs(path, split: str = "train", *, verify: bool = True):
    """Open a pair dataset: a ``.npz`` pairs file, or a folder written by ``evnoise make-dataset``.

    Parameters
    ----------
    path : str or os.PathLike
        A ``.npz`` pairs file (:class:`NpzPairs`) or a dataset folder (:class:`evnoise.generators.PairDataset`).
    split : {"train", "val", "test"}, default "train"
        The split of a dataset folder; unused for a ``.npz`` file.
    verify : bool, default True
        Check each shard of a folder's split against its SHA-256 in the manifest first, as training
        and evaluation read them all; unused for a ``.npz`` file.

    Returns
    -------
    NpzPairs or evnoise.generators.PairDataset
        The dataset.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"dataset not found: {path}")
    if path.is_file():
        if path.suffix == ".npz":
            return NpzPairs(path)
        raise InputError(f"{path} is not a dataset (expected a make-dataset folder or a .npz pairs file)")
    try:
        from ..generators import PairDataset  # written by `evnoise make-dataset`
    except ImportError:
        raise InputError(
            f"cannot read dataset folder {path}: this evnoise has no dataset reader "
            "(evnoise.generators.PairDataset)"
        ) from None
    return PairDataset(path, split=split, verify=verify)


# photos bundled with scikit-image (no download), used for synthetic experiments and tests
SKIMAGE_PHOTOS = (
    "astronaut", "brick", "camera", "cell", "chelsea", "coffee", "coins", "grass", "gravel",
    "hubble_deep_field", "immunohistochemistry", "microaneurysms", "moon", "page", "retina",
    "rocket", "text", "motorcycle_left",
)


def skimage_photos(names=SKIMAGE_PHOTOS) -> dict:
    """Grayscale display-encoded photos in ``[0, 1]`` from scikit-image's bundled data.

    These are read from the installed scikit-image at run time; they are not part of evnoise.
    """
    try:
        import skimage.data as data
        from skimage.color import rgb2gray
    except ImportError:
        raise InputError("skimage_photos needs scikit-image: pip install 'evnoise[train]'") from None
    out = {}
    for name in names:
        if name == "motorcycle_left":
            img = data.stereo_motorcycle()[0]
        else:
            fetch = getattr(data, name, None)
            if fetch is None:
                raise InputError(f"scikit-image has no sample image {name!r}")
            img = fetch()
        img = np.asarray(img)
        if img.ndim == 3:
            img = img[..., :3]
            # rgb2gray works on linear values in principle; for display-encoded inputs the
            # luma of the encoded values is the usual (and here sufficient) approximation
            img = rgb2gray(img)
        elif img.dtype == np.uint8:
            img = img / 255.0
        elif img.dtype == bool:
            img = img.astype(np.float64)
        img = np.asarray(img, dtype=np.float64)
        if img.max() > 1.0:
            img = img / img.max()
        out[name] = np.clip(img, 0.0, 1.0)
    return out


def photos_to_lux(photos: dict, max_lux: float) -> dict:
    """Display-encoded photos -> illuminance in lux (``max_lux`` = white)."""
    return {k: srgb_decode(v) * float(max_lux) for k, v in photos.items()}
