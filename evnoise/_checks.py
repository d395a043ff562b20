"""Validation helpers shared by the public functions (raise, never assert)."""

from __future__ import annotations

import math
import numbers
import os
from pathlib import Path

import numpy as np

from .errors import InputError, ParameterError
from .params import NoiseParams


def as_generator(rng) -> np.random.Generator:
    """Normalise ``rng`` (a Generator, an int seed, a SeedSequence or None) to a Generator."""
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None or isinstance(rng, np.random.SeedSequence):
        return np.random.default_rng(rng)
    if isinstance(rng, numbers.Integral) and not isinstance(rng, bool):
        if rng < 0:
            raise ParameterError(f"seed must be a non-negative integer, got {rng}")
        return np.random.default_rng(int(rng))
    raise ParameterError(f"rng must be a numpy Generator, an integer seed or None, got {type(rng).__name__}")


def default_threads() -> int:
    """Threads used by the simulators: ``NUMBA_NUM_THREADS`` if set, else the CPU count."""
    env = os.environ.get("NUMBA_NUM_THREADS")
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            pass
    return max(1, os.cpu_count() or 1)


def resolve_threads(threads) -> int:
    """``threads`` as given (a whole number >= 1; :class:`ParameterError` otherwise), or :func:`default_threads` for
    None."""
    if threads is None:
        return default_threads()
    if isinstance(threads, (bool, np.bool_)) or not isinstance(threads, numbers.Integral) or threads < 1:
        raise ParameterError(f"threads must be a whole number >= 1 (or None: every CPU), got {threads!r}")
    return int(threads)


def check_input_file(path, *, missing: str, kind: str, folders: bool = False):
    """``Path(path)`` of an input that must be an existing file; :class:`InputError` naming it otherwise.

    ``missing`` names it when absent (``"image"`` -> "image not found: ..."), ``kind`` when it is a
    folder or a special file (``"an image file"`` -> "expected an image file, got a folder: ..."). A symbolic link
    counts as what it points to. ``folders``: a folder is fine too (``evnoise info`` reads dataset folders).
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{missing} not found: {path}")
    if path.is_dir():
        if folders:
            return path
        raise InputError(f"expected {kind}, got a folder: {path}")
    if not path.is_file():  # a pipe would block the read for ever, a device (/dev/zero) never ends
        raise InputError(f"expected {kind}, got a special file (a pipe, device or socket): {path}")
    return path


def read_bounded_file(path, *, max_bytes: int, missing: str, kind: str, bound: str) -> bytes:
    """The bytes of an input that must be a regular file of at most ``max_bytes`` bytes; :class:`InputError`
    naming it otherwise.

    :func:`check_input_file`'s checks first (``missing``, ``kind``: a pipe would block the read for ever, a device
    never ends), then the size, before anything is read: ``bound`` says whose size the limit is ("a table of rates
    may have" -> "t.csv: 300.0 MB, more than the 268.4 MB a table of rates may have"). A file that grows while it is
    read is cut at ``max_bytes + 1`` bytes and refused the same way.
    """
    from ._budget import human_bytes

    path = check_input_file(path, missing=missing, kind=kind)

    def too_big(size):
        return InputError(f"{path}: {human_bytes(size)}, more than the {human_bytes(max_bytes)} {bound}")

    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            if size > max_bytes:
                raise too_big(size)
            data = fh.read(max_bytes + 1)
    except FileNotFoundError:
        raise InputError(f"{missing} not found: {path}") from None
    except OSError as exc:
        raise InputError(f"cannot read {path}: {exc.strerror or exc}") from None
    if len(data) > max_bytes:
        raise too_big(len(data))
    return data


def check_params(params) -> NoiseParams:
    if isinstance(params, NoiseParams):
        return params
    if isinstance(params, str):
        from .params import load_preset

        return load_preset(params)
    raise ParameterError(f"params must be a NoiseParams (or a preset name), got {type(params).__name__}")


#: the largest illuminance evnoise takes (lux): 10,000 times full sunlight; far beyond, photon counts overflow
#: (1e308 lux gave overflow warnings, then NaN) — the API's limit and the CLI options' (``--max-lux``, ``--lux-scale``)
MAX_LUX = 1e9


def check_lux(lux, *, name: str = "lux", ndim: int | None = 2) -> np.ndarray:
    """A float64 illuminance array: finite, >= 0 and at most :data:`MAX_LUX` everywhere."""
    arr = real_array(lux, name)
    if ndim is not None and arr.ndim != ndim:
        raise InputError(f"{name} must be a {ndim}-D array (H, W), got shape {arr.shape}")
    if arr.size == 0:
        raise InputError(f"{name} is empty")
    if not np.isfinite(arr).all():
        raise InputError(f"{name} contains NaN or Inf values")
    if (arr < 0).any():
        raise InputError(f"{name} contains negative illuminance (min {arr.min():g} lux)")
    if (arr > MAX_LUX).any():
        raise InputError(f"{name} contains illuminance above {MAX_LUX:g} lux, 10,000 times full sunlight "
                         f"(max {arr.max():g} lux): is it in lux?")
    if ndim == 2 and (arr.shape[0] > 65536 or arr.shape[1] > 65536):
        raise InputError(f"{name} is larger than 65536 pixels on a side: {arr.shape}")
    return arr


def check_positive(value, name: str, unit: str = "") -> float:
    try:
        if isinstance(value, (bool, np.bool_)):  # float(True) is 1: a flag passed for a number
            raise TypeError
        v = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ParameterError(f"{name} must be finite and > 0{(' ' + unit) if unit else ''}, got {value!r}")
    return v


def check_float(value, name: str, unit: str, *, minimum: float = 0.0, strict: bool = True) -> float:
    """``float(value)``, finite and above ``minimum`` (``strict``) or at least ``minimum``.

    Raises ``ParameterError`` otherwise.
    """
    try:
        if isinstance(value, (bool, np.bool_)):  # float(True) is 1: a flag passed for a number
            raise TypeError
        v = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be a number ({unit}), got {value!r}") from None
    if not math.isfinite(v) or (v <= minimum if strict else v < minimum):
        raise ParameterError(f"{name} must be finite and {'>' if strict else '>='} {minimum:g} {unit}, got {value!r}")
    return v


def check_int(value, name: str, lo: int, hi: int, unit: str, *, integral_floats: bool = False) -> int:
    """``int(value)`` of an integer (not a bool) in ``lo .. hi``; ``ParameterError`` otherwise.

    A float is refused unless ``integral_floats`` (then a finite whole float such as ``1e4`` is taken:
    for durations in microseconds, which are naturally written that way).
    """
    whole_float = isinstance(value, (float, np.floating)) and math.isfinite(value) and float(value).is_integer()
    if integral_floats and whole_float:
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ParameterError(f"{name} must be an integer ({unit}), got {value!r}")
    if not lo <= int(value) <= hi:
        raise ParameterError(f"{name} must be in {lo} .. {hi} {unit}, got {value}")
    return int(value)


def duration_to_us(duration_s) -> int:
    """Duration in whole microseconds (at least 1)."""
    d = check_positive(duration_s, "duration_s", "seconds")
    us = int(round(d * 1e6))
    if us < 1:
        raise ParameterError(f"duration_s must be at least 1 microsecond, got {duration_s!r}")
    return us


def check_thresholds(thresholds, shape) -> np.ndarray:
    """Per-pixel thresholds ``(2, H, W)``: finite and > 0 (any size: a map may hold thresholds no light change
    reaches, which the kernels take, as the probability functions take any ``eps``; drawn maps can too)."""
    arr = real_array(thresholds, "thresholds")
    if arr.shape != (2, *shape):
        raise InputError(f"thresholds must have shape (2, H, W) = {(2, *shape)}, got {arr.shape}")
    if not (np.isfinite(arr).all() and (arr > 0).all()):
        raise InputError("thresholds must be finite and > 0")
    return arr


def real_array(values, name: str) -> np.ndarray:
    """``values`` as float64; a complex array (whose imaginary part NumPy's cast would drop with a warning) or one
    that is not numeric is an :class:`InputError` naming ``name``."""
    try:
        arr = np.asarray(values)
    except (TypeError, ValueError):  # a ragged nesting, or an object whose array conversion fails
        raise InputError(f"{name} must be a numeric array") from None
    if np.iscomplexobj(arr):
        raise InputError(f"{name} must be real numbers, got a complex array")
    if arr.dtype.kind in "US":
        raise InputError(f"{name} must be numbers, got text")  # NumPy's cast reads "3" as 3.0
    if arr.dtype.kind == "V":
        raise InputError(f"{name} must be numbers, got a structured array ({arr.dtype})")
    if arr.dtype.kind == "O":  # NumPy's cast reads "3" as 3.0 and None as NaN
        odd = [v for v in arr.flat if v is None or isinstance(v, (str, bytes))][:1]
        if odd:
            raise InputError(f"{name} must be numbers, got {type(odd[0]).__name__} {str(odd[0])[:40]!r}")
    try:
        return arr.astype(np.float64, copy=False)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a numeric array") from None


def path_text(path) -> str:
    """``path`` as text that can be stored (HDF5 attributes, JSON) and printed: bytes of a file name that are
    not UTF-8 (which Python keeps as surrogates) are written as ``\\xNN``."""
    return str(path).encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def check_map_shape(shape, what: str) -> tuple:
    """A shape ``(H, W)`` of whole numbers >= 1 for per-pixel maps ``(2, H, W)`` of float64 whose memory (with the
    draws' working arrays) fits the budget; any side (a ``(1, N)`` population of pixels too): ``what`` names the
    maps in the error."""
    from ._budget import check_allocation

    try:
        height, width = (int(v) for v in shape)
        whole = all(float(v) == int(v) for v in shape)
    except (TypeError, ValueError, OverflowError):
        raise ParameterError(f"shape must be (H, W), got {shape!r}") from None
    if not whole or height < 1 or width < 1:
        raise ParameterError(f"shape must be (H, W) of whole numbers >= 1, got {shape!r}")
    check_allocation(4 * 2 * 8 * height * width, f"the {what} maps of a {width}x{height} sensor",
                     error=ParameterError)
    return height, width
