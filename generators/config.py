"""The options of a pair dataset, as one validated, immutable value object.

:class:`PairConfig` holds everything that decides the *content* of a dataset (sizes, windows,
illumination, noise model, seed, splits, sharding, compression). How the work is run
(workers, threads, a Dask scheduler, progress bars) is not part of it: it never changes the
bytes written.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass

from evnoise.errors import ParameterError
from evnoise.params import NoiseParams
from evnoise.radiometry import FIT_MODES

__all__ = ["PairConfig", "MODES", "COMPRESSIONS", "LEVELS", "parse_range", "parse_windows", "parse_shape"]

#: How counts are drawn: ``"counts"`` (count sampler) or ``"events"`` (full event simulation).
MODES = ("counts", "events")
#: HDF5 compression of the shards' ``counts`` and ``image`` datasets.
COMPRESSIONS = ("gzip", "lzf", None)
#: The scene's illuminance is quantised to steps of ``white_lux / LEVELS`` (a 14-bit display:
#: finer than an 8-bit sRGB display everywhere, at most 0.2 of an 8-bit code near black). The
#: count sampler's per-level table then fits a core's L2 cache.
LEVELS = 16383
#: Preset used when neither ``preset`` nor ``params`` is given.
DEFAULT_PRESET = "evk3-hd"
#: Largest count a ``uint16`` bin holds; larger binned counts saturate at this value.
COUNT_MAX = 65535
_ENCODINGS = ("srgb", "gamma2.2", "linear")


#: largest sensor a dataset is made at (the image decoder's default limit: a frame is made whole, in float64)
MAX_SENSOR_PIXELS = 1 << 26
#: most crops taken from one image (a billion made a run of days with nothing to stop it but Ctrl-C)
MAX_CROPS_PER_IMAGE = 100_000


def _int(value, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or int(value) < minimum:
        raise ParameterError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _positive(value, name: str, unit: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be a number ({unit}), got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ParameterError(f"{name} must be finite and > 0 {unit}, got {value!r}")
    return v


def _shape(value, name: str):
    if value is None:
        return None
    try:
        h, w = value
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be (height, width) in pixels, got {value!r}") from None
    return (_int(h, f"{name} height", 1), _int(w, f"{name} width", 1))


def _range(value, name: str, unit: str):
    """A scalar or ``(lo, hi)`` with ``0 < lo <= hi``, as a tuple of two floats."""
    if isinstance(value, (int, float, numbers.Real)) and not isinstance(value, bool):
        v = _positive(value, name, unit)
        return (v, v)
    try:
        lo, hi = value
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be a number or a (low, high) pair ({unit}), got {value!r}") from None
    lo, hi = _positive(lo, name, unit), _positive(hi, name, unit)
    if lo > hi:
        raise ParameterError(f"{name} range must have low <= high, got {lo:g}:{hi:g}")
    return (lo, hi)


def parse_range(text: str, flag: str, unit: str):
    """``"18"`` -> ``(18.0, 18.0)``; ``"6:30"`` -> ``(6.0, 30.0)`` (a log-uniform range)."""
    parts = str(text).split(":")
    if len(parts) not in (1, 2):
        raise ParameterError(f"{flag} must be a number or LOW:HIGH ({unit}), got {text!r}")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ParameterError(f"{flag} must be a number or LOW:HIGH ({unit}), got {text!r}") from None
    return _range(values[0] if len(values) == 1 else tuple(values), flag, unit)


def parse_windows(texts) -> tuple:
    """Windows in seconds from ``["0.1,0.25", "1"]`` (comma lists, repeatable flags)."""
    values = []
    for text in texts:
        for part in str(text).split(","):
            part = part.strip()
            if not part:
                continue
            try:
                values.append(float(part))
            except ValueError:
                raise ParameterError(f"windows_s must be seconds (e.g. 0.1,0.25,1), got {part!r}") from None
    if not values:
        raise ParameterError("windows_s needs at least one window in seconds")
    return tuple(values)


def parse_shape(text: str, flag: str):
    """``"1280x720"`` -> ``(720, 1280)`` (H, W); ``"256"`` -> ``(256, 256)``."""
    import re

    m = re.fullmatch(r"\s*(\d+)\s*(?:[xX*,]\s*(\d+)\s*)?", str(text))
    if not m:
        raise ParameterError(f"{flag} must be WIDTHxHEIGHT (or one number for a square), got {text!r}")
    w = int(m.group(1))
    h = int(m.group(2)) if m.group(2) else w
    if min(w, h) < 1 or max(w, h) > 65536:
        raise ParameterError(f"{flag} sizes must be 1 .. 65536 pixels, got {text!r}")
    return (h, w)


@dataclass(frozen=True)
class PairConfig:
    """What a pair dataset contains. All sizes are in sensor pixels (before binning).

    Parameters
    ----------
    sensor_shape : (H, W)
        Sensor size; every source image is first brought to it with ``fit``
        (default ``(720, 1280)``, the EVK3-HD of the Noise2Image paper).
    crop_shape : (h, w), optional
        Size of the training crops cut from the fitted image (random positions); ``None``
        (default) keeps the whole sensor. Both must be multiples of ``binning``.
    crops_per_image : int
        Crops per source image (each with its own position, illumination and noise).
        More than 1 needs ``crop_shape``.
    binning : int
        Counts are summed and the image averaged over ``binning x binning`` blocks (paper: 2).
    windows_s : sequence of float
        Integration windows in seconds (rounded to whole microseconds, all different); every
        crop is sampled once per window (paper Table S1: 0.1, 0.25, 0.5, 1, 2 s).
    mode : {"counts", "events"}
        ``"counts"``: draw the counts directly (the event process's own count distribution).
        ``"events"``: simulate the event stream and count it (slower; same distribution).
    max_lux : float or (low, high)
        Illuminance in lux of full-scale white of display-referred sources (8/16-bit files,
        procedural images); a range draws one value per crop, log-uniformly (brightness
        augmentation). Default 18 lux (the Noise2Image monitor).
    lux_scale : float or (low, high)
        Lux per unit of linear sources (OpenEXR, float TIFF); a range is drawn per crop.
    contrast : float or (low, high)
        Exponent ``gamma`` applied to the source's linear luminance, ``Y -> Y ** gamma``
        (contrast augmentation, drawn per crop, log-uniformly); default 1.
    white_lux : float, optional
        Illuminance shown as white in the stored images: ``image = srgb(lux / white_lux)``,
        clipped to 1. Default: the top of the ``max_lux`` range (no display-referred source
        clips).
    fit : {"cover", "crop", "resize"}
        How source images are brought to ``sensor_shape`` (see :func:`evnoise.radiometry.fit_to_sensor`).
    encoding : {"srgb", "gamma2.2", "linear"}
        Transfer function of display-referred source files.
    clip_invalid : bool
        Clip NaN / Inf / negative pixel values of source files instead of skipping the file.
    splits : (train, val, test)
        Fractions of the *source images* in each split (normalised to sum 1).
    shard_size : int
        Target number of pairs per HDF5 shard (all pairs of a source stay in one shard).
    compression : {"lzf", "gzip", None}
        HDF5 filter of ``counts`` and ``image`` (with the shuffle filter; gzip at level 1). The
        default is ``"lzf"``: the shards' reader is h5py (evnoise's training and evaluation), which
        always includes LZF, and LZF makes a one-worker job about 1.3x faster than gzip (gzip's
        compression is 39 % of a pair's time; benchmarks/REPORT.md) for shards about 1.17x larger.
        Choose ``"gzip"`` for shards that tools without h5py's LZF filter must read.
    seed : int, optional
        The seed everything derives from; ``None`` lets :func:`~evnoise.generators.make_dataset`
        pick one (reusing the seed of an interrupted run in the same folder).
    preset : str, optional
        Name (or TOML path) of the noise-model preset (default ``"evk3-hd"`` when ``params``
        is not given), recorded in the manifest; ``"custom"`` is recorded for explicit
        ``params`` without a preset name.
    params : NoiseParams, optional
        Noise-model parameters; default: ``load_preset(preset)``.
    """

    sensor_shape: tuple = (720, 1280)
    crop_shape: tuple | None = None
    crops_per_image: int = 1
    binning: int = 2
    windows_s: tuple = (1.0,)
    mode: str = "counts"
    max_lux: tuple = (18.0, 18.0)
    lux_scale: tuple = (1.0, 1.0)
    contrast: tuple = (1.0, 1.0)
    white_lux: float | None = None
    fit: str = "cover"
    encoding: str = "srgb"
    clip_invalid: bool = False
    splits: tuple = (0.8, 0.1, 0.1)
    shard_size: int = 64
    compression: str | None = "lzf"
    seed: int | None = None
    preset: str | None = None
    params: NoiseParams | None = None

    def __post_init__(self):
        def put(name, value):
            object.__setattr__(self, name, value)

        sensor = _shape(self.sensor_shape, "sensor_shape")
        if sensor is not None and sensor[0] * sensor[1] > MAX_SENSOR_PIXELS:  # a frame is made whole, in float64
            raise ParameterError(f"sensor_shape {sensor[1]}x{sensor[0]} has more than the {MAX_SENSOR_PIXELS:,} "
                                 f"pixels (8192 x 8192) a dataset's images may have")
        put("sensor_shape", sensor)
        b = _int(self.binning, "binning", 1)
        put("binning", b)
        crop = _shape(self.crop_shape, "crop_shape")
        put("crop_shape", crop)
        if crop is not None and (crop[0] > sensor[0] or crop[1] > sensor[1]):
            raise ParameterError(f"crop_shape {crop[1]}x{crop[0]} is larger than the sensor "
                                 f"{sensor[1]}x{sensor[0]}")
        h, w = crop if crop is not None else sensor
        if h % b or w % b:
            what = "crop" if crop is not None else "sensor"
            raise ParameterError(f"the {what} size {w}x{h} must be a multiple of binning={b} in both directions")
        n_crops = _int(self.crops_per_image, "crops_per_image", 1)
        if n_crops > MAX_CROPS_PER_IMAGE:
            raise ParameterError(f"crops_per_image must be at most {MAX_CROPS_PER_IMAGE:,}, got {n_crops:,}")
        if n_crops > 1 and crop is None:
            raise ParameterError("crops_per_image > 1 needs a crop_shape smaller than the sensor")
        put("crops_per_image", n_crops)
        windows = self.windows_s
        if isinstance(windows, (int, float)) and not isinstance(windows, bool):
            windows = (windows,)
        try:
            windows = tuple(windows)
        except TypeError:
            raise ParameterError(f"windows_s must be a sequence of seconds, got {self.windows_s!r}") from None
        if not windows:
            raise ParameterError("windows_s needs at least one window in seconds")
        checked = []
        for wnd in windows:
            v = _positive(wnd, "window", "seconds")
            if round(v * 1e6) < 1:
                raise ParameterError(f"windows must be at least 1 microsecond, got {wnd!r} s")
            checked.append(v)
        us = [round(v * 1e6) for v in checked]
        if len(set(us)) != len(us):
            raise ParameterError(f"windows must all differ (to the microsecond), got {list(windows)}")
        put("windows_s", tuple(checked))
        if self.mode not in MODES:
            raise ParameterError(f"mode must be one of {MODES}, got {self.mode!r}")
        put("max_lux", _range(self.max_lux, "max_lux", "lux"))
        put("lux_scale", _range(self.lux_scale, "lux_scale", "lux per unit"))
        put("contrast", _range(self.contrast, "contrast", "(gamma exponent)"))
        if self.white_lux is not None:
            put("white_lux", _positive(self.white_lux, "white_lux", "lux"))
        if self.fit not in FIT_MODES:
            raise ParameterError(f"fit must be one of {FIT_MODES}, got {self.fit!r}")
        if self.encoding not in _ENCODINGS:
            raise ParameterError(f"encoding must be one of {_ENCODINGS}, got {self.encoding!r}")
        put("clip_invalid", bool(self.clip_invalid))
        try:
            fractions = tuple(float(f) for f in self.splits)
        except (TypeError, ValueError):
            raise ParameterError(f"splits must be three fractions (train, val, test), got {self.splits!r}") from None
        if len(fractions) != 3 or not all(math.isfinite(f) and f >= 0 for f in fractions) or sum(fractions) <= 0:
            raise ParameterError(f"splits must be three fractions >= 0 (train, val, test) with a positive sum, "
                                 f"got {self.splits!r}")
        total = sum(fractions)
        put("splits", tuple(f / total for f in fractions))
        put("shard_size", _int(self.shard_size, "shard_size", 1))
        if self.compression not in COMPRESSIONS:
            raise ParameterError(f"compression must be one of {COMPRESSIONS}, got {self.compression!r}")
        if self.seed is not None:
            put("seed", _int(self.seed, "seed", 0))
        if self.params is not None and not isinstance(self.params, NoiseParams):
            raise ParameterError(f"params must be a NoiseParams, got {type(self.params).__name__}")
        if self.preset is not None and (not isinstance(self.preset, str) or not self.preset):
            raise ParameterError(f"preset must be a preset name or a TOML path, got {self.preset!r}")
        if self.preset is None:
            put("preset", "custom" if self.params is not None else DEFAULT_PRESET)

    # -- derived ---------------------------------------------------------------------------
    @property
    def noise_params(self) -> NoiseParams:
        """The model parameters (``params``, or the preset loaded by name)."""
        if self.params is not None:
            return self.params
        from evnoise.params import load_preset

        if self.preset == "custom":
            raise ParameterError("preset 'custom' needs explicit params")
        return load_preset(self.preset)

    @property
    def display_white_lux(self) -> float:
        """Lux shown as white (image value 1): ``white_lux`` or the top of ``max_lux``."""
        return self.white_lux if self.white_lux is not None else self.max_lux[1]

    @property
    def lux_step(self) -> float:
        """Quantisation step of the scene's illuminance, lux."""
        return self.display_white_lux / LEVELS

    @property
    def windows_us(self) -> tuple:
        return tuple(round(w * 1e6) for w in self.windows_s)

    @property
    def sample_shape(self) -> tuple:
        """``(h, w)`` of a crop in sensor pixels (before binning)."""
        return self.crop_shape if self.crop_shape is not None else self.sensor_shape

    @property
    def pair_shape(self) -> tuple:
        """``(h, w)`` of a stored pair (after binning)."""
        h, w = self.sample_shape
        return (h // self.binning, w // self.binning)

    @property
    def samples_per_source(self) -> int:
        return self.crops_per_image * len(self.windows_s)

    def replace(self, **changes) -> "PairConfig":
        """A copy with some options changed (checked again, as a new configuration).

        Parameters
        ----------
        **changes
            New values of options, by name (the class's parameters).

        Returns
        -------
        PairConfig
            The new configuration.
        """
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """Plain JSON types; ``params`` are the resolved model parameters."""
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "params":
                continue
            out[f.name] = list(value) if isinstance(value, tuple) else value
        out["params"] = self.noise_params.to_dict()
        out["white_lux"] = self.display_white_lux
        return out

    @classmethod
    def from_dict(cls, data: dict) -> "PairConfig":
        """The configuration a dict describes, e.g. one written by :meth:`to_dict` (a manifest's ``config``).

        Parameters
        ----------
        data : dict
            Options by name, in plain JSON types (lists for tuples); ``params``, if present, is a dict of
            model parameters read with :meth:`evnoise.NoiseParams.from_dict`. An unknown name is an error.

        Returns
        -------
        PairConfig
            The configuration, checked.
        """
        data = dict(data)
        params = data.pop("params", None)
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise ParameterError(f"unknown dataset option(s): {', '.join(sorted(unknown))}")
        for key in ("sensor_shape", "crop_shape", "windows_s", "max_lux", "lux_scale", "contrast", "splits"):
            if isinstance(data.get(key), list):
                data[key] = tuple(data[key])
        if params is not None:
            data["params"] = NoiseParams.from_dict(params)
        return cls(**data)
