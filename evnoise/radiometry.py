"""Images in, illuminance out: decoding, linearisation, luminance and the mapping to lux.

Two kinds of image reach the simulator:

*display-referred* images (8- or 16-bit PNG, JPEG, TIFF, or ``uint8``/``uint16`` arrays)
    hold encoded grey or RGB values. They are normalised to ``[0, 1]`` by the full scale
    of their bit depth, decoded to linear light (sRGB by default, IEC 61966-2-1), reduced to
    relative luminance ``Y = 0.2126 R + 0.7152 G + 0.0722 B`` (Rec. 709 / sRGB primaries) and
    mapped to illuminance by ``lux = max_lux * Y``: full-scale white gives ``max_lux``.
    The default, :data:`DEFAULT_MAX_LUX` = 18 lux, is the Noise2Image setup: the paper's
    monitor, showing grey 255, gave about 17.8 lux at the camera.
*linear* images (OpenEXR half/float, floating-point TIFF, float arrays)
    hold linear values already (relative luminance ``Y`` or linear ``R, G, B``). They are
    mapped by ``lux = lux_scale * Y`` (default ``lux_scale = 1``: the values are lux).

Invalid values (NaN, Inf, negative) are an :class:`~evnoise.InputError` that names the
file, or, with ``clip_invalid=True``, replaced (NaN and negative values by 0, ``+Inf`` by the
largest finite value of the image) with a logged warning.

Decompression bombs: every decoder's declared size is read from the file's header and checked
against one pixel limit, :data:`DEFAULT_MAX_IMAGE_PIXELS` (64 megapixels, about 3 GB of working
memory at most), *before* any pixel is decoded; ``EVNOISE_MAX_IMAGE_PIXELS`` (or ``max_pixels=``)
raises or lowers it.

Heavy libraries (Pillow, tifffile, imagecodecs, OpenEXR) are imported inside the functions;
imagecodecs is optional (``pip install 'evnoise[imagecodecs]'``): it decodes 16-bit colour PNG
and TIFF compressions other than deflate, LZMA and PackBits.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import re
import sys
import threading
from pathlib import Path

import numpy as np

from ._budget import check_allocation
from ._checks import check_input_file
from .errors import InputError, ParameterError

__all__ = [
    "DEFAULT_MAX_LUX",
    "DEFAULT_MAX_IMAGE_PIXELS",
    "max_image_pixels",
    "ENCODINGS",
    "FIT_MODES",
    "IMAGE_EXTENSIONS",
    "read_image",
    "image_to_lux",
    "lux_and_kind",
    "fit_to_sensor",
    "srgb_to_linear",
    "srgb_encode",
    "block_sum",
    "luminance",
    "natural_sort_key",
    "list_frames",
]

log = logging.getLogger(__name__)

#: Illuminance (lux) of full-scale white of a display-referred image, by default.
#: Noise2Image's monitor at grey 255 gave about 17.8 lux at the camera position.
DEFAULT_MAX_LUX = 18.0

#: Transfer functions that decode display-referred values to linear light.
ENCODINGS = ("srgb", "gamma2.2", "linear")

#: Ways to bring an image to the sensor size, see :func:`fit_to_sensor`.
FIT_MODES = ("cover", "crop", "resize")

#: Largest image (pixels) decoded unless ``EVNOISE_MAX_IMAGE_PIXELS`` or ``max_pixels=`` says otherwise:
#: 64 megapixels (8192 x 8192). Decoding works in float64 (up to ~45 bytes per pixel at the peak).
DEFAULT_MAX_IMAGE_PIXELS = 1 << 26
MAX_PIXELS_ENV = "EVNOISE_MAX_IMAGE_PIXELS"
#: channels beyond this count as extra pixels (a TIFF or EXR may declare thousands of channels)
_CHANNELS_PER_PIXEL = 4

#: File name extensions that :func:`list_frames` treats as images (case-insensitive).
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr")

#: Relative-luminance weights of linear sRGB / Rec. 709 ``R, G, B`` (IEC 61966-2-1).
REC709_LUMA = np.array([0.2126, 0.7152, 0.0722])

_EXR_MAGIC = b"\x76\x2f\x31\x01"
_TIFF_MAGICS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_PIL_LIMIT_LOCK = threading.Lock()  # held while Pillow's own bomb check is lifted (see _open_pillow)


# --------------------------------------------------------------------------------------
# transfer functions and luminance
# --------------------------------------------------------------------------------------
# The one home of the sRGB closed form (IEC 61966-2-1): ``srgb_to_linear`` decodes, ``srgb_encode``
# encodes. ``reconstruct.imaging.srgb_decode`` / ``srgb_encode`` and ``generators.pairs.linear_to_srgb``
# are these functions (colour-science is not imported: ``import evnoise`` stays light).
def srgb_encode(linear) -> np.ndarray:
    """sRGB encoding (IEC 61966-2-1 OETF) of linear values, clipped to ``[0, 1]`` (float64).

    ``12.92 V`` for ``V <= 0.0031308``, else ``1.055 V ** (1 / 2.4) - 0.055``: the inverse of
    :func:`srgb_to_linear`.

    Parameters
    ----------
    linear : array_like
        Linear light values, nominally in ``[0, 1]`` (clipped there first), any shape.

    Returns
    -------
    numpy.ndarray
        float64 array of the input's shape (0-d for a scalar), sRGB-encoded values in ``[0, 1]``.
    """
    v = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    out = np.asarray(v * 12.92)  # an array also for a scalar input
    high = v > 0.0031308
    out[high] = 1.055 * np.power(v[high], 1.0 / 2.4) - 0.055
    return out


def srgb_to_linear(values) -> np.ndarray:
    """Decode sRGB-encoded values in ``[0, 1]`` to linear light (the IEC 61966-2-1 EOTF).

    ``V / 12.92`` for ``V <= 0.04045``, else ``((V + 0.055) / 1.055) ** 2.4``; the same
    function as ``colour.models.eotf_sRGB`` (checked in the tests), without importing colour.
    Values are not clipped (``reconstruct.imaging.srgb_decode`` clips to ``[0, 1]`` first).
    """
    v = np.asarray(values, dtype=np.float64)
    low = v <= 0.04045
    out = np.empty_like(v)
    out[low] = v[low] / 12.92
    out[~low] = ((v[~low] + 0.055) / 1.055) ** 2.4
    return out


def block_sum(arr: np.ndarray, b: int, what: str = "image") -> np.ndarray:
    """Sum of ``b x b`` blocks over the last two axes; a partial last row or column is dropped.

    Raises :class:`~evnoise.InputError` (naming ``what``) when the array is smaller than one block.
    """
    h, w = arr.shape[-2] // b, arr.shape[-1] // b
    if h == 0 or w == 0:
        raise InputError(f"{what} of shape {arr.shape} is smaller than one {b}x{b} bin")
    arr = arr[..., : h * b, : w * b]
    return arr.reshape(*arr.shape[:-2], h, b, w, b).sum(axis=(-3, -1))


@functools.lru_cache(maxsize=8)
def _decode_table(bits: int, encoding: str) -> np.ndarray:
    """Linear value of every code of a ``bits``-bit display-referred image (read-only)."""
    codes = np.arange(1 << bits, dtype=np.float64) / ((1 << bits) - 1)
    if encoding == "srgb":
        table = srgb_to_linear(codes)
    elif encoding == "gamma2.2":
        table = codes**2.2
    else:
        table = codes
    table.flags.writeable = False
    return table


def _check_encoding(encoding) -> str:
    if encoding not in ENCODINGS:
        raise ParameterError(f"encoding must be one of {ENCODINGS}, got {encoding!r}")
    return encoding


def luminance(rgb, weights=REC709_LUMA) -> np.ndarray:
    """Relative luminance ``Y`` of linear ``(H, W, 3)`` RGB (Rec. 709 weights by default)."""
    rgb = np.asarray(rgb, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    return rgb[..., 0] * w[0] + rgb[..., 1] * w[1] + rgb[..., 2] * w[2]


def _luma_from_chromaticities(c) -> np.ndarray | None:
    """Luminance weights of the RGB primaries ``(xr, yr, xg, yg, xb, yb, xw, yw)``, or None where they describe no
    RGB space (a y of 0 or not finite, primaries on one line: a file's attribute is the stranger's)."""
    xr, yr, xg, yg, xb, yb, xw, yw = (float(v) for v in c)
    values = np.array([xr, yr, xg, yg, xb, yb, xw, yw])
    if not np.all(np.isfinite(values)) or not np.all(values[1::2] > 0):
        return None
    prim = np.array([[x / y, 1.0, (1.0 - x - y) / y] for x, y in ((xr, yr), (xg, yg), (xb, yb))]).T
    white = np.array([xw / yw, 1.0, (1.0 - xw - yw) / yw])
    if not np.all(np.isfinite(prim)) or np.linalg.cond(prim) > 1e12:  # primaries (nearly) on one line
        return None
    weights = np.linalg.solve(prim, white)  # scales of the primaries = their Y contributions
    return weights if np.all(np.isfinite(weights)) else None


# --------------------------------------------------------------------------------------
# decoding files
# --------------------------------------------------------------------------------------
def _describe(path) -> str:
    return os.fspath(path)


def _sniff(path: Path) -> bytes:
    check_input_file(path, missing="image", kind="an image file")
    try:
        with open(path, "rb") as fh:
            head = fh.read(32)
    except OSError as exc:
        raise InputError(f"cannot read image {_describe(path)}: {exc.strerror or exc}") from None
    if not head:
        raise InputError(f"cannot read image {_describe(path)}: the file is empty")
    return head


def max_image_pixels(max_pixels=None) -> int:
    """The pixel limit of image decoding: ``max_pixels``, else ``$EVNOISE_MAX_IMAGE_PIXELS``, else the default."""
    source = "max_pixels"
    if max_pixels is None:
        text = os.environ.get(MAX_PIXELS_ENV, "").strip()
        if not text:
            return DEFAULT_MAX_IMAGE_PIXELS
        source, max_pixels = MAX_PIXELS_ENV, text.replace("_", "")
    try:
        limit = int(max_pixels)
    except (TypeError, ValueError, OverflowError):
        limit = 0
    if limit < 1 or (not isinstance(max_pixels, str) and limit != max_pixels):
        raise ParameterError(f"{source} must be a positive whole number of pixels, got {max_pixels!r}")
    return limit


def _declared_pixels(width, height, channels: int = 1, depth: int = 1) -> int:
    """Pixels an image header declares; every 4 channels beyond the first 4 count as another image."""
    return int(width) * int(height) * max(1, int(depth)) * max(1, -(-int(channels) // _CHANNELS_PER_PIXEL))


def _check_pixels(name: str, pixels: int, size: str, limit: int) -> None:
    """Refuse an image whose header declares more than ``limit`` pixels (before anything is decoded)."""
    if pixels <= limit:
        return
    raise InputError(f"{name}: the image declares {size} ({pixels:,} pixels), more than the limit of {limit:,} "
                     f"pixels (a guard against decompression bombs); to read it, raise the limit with "
                     f"{MAX_PIXELS_ENV}=N (max_pixels=N in Python)")


def _require_imagecodecs(name: str, what: str):
    try:
        import imagecodecs
    except ImportError:
        raise InputError(f"{name}: {what} needs the imagecodecs package: pip install 'evnoise[imagecodecs]'") from None
    return imagecodecs


def load_luminance(path, encoding: str = "srgb", *, max_pixels=None):
    """``(values, kind)``: relative linear luminance (float64, H x W) and ``"display"`` or ``"linear"``.

    ``max_pixels``: see :func:`max_image_pixels`; the size is checked from the header, before decoding.
    """
    path = Path(path)
    encoding = _check_encoding(encoding)
    limit = max_image_pixels(max_pixels)
    head = _sniff(path)
    if head.startswith(_EXR_MAGIC):
        return _read_exr(path, limit), "linear"
    if head[:4] in _TIFF_MAGICS:
        raw = _read_tiff(path, limit)
    elif head.startswith(_PNG_MAGIC) and len(head) >= 24 and head[12:16] == b"IHDR" and not (
            int.from_bytes(head[16:20], "big") and int.from_bytes(head[20:24], "big")):
        # a decoder asked to read it prints its own warnings before failing
        raise InputError(f"cannot read image {_describe(path)}: its PNG header declares a "
                         f"{int.from_bytes(head[16:20], 'big')}x{int.from_bytes(head[20:24], 'big')} image (no pixels)")
    elif head.startswith(_PNG_MAGIC) and len(head) >= 26 and head[24] == 16 and head[25] in (2, 4, 6):
        raw = _read_png16(path, head, limit)  # Pillow would truncate 16-bit colour / grey+alpha PNG to 8 bits
    else:
        raw = _read_pillow(path, limit)
    return to_luminance(raw, encoding, _describe(path))


def to_luminance(raw: np.ndarray, encoding: str, name: str):
    """Luminance of a decoded ``(H, W)`` / ``(H, W, C)`` array; integer = display-referred."""
    if raw.ndim == 3 and raw.shape[2] == 1:
        raw = raw[..., 0]
    if raw.ndim == 3 and raw.shape[2] == 2:  # grey + alpha
        raw = raw[..., 0]
    if raw.ndim == 3:
        if raw.shape[2] < 3:
            raise InputError(f"{name}: unsupported channel layout {raw.shape}")
        raw = raw[..., :3]  # alpha / extra samples are ignored
    if raw.ndim not in (2, 3) or raw.shape[0] == 0 or raw.shape[1] == 0:
        raise InputError(f"{name}: expected a grey or RGB image, got an array of shape {raw.shape}")
    if raw.dtype.kind == "u" and raw.dtype.itemsize in (1, 2):
        table = _decode_table(8 * raw.dtype.itemsize, encoding)
        lin = table[raw]
        return (lin if lin.ndim == 2 else luminance(lin)), "display"
    if raw.dtype.kind == "f":
        lin = raw.astype(np.float64)
        return (lin if lin.ndim == 2 else luminance(lin)), "linear"
    raise InputError(f"{name}: unsupported pixel type {raw.dtype} (use 8/16-bit integers or floats)")


#: The raster formats Pillow may decode for evnoise, whatever a file's name says: plain pixel formats only. Pillow
#: knows others that run programs (EPS and PDF through Ghostscript) or are rarely images: a file in one of those is
#: "cannot identify image file".
PILLOW_FORMATS = ("PNG", "JPEG", "TIFF", "GIF", "BMP", "PPM", "WEBP")  # JPEG includes MPO (phones)


def _open_pillow(path: Path, limit: int):
    """``Image.open`` with evnoise's pixel limit in place of Pillow's own bomb check (header only)."""
    import warnings

    from PIL import Image

    pil_limit = Image.MAX_IMAGE_PIXELS
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # the limit below is the one that counts
        try:
            return Image.open(path, formats=PILLOW_FORMATS)
        except Image.DecompressionBombError:
            pass
        # beyond Pillow's refusal threshold: open the header without that check; the caller checks the size
        with _PIL_LIMIT_LOCK:
            Image.MAX_IMAGE_PIXELS = None
            try:
                return Image.open(path, formats=PILLOW_FORMATS)
            finally:
                Image.MAX_IMAGE_PIXELS = pil_limit


#: Most scans (start-of-scan markers) a JPEG may have: a progressive JPEG has about 10, and the decoder walks the
#: whole image once per scan, so thousands of tiny scans made a 2 MB file take minutes.
MAX_JPEG_SCANS = 1000


def _count_jpeg_scans(path: Path, stop: int) -> int:
    """Start-of-scan markers (``FF DA``) in a JPEG file, counted up to ``stop`` (no pixel is decoded).

    In entropy-coded data every ``FF`` byte is followed by ``00`` or a restart marker, so ``FF DA`` is a
    marker (an embedded thumbnail's scans count too, which is harmless against a limit of hundreds).
    """
    count, tail = 0, b""
    with open(path, "rb") as fh:
        while count < stop:
            block = fh.read(1 << 20)
            if not block:
                break
            data = tail + block
            count += data.count(b"\xff\xda")
            tail = data[-1:] if data[-1:] == b"\xff" else b""
    return count


def _check_jpeg_scans(name: str, path: Path) -> None:
    """Refuse a JPEG with more than :data:`MAX_JPEG_SCANS` scans before it is decoded."""
    scans = _count_jpeg_scans(path, MAX_JPEG_SCANS + 1)
    if scans > MAX_JPEG_SCANS:
        raise InputError(f"{name}: the JPEG has more than {MAX_JPEG_SCANS} scans (a progressive JPEG has about "
                         "10; each is a pass over the whole image, a guard against decompression bombs)")


def _read_pillow(path: Path, limit: int = DEFAULT_MAX_IMAGE_PIXELS) -> np.ndarray:
    from PIL import ImageOps

    name = _describe(path)
    try:
        with _open_pillow(path, limit) as im:
            _check_pixels(name, _declared_pixels(im.width, im.height), f"{im.width}x{im.height}", limit)
            if im.format in ("JPEG", "MPO"):
                _check_jpeg_scans(name, path)
            im.load()
            im = ImageOps.exif_transpose(im)
            if "icc_profile" in im.info:
                log.info("%s has an embedded ICC profile; it is ignored (values are decoded as `encoding`)", name)
            mode = im.mode
            if mode in ("1", "LA", "La", "P", "PA"):
                im = im.convert("RGBA" if mode.startswith("P") else "L")
            elif mode in ("CMYK", "YCbCr", "LAB", "HSV"):
                im = im.convert("RGB")
            arr = np.asarray(im)
            mode = im.mode
    except InputError:
        raise
    except Exception as exc:  # Pillow raises many types for corrupt or unknown files
        raise InputError(f"cannot read image {name}: {exc}") from None
    if mode.startswith("I;16"):
        return arr.astype(np.uint16)
    if mode == "I":
        if arr.size and (arr.min() < 0 or arr.max() > 65535):
            raise InputError(f"{name}: 32-bit integer image with values outside 0 .. 65535 is not supported")
        return arr.astype(np.uint16)
    if mode == "F":
        return arr.astype(np.float32)
    if arr.dtype != np.uint8:
        raise InputError(f"{name}: unsupported image mode {mode!r}")
    return arr


def _read_png16(path: Path, head: bytes, limit: int = DEFAULT_MAX_IMAGE_PIXELS) -> np.ndarray:
    name = _describe(path)
    if head[12:16] != b"IHDR":
        raise InputError(f"cannot read image {name}: the PNG does not start with its IHDR header")
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    _check_pixels(name, _declared_pixels(width, height), f"{width}x{height}", limit)
    imagecodecs = _require_imagecodecs(name, "a 16-bit colour or grey+alpha PNG")
    try:
        arr = imagecodecs.png_decode(path.read_bytes())
    except Exception as exc:
        raise InputError(f"cannot read image {_describe(path)}: {exc}") from None
    return np.asarray(arr)


def _check_tiles(name: str, page, limit: int) -> None:
    """Refuse a tiled TIFF page whose tiles declare more than ``limit`` pixels or the memory budget (header only)."""
    from ._budget import check_allocation

    depth = max(1, int(page.tiledepth))
    tile = f"{page.tilewidth}x{page.tilelength}" + (f"x{depth}" if depth > 1 else "")
    _check_pixels(name, _declared_pixels(page.tilewidth, page.tilelength, page.samplesperpixel, depth),
                  f"tiles of {tile}", limit)
    nbytes = int(page.tilewidth) * int(page.tilelength) * depth * max(1, int(page.samplesperpixel))
    check_allocation(nbytes * page.dtype.itemsize, f"{name}: decoding one of its {tile} tiles")


def _read_tiff(path: Path, limit: int = DEFAULT_MAX_IMAGE_PIXELS) -> np.ndarray:
    import tifffile

    name = _describe(path)
    ph = tifffile.PHOTOMETRIC
    try:
        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]  # the header (tags) only; pixels are decoded by asarray
            size = f"{page.imagewidth}x{page.imagelength}" + (f"x{page.imagedepth}" if page.imagedepth > 1 else "")
            if page.samplesperpixel > _CHANNELS_PER_PIXEL:
                size += f" with {page.samplesperpixel} samples"
            _check_pixels(name, _declared_pixels(page.imagewidth, page.imagelength, page.samplesperpixel,
                                                 page.imagedepth), size, limit)
            if page.is_tiled:  # a tile is decoded whole, whatever the image size: 16x16 pixels in one 48k x 48k tile
                _check_tiles(name, page, limit)
            photometric = page.photometric
            if photometric not in (ph.MINISBLACK, ph.MINISWHITE, ph.RGB):
                return _read_pillow(path, limit)  # palette, CMYK, YCbCr: let Pillow convert
            axes = page.axes
            if page.imagedepth > 1 or axes not in ("YX", "YXS", "SYX"):
                raise InputError(f"{name}: a TIFF whose first image has axes {axes!r} ({size}); expected a 2-D "
                                 "image (YX), with samples per pixel (YXS or SYX)")
            arr = page.asarray()
    except InputError:
        raise
    except Exception as exc:
        if "imagecodecs" in str(exc):  # a compression tifffile cannot decode on its own (LZW, JPEG, ...)
            _require_imagecodecs(name, f"this TIFF ({exc})")
        raise InputError(f"cannot read image {name}: {exc}") from None
    if axes.startswith("S") and arr.ndim == 3:
        arr = np.moveaxis(arr, 0, -1)  # planar configuration: samples first
    if arr.dtype == np.bool_:  # a 1-bit (bilevel) TIFF: black and full-scale white, as Pillow gives a 1-bit PNG
        arr = np.where(arr, np.uint8(255), np.uint8(0))
    if photometric == ph.MINISWHITE and arr.dtype.kind == "u":
        arr = np.iinfo(arr.dtype).max - arr
    if arr.dtype.kind == "f" and arr.dtype.itemsize < 4:
        arr = arr.astype(np.float32)
    return arr


_C_OUTPUT_LOCK = threading.Lock()  # the standard streams are the process's: one capture at a time


@contextlib.contextmanager
def _c_library_output():
    """Capture what a C library writes to the standard output and error (file descriptors 1 and 2) meanwhile;
    yields a list that holds the text afterwards. OpenEXR's C core prints its errors on a damaged file there, and
    its Python module a "Warning:" line, before raising an exception of its own."""
    import ctypes
    import io
    import tempfile

    python_text = io.StringIO()  # the Python module's own lines go through sys.stdout
    with _C_OUTPUT_LOCK, tempfile.TemporaryFile() as tmp:
        sys.stdout.flush()
        sys.stderr.flush()
        saved = (os.dup(1), os.dup(2))
        text = []
        try:
            os.dup2(tmp.fileno(), 1)
            os.dup2(tmp.fileno(), 2)
            with contextlib.redirect_stdout(python_text), contextlib.redirect_stderr(python_text):
                yield text
        finally:
            try:
                ctypes.CDLL(None).fflush(None)  # C's buffered streams (C++'s iostreams write through them)
            except (OSError, AttributeError):  # pragma: no cover - no C library to call
                pass
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
            tmp.seek(0)
            text.append(tmp.read().decode("utf-8", "replace") + python_text.getvalue())


def _exr_failure(name: str, exc: Exception | None, printed: str) -> InputError:
    """The error of an EXR that OpenEXR could not read: its own first printed complaint (the cause), else ``exc``."""
    lines = [line.strip() for line in printed.splitlines() if line.strip()]
    cause = next((line for line in lines if "EXR_ERR" in line or "corrupt" in line.lower()), None)
    if cause is not None:
        cause = re.sub(r"^.*?\(EXR_ERR_\w+\)\s*", "", cause)  # "FILE: (EXR_ERR_CODE) text" -> "text"
        return InputError(f"cannot read OpenEXR image {name}: a damaged or truncated file (OpenEXR: {cause[:200]})")
    return InputError(f"cannot read OpenEXR image {name}: {exc or (lines[0][:200] if lines else 'unreadable')}")


def _echo(printed: str) -> None:
    """Give back what was captured around a read that worked (it was not the reader's: a progress bar's, say)."""
    if printed:
        sys.stderr.write(printed)


def _read_exr(path: Path, limit: int = DEFAULT_MAX_IMAGE_PIXELS) -> np.ndarray:
    import OpenEXR

    name = _describe(path)
    error = None
    with _c_library_output() as printed:
        try:
            with OpenEXR.File(os.fspath(path), header_only=True) as exr:
                sizes = []
                for part in exr.parts:
                    header = part.header
                    (x0, y0), (x1, y1) = (np.asarray(c, dtype=np.int64) for c in header["dataWindow"])
                    sizes.append((int(x1) - int(x0) + 1, int(y1) - int(y0) + 1, len(header.get("channels", ()))))
        except Exception as exc:
            error = exc
    if error is not None or not sizes:
        raise _exr_failure(name, error, printed[0])
    _echo(printed[0])
    if any(w < 1 or h < 1 for w, h, _ in sizes):
        raise InputError(f"{name}: EXR declares an empty data window {sizes}")
    # all parts are decoded: they count together
    size = " + ".join(f"{w}x{h}" + (f" with {c} channels" if c > _CHANNELS_PER_PIXEL else "") for w, h, c in sizes)
    _check_pixels(name, sum(_declared_pixels(w, h, c) for w, h, c in sizes), size, limit)
    with _c_library_output() as printed:
        try:
            with OpenEXR.File(os.fspath(path), separate_channels=True) as exr:
                # the header is emptied on close: copy what is needed of every part
                parts = [(part.header.get("chromaticities"),
                          {k: np.asarray(v.pixels) for k, v in part.channels.items()}) for part in exr.parts]
        except Exception as exc:
            error = exc
    if error is not None or not parts:  # a truncated file can decode to no part without an exception
        raise _exr_failure(name, error, printed[0])
    _echo(printed[0])
    # a multipart file (a depth or a mask part beside the image): the first part holding an image
    usable = [k for k, (_, ch) in enumerate(parts) if "Y" in ch or all(c in ch for c in "RGB")]
    if len(parts) > 1 and not usable:
        raise InputError(f"{name}: no part of this {len(parts)}-part EXR has channels 'Y' or 'R', 'G', 'B' "
                         f"(parts: {'; '.join(', '.join(sorted(ch)) for _, ch in parts)})")
    k = usable[0] if usable else 0
    if k > 0:
        log.info("%s: read part %d of %d, the first with a 'Y' or 'R', 'G', 'B' image", name, k, len(parts))
    chroma, channels = parts[k]
    for key, arr in channels.items():
        if arr.dtype.kind != "f":
            raise InputError(f"{name}: EXR channel {key!r} has pixel type {arr.dtype}; expected half or float")
    if "Y" in channels:
        return channels["Y"].astype(np.float64)
    if all(c in channels for c in "RGB"):
        shapes = {channels[c].shape for c in "RGB"}
        if len(shapes) != 1:
            raise InputError(f"{name}: EXR channels R, G, B have different sizes {sorted(shapes)}")
        weights = REC709_LUMA
        if chroma is not None:
            weights = _luma_from_chromaticities(chroma)
            if weights is None:
                raise InputError(f"{name}: its chromaticities attribute {tuple(float(v) for v in chroma)} does not "
                                 "describe RGB primaries and a white point (each y > 0, the primaries independent)")
        rgb = np.stack([channels[c].astype(np.float64) for c in "RGB"], axis=-1)
        return luminance(rgb, weights)
    raise InputError(f"{name}: EXR has channels {sorted(channels)}; expected 'Y' or 'R', 'G', 'B'")


# --------------------------------------------------------------------------------------
# invalid values
# --------------------------------------------------------------------------------------
def handle_invalid(values: np.ndarray, name: str, clip_invalid: bool) -> np.ndarray:
    """``values`` with NaN / infinite / negative pixels refused (``InputError``) or, with ``clip_invalid``, clipped."""
    nan = np.isnan(values)
    inf = np.isinf(values)
    neg = values < 0  # -inf counts as negative too
    n_nan, n_inf, n_neg = int(nan.sum()), int(inf.sum()), int((neg & ~inf).sum())
    if not (n_nan or n_inf or n_neg):
        return values
    what = ", ".join(f"{n} {label}" for n, label in ((n_nan, "NaN"), (n_inf, "infinite"), (n_neg, "negative"))
                     if n)
    if not clip_invalid:
        raise InputError(f"{name} has invalid pixel values ({what}); fix the image or clip them "
                         f"(clip_invalid=True)")
    finite = values[np.isfinite(values)]
    top = float(finite.max()) if finite.size else 0.0
    out = values.copy()
    out[nan | neg] = 0.0
    out[np.isposinf(values)] = max(top, 0.0)
    log.warning("%s: clipped %s pixel values (NaN and negative to 0, +Inf to the largest finite value)",
                name, what)
    return out


# --------------------------------------------------------------------------------------
# public functions
# --------------------------------------------------------------------------------------
def read_image(path, *, encoding: str = "srgb", clip_invalid: bool = False, max_pixels=None) -> np.ndarray:
    """Read an image file as relative *linear* luminance.

    Parameters
    ----------
    path : str or os.PathLike
        PNG, JPEG, TIFF (1/8/16-bit integer or floating point; grey or RGB; alpha is ignored)
        or OpenEXR (half/float; a ``Y`` channel, or ``R``, ``G``, ``B``; of a multipart file, the
        first part holding them). The format is
        detected from the file's content, not its name.
    encoding : {"srgb", "gamma2.2", "linear"}
        Transfer function of integer (display-referred) images; floating-point images
        and EXR are linear and not decoded.
    clip_invalid : bool
        Replace NaN and negative values by 0 and ``+Inf`` by the largest finite value (with a
        logged warning) instead of raising.
    max_pixels : int, optional
        Largest image decoded, in pixels, checked from the file's header before decoding
        (default ``$EVNOISE_MAX_IMAGE_PIXELS`` or :data:`DEFAULT_MAX_IMAGE_PIXELS`, 64 megapixels).

    Returns
    -------
    numpy.ndarray
        float64 ``(H, W)``: ``Y`` in ``[0, 1]`` for integer images (1 = full-scale white);
        the stored linear luminance for floating-point images and EXR.

    Raises
    ------
    InputError
        Missing, unreadable or corrupt file; unsupported layout; NaN, Inf or negative values
        (unless ``clip_invalid``); more pixels than ``max_pixels``.
    """
    values, _ = load_luminance(path, encoding, max_pixels=max_pixels)
    return handle_invalid(values, _describe(path), clip_invalid)


def image_to_lux(
    path_or_array,
    *,
    max_lux: float | None = None,
    lux_scale: float | None = None,
    encoding: str = "srgb",
    clip_invalid: bool = False,
    sensor_shape=None,
    fit: str = "cover",
    name: str | None = None,
    max_pixels=None,
) -> np.ndarray:
    """Illuminance at the sensor, in lux, of an image file or array.

    Parameters
    ----------
    path_or_array : str, os.PathLike or array_like
        An image file (see :func:`read_image`) or an array ``(H, W)`` / ``(H, W, 3)``:
        ``uint8`` / ``uint16`` arrays are display-referred (encoded by ``encoding``, full
        scale 255 / 65535), floating-point arrays are linear values.
    max_lux : float, optional
        Illuminance in lux of full-scale white of a display-referred image:
        ``lux = max_lux * Y`` (default :data:`DEFAULT_MAX_LUX` = 18 lux, the Noise2Image
        monitor at grey 255). Not valid for linear images.
    lux_scale : float, optional
        Lux per unit of a linear image (EXR, float TIFF, float array): ``lux = lux_scale * Y``
        (default 1: the values are lux). Not valid for display-referred images.
    encoding : {"srgb", "gamma2.2", "linear"}
        Transfer function of display-referred values (default sRGB).
    clip_invalid : bool
        Clip NaN, Inf and negative values with a logged warning instead of raising.
    sensor_shape : (H, W), optional
        Bring the image to this sensor size with :func:`fit_to_sensor` (on linear values).
    fit : {"cover", "crop", "resize"}
        How to fit the sensor size (see :func:`fit_to_sensor`).
    name : str, optional
        Label of an array input in error messages (default ``"image"``).
    max_pixels : int, optional
        Largest image file decoded, in pixels (see :func:`read_image`).

    Returns
    -------
    numpy.ndarray
        float64 ``(H, W)`` illuminance in lux, finite and ``>= 0``.
    """
    return lux_and_kind(path_or_array, max_lux=max_lux, lux_scale=lux_scale, encoding=encoding,
                        clip_invalid=clip_invalid, sensor_shape=sensor_shape, fit=fit, name=name,
                        max_pixels=max_pixels)[0]


def lux_and_kind(path_or_array, *, max_lux=None, lux_scale=None, encoding="srgb", clip_invalid=False,
                 sensor_shape=None, fit="cover", name=None, max_pixels=None) -> tuple[np.ndarray, str]:
    """:func:`image_to_lux` (same arguments) and the kind of image it read: ``"display"`` (8/16-bit,
    scaled by ``max_lux``) or ``"linear"`` (EXR / floating point, scaled by ``lux_scale``). A video's
    frames must all be of one kind: their illuminance scales differ."""
    encoding = _check_encoding(encoding)
    if isinstance(path_or_array, (str, os.PathLike)):
        label = name or _describe(path_or_array)
        values, kind = load_luminance(path_or_array, encoding, max_pixels=max_pixels)
    else:
        label = name or "image"
        values, kind = _array_luminance(path_or_array, encoding, label)
    if kind == "display":
        if lux_scale is not None:
            raise ParameterError(f"lux_scale applies to linear (EXR / floating-point) images, but {label} is "
                                 f"an 8/16-bit display-referred image; use max_lux")
        scale = DEFAULT_MAX_LUX if max_lux is None else _positive(max_lux, "max_lux", "lux")
    else:
        if max_lux is not None:
            raise ParameterError(f"max_lux applies to 8/16-bit display-referred images, but {label} is a "
                                 f"linear (EXR / floating-point) image; use lux_scale")
        scale = 1.0 if lux_scale is None else _positive(lux_scale, "lux_scale", "lux per unit")
    values = handle_invalid(values, label, clip_invalid)
    if sensor_shape is not None:
        values = fit_to_sensor(values, sensor_shape, mode=fit)
    with np.errstate(over="ignore"):
        lux = values * scale
    if not np.isfinite(lux).all():
        raise InputError(f"{label}: illuminance overflows float64 after scaling by {scale:g}")
    return lux, kind


def _positive(value, name: str, unit: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be a number ({unit}), got {value!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise ParameterError(f"{name} must be finite and > 0 ({unit}), got {value!r}")
    return v


def _array_luminance(arr, encoding: str, label: str):
    try:
        arr = np.asarray(arr)
    except Exception:
        raise InputError(f"{label} must be an image array (H, W) or (H, W, 3)") from None
    if arr.dtype == np.bool_ or arr.dtype.kind not in "uif":
        raise InputError(f"{label} must be a numeric image array, got dtype {arr.dtype}")
    if arr.dtype.kind in "iu" and arr.dtype not in (np.uint8, np.uint16):
        raise InputError(f"integer {label} must be uint8 or uint16 (display-referred), got {arr.dtype}; "
                         f"pass floating-point values for linear input")
    if not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[2] in (1, 3, 4))):
        raise InputError(f"{label} must have shape (H, W) or (H, W, 3), got {arr.shape}")
    return to_luminance(arr, encoding, label)


def fit_to_sensor(image, shape, mode: str = "cover") -> np.ndarray:
    """Bring a 2-D image (linear values) to the sensor size ``shape = (H, W)``.

    Parameters
    ----------
    image : array_like, shape (h, w)
        Linear values (luminance or lux); resampling happens on linear values.
    shape : (H, W)
        Sensor size in pixels (rows, columns).
    mode : {"cover", "crop", "resize"}
        ``"cover"``: scale, keeping the aspect ratio, until the image covers the sensor,
        then crop the centre. ``"crop"``: crop the centre at the image's own resolution
        (the image must be at least ``H x W``). ``"resize"``: resample to exactly ``H x W``
        (the aspect ratio may change). Resampling uses Pillow's bilinear (triangle) filter,
        widened when shrinking, so it averages instead of aliasing and never makes
        negative values.

    Returns
    -------
    numpy.ndarray
        float64 ``(H, W)``.
    """
    from .events import check_shape

    if mode not in FIT_MODES:
        raise ParameterError(f"fit mode must be one of {FIT_MODES}, got {mode!r}")
    height, width = check_shape(shape)
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2 or img.size == 0:
        raise InputError(f"fit_to_sensor needs a non-empty 2-D image, got shape {img.shape}")
    # the float32 resampling planes and the float64 result, and a simulation's own per-pixel state after it
    check_allocation(24.0 * height * width, f"an image brought to a {width}x{height} sensor",
                     hint="choose a smaller sensor (sensor_shape) or raise EVNOISE_MAX_MEMORY", error=ParameterError)
    h, w = img.shape
    if (h, w) == (height, width):
        return img
    if mode == "crop":
        if h < height or w < width:
            raise InputError(f"cannot crop a {w}x{h} image to a {width}x{height} sensor (the image is "
                             f"smaller); use fit mode 'cover' or 'resize'")
        return _centre_crop(img, height, width)
    if mode == "resize":
        return _resample(img, height, width)
    scale = max(height / h, width / w)
    new_h = max(height, round(h * scale))
    new_w = max(width, round(w * scale))
    return _centre_crop(_resample(img, new_h, new_w), height, width)


def _centre_crop(img, height, width):
    top = (img.shape[0] - height) // 2
    left = (img.shape[1] - width) // 2
    return np.ascontiguousarray(img[top:top + height, left:left + width])


def _resample(img, height, width):
    if img.shape == (height, width):
        return img
    from PIL import Image

    peak = float(np.abs(img).max())
    norm = peak if peak > 0 else 1.0
    # normalised, so that float32 keeps full relative precision whatever the units
    pil = Image.fromarray((img / norm).astype(np.float32))  # mode "F"
    out = np.asarray(pil.resize((width, height), resample=Image.Resampling.BILINEAR), dtype=np.float64)
    out *= norm
    if img.min() >= 0:
        np.maximum(out, 0.0, out=out)  # the filter's weights are >= 0; guard against rounding
    return out


# --------------------------------------------------------------------------------------
# frame folders
# --------------------------------------------------------------------------------------
_DIGITS = re.compile(r"(\d+)")


def natural_sort_key(name) -> tuple:
    """Sort key that orders ``frame2`` before ``frame10`` (digit runs compare as numbers).

    Case-insensitive; ties between equal keys (``f01`` and ``f1``) break on the plain name.
    """
    text = os.fspath(name)
    text = os.path.basename(text) or text
    parts = _DIGITS.split(text.casefold())
    key = tuple(int(p) if i % 2 else p for i, p in enumerate(parts))
    return key, text


def list_frames(folder, extensions=IMAGE_EXTENSIONS) -> list[Path]:
    """Image files of a folder (not hidden, known extension), sorted naturally by file name.

    Raises
    ------
    InputError
        The folder does not exist, is not a folder, cannot be listed, or holds no image file.
    """
    folder = Path(folder)
    if not folder.exists():
        raise InputError(f"folder not found: {_describe(folder)}")
    if not folder.is_dir():
        raise InputError(f"not a folder: {_describe(folder)}")
    exts = tuple(e.lower() for e in extensions)
    try:
        files = [p for p in folder.iterdir() if not p.name.startswith(".") and p.suffix.lower() in exts]
        # a frame's name that is not a regular file (a folder, a pipe, a link to a device) would drop that frame
        # and move every later one earlier in time: an error, not a skip
        odd = [p for p in files if not p.is_file()]
    except OSError as exc:
        raise InputError(f"cannot list folder {_describe(folder)}: {exc.strerror or exc}") from None
    if odd:
        first = odd[0]
        kind = "a folder" if first.is_dir() else "not a regular file (a pipe, socket, device or broken link)"
        raise InputError(f"{_describe(first)} is named like a frame but is {kind}"
                         + (f" ({len(odd) - 1} more like it)" if len(odd) > 1 else ""))
    if not files:
        raise InputError(f"folder {_describe(folder)} holds no image files ({', '.join(exts)})")
    return sorted(files, key=lambda p: natural_sort_key(p.name))

