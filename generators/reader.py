"""Reading a pair dataset: :class:`PairDataset`, usable directly by PyTorch's ``DataLoader``."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from evnoise.errors import InputError, ParameterError

from .dataset import SPLITS, load_manifest

__all__ = ["PairDataset"]

#: Bytes of memory per binned pixel of one pair: the pair (uint16 counts [ON, OFF] and a float32 image) and the
#: float64 copies evaluation and ``evnoise info``'s check make of it.
PAIR_WORK_BYTES = 64


class PairDataset:
    """The pairs of one split of a dataset made by ``evnoise make-dataset``.

    A map-style dataset (``len`` and indexing) that a ``torch.utils.data.DataLoader`` uses
    directly, with any ``num_workers``: HDF5 files are opened lazily, one handle per shard and
    per process (a forked or spawned worker opens its own), and the object pickles without
    them. No torch import is needed here.

    Parameters
    ----------
    path : str or os.PathLike
        The dataset folder (or its ``manifest.json``).
    split : {"train", "val", "test"}
        Which split (made by source image: no source has pairs in two splits).
    verify : bool
        Check every shard of the split against its SHA-256 in the manifest first.

    Attributes
    ----------
    sources : list of str
        The source id of every item (without reading the shards).
    params : NoiseParams
        The noise model the counts were drawn with.
    max_lux : float
        Lux shown as white: ``image = srgb(lux / max_lux)`` (the dataset's ``white_lux``).
    binning : int
        Counts were summed over ``binning x binning`` sensor pixels.
    windows_s : tuple of float
        The integration windows of the dataset.
    manifest : dict
        The whole manifest (generation config, shards, skipped sources).

    Notes
    -----
    ``ds[i]`` is a dict:

    ``"counts"``          uint16 ``(2, h, w)``: noise-event counts ``[ON, OFF]`` after binning
    ``"image"``           float32 ``(h, w)`` in ``[0, 1]``: display-encoded (sRGB) grey image
    ``"window_s"``        float: the integration window in seconds
    ``"source"``          str: id of the source image
    ``"crop_index"``      int: crop number within the source
    ``"crop_box"``        int32 ``(4,)``: top, left, height, width in fitted-sensor pixels
    ``"lux_scale"``       float: lux of image value 1 (``srgb_decode(image) * lux_scale`` is the binned lux)
    ``"max_lux"``         float: lux of the source's full-scale white for this crop
    ``"contrast_gamma"``  float: contrast exponent applied to the source's luminance
    ``"seed"``            int: the pair's noise seed
    ``"saturated"``       int: count bins that saturated at 65535 (normally 0)
    """

    def __init__(self, path, split: str = "train", *, verify: bool = False):
        if split not in SPLITS:
            raise ParameterError(f"split must be one of {SPLITS}, got {split!r}")
        root, manifest = load_manifest(path)
        self.root = Path(root)
        self.split = split
        self.manifest = manifest
        config = manifest["config"]
        per_source = int(config["crops_per_image"]) * len(config["windows_s"])
        shards = [s for s in manifest["shards"] if s["split"] == split and s["samples"] > 0]
        self._paths = [os.fspath(self.root / s["file"]) for s in shards]
        self._offsets = np.cumsum([0] + [int(s["samples"]) for s in shards])
        sources = []
        for s in shards:
            if len(s["sources"]) * per_source != s["samples"]:
                raise InputError(f"manifest of {self.root} is inconsistent: shard {s['name']} lists "
                                 f"{len(s['sources'])} sources for {s['samples']} pairs")
            sources.extend(item for item in s["sources"] for _ in range(per_source))
        self.sources = sources
        _, h, w = manifest["pair"]["counts"]["shape"]
        self._pair_shape = (h, w)
        self._samples = [int(s["samples"]) for s in shards]
        from evnoise._budget import check_allocation

        # a pair read (uint16 counts, float32 image) and the float64 work done on it (evaluation, `info`'s check)
        check_allocation(h * w * PAIR_WORK_BYTES, f"reading the {w}x{h} pairs the manifest of {self.root} declares")
        if verify:
            from .shards import file_sha256

            for s, p in zip(shards, self._paths, strict=True):
                if not Path(p).is_file() or file_sha256(p) != s["sha256"]:
                    raise InputError(f"shard {p} is missing or does not match its checksum; run make-dataset "
                                     "again on this folder to repair it")
        from evnoise.params import NoiseParams

        self.params = NoiseParams.from_dict(config["params"])
        self.max_lux = float(config["white_lux"])
        self.binning = int(config["binning"])
        self.windows_s = tuple(float(w) for w in config["windows_s"])
        preset = config.get("preset")
        #: the preset name (or TOML path) the pairs were made with; ``None`` for parameters given without one
        self.preset = preset if isinstance(preset, str) and preset and preset != "custom" else None
        self._handles: dict = {}
        self._meta: dict = {}
        self._pid = os.getpid()

    def __len__(self) -> int:
        return int(self._offsets[-1])

    def __repr__(self) -> str:
        shape = self.manifest["pair"]["counts"]["shape"]
        return (f"PairDataset({os.fspath(self.root)!r}, split={self.split!r}: {len(self)} pairs of "
                f"{shape[2]}x{shape[1]}, windows {list(self.windows_s)} s)")

    # -- lazy HDF5 handles (one per shard and process) ------------------------------------
    def _file(self, k: int):
        if os.getpid() != self._pid:  # a forked worker: never reuse the parent's handles
            self._handles, self._meta, self._pid = {}, {}, os.getpid()
        f = self._handles.get(k)
        if f is None:
            import h5py

            from evnoise._h5 import check_global_heaps, check_stored_inside

            from .shards import read_meta

            path = self._paths[k]
            check_global_heaps(path)
            try:
                f = h5py.File(path, "r")
            except OSError as exc:
                raise InputError(f"cannot open shard {path}: {exc}") from None
            try:
                # as for events.h5 (evnoise._h5.open_h5): nothing is read from other files (external links, external
                # storage, virtual datasets), so a shard cannot make a reader open what the user did not name
                check_stored_inside(f, path)
                self._check_layout(f, path, k)
                self._meta[k] = read_meta(f, path)
            except BaseException:
                f.close()
                raise
            self._handles[k] = f
        return f

    def _check_layout(self, f, path, k: int) -> None:
        """Refuse a shard whose ``counts`` / ``image`` differ from the pairs the manifest declares (shape, dtype,
        chunks), before any pair is read: a small file of compressed zeros may declare gigabytes per pair."""
        from evnoise._budget import check_allocation

        h, w = self._pair_shape
        n = self._samples[k]
        for key, shape, dtype in (("counts", (n, 2, h, w), np.uint16), ("image", None, np.float32)):
            try:
                ds = f[key]
                got, got_dtype, chunks = ds.shape, ds.dtype, ds.chunks
            except (KeyError, OSError, TypeError, AttributeError) as exc:
                raise InputError(f"{path} is not a complete evnoise pairs shard: no dataset {key!r} ({exc})") from None
            if shape is None:  # one image per crop: any number of rows (read_meta checks the pairs point inside)
                shape = (got[0] if len(got) == 3 else -1, h, w)
            if got != shape or got_dtype != dtype:
                raise InputError(f"{path}: {key!r} is {got_dtype} of shape {got}, but the manifest declares "
                                 f"{np.dtype(dtype)} of shape {shape}")
            if chunks is not None:
                check_allocation(math.prod(chunks) * got_dtype.itemsize,
                                 f"{path}: one stored chunk of {key!r} (shape {chunks})")

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_handles"], state["_meta"] = {}, {}
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._pid = os.getpid()

    def close(self) -> None:
        """Close the open shard files of this process."""
        for f in self._handles.values():
            try:
                f.close()
            except Exception:
                pass
        self._handles, self._meta = {}, {}

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def __del__(self):
        try:
            if os.getpid() == self._pid:
                self.close()
        except Exception:
            pass

    # -- items -----------------------------------------------------------------------------
    def locate(self, i: int) -> tuple:
        """``(shard, row)`` of item ``i``: the index of its shard in the split and its row there.

        Parameters
        ----------
        i : int
            Index of the pair in the split; negative counts from the end.

        Returns
        -------
        tuple of (int, int)
            The shard's index in the split's order and the pair's row in that shard.

        Raises
        ------
        TypeError
            ``i`` is not an integer (a bool is not one).
        IndexError
            ``i`` is out of range.
        """
        n = len(self)
        if isinstance(i, (bool, np.bool_)) or not isinstance(i, (int, np.integer)):
            raise TypeError(f"PairDataset indices must be integers, got {type(i).__name__}")
        i = int(i)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"index {i} is out of range for a split of {n} pairs")
        k = int(np.searchsorted(self._offsets, i, side="right")) - 1
        return k, i - int(self._offsets[k])

    def __getitem__(self, i) -> dict:
        k, row = self.locate(i)
        f = self._file(k)
        meta = self._meta[k]
        try:
            counts = np.asarray(f["counts"][row])
            image = np.asarray(f["image"][int(meta["image_index"][row])])
        except OSError as exc:
            raise InputError(f"cannot read pair {row} of {self._paths[k]}: {exc}") from None
        return {
            "counts": counts,
            "image": image,
            "window_s": float(meta["window_s"][row]),
            "source": meta["source"][row],
            "crop_index": int(meta["crop_index"][row]),
            "crop_box": meta["crop_box"][row].copy(),
            "lux_scale": float(meta["lux_scale"][row]),
            "max_lux": float(meta["max_lux"][row]),
            "contrast_gamma": float(meta["contrast_gamma"][row]),
            "seed": int(meta["seed"][row]),
            "saturated": int(meta["saturated"][row]),
        }
