"""HDF5 shards of pairs: layout, an atomic writer, checksums.

One shard file (``shards/<split>-<index>.h5``) holds ``n`` pairs::

    /counts         uint16  (n, 2, h, w)   [ON, OFF] noise-event counts, binned
    /image          float32 (m, h, w)      display-encoded (sRGB) images in [0, 1], one per crop
    /image_index    int32   (n,)           row of /image that belongs to each pair (the windows
                                           of one crop share their image)
    /source         str     (n,)           item id of the source image
    /crop_index     int32   (n,)           index of the crop within its source
    /crop_box       int32   (n, 4)         top, left, height, width in fitted-sensor pixels
    /window_s       float64 (n,)           integration window, seconds
    /window_us      int64   (n,)           the same in whole microseconds (as simulated)
    /lux_scale      float64 (n,)           lux of image value 1 (the display white)
    /max_lux        float64 (n,)           lux of the source's full-scale white for this crop
    /contrast_gamma float64 (n,)           contrast exponent applied to the source's luminance
    /seed           uint64  (n,)           the pair's noise seed
    /saturated      int32   (n,)           count bins that saturated at 65535
    root attributes: format = "evnoise-pairs", format_version, evnoise_version, split, shard,
                     binning, counts_order = "ON,OFF", image_encoding = "srgb", params (JSON)

``counts`` and ``image`` are chunked one item per chunk (random access costs one chunk read),
compressed with the configured filter plus shuffle. LZF chunks are encoded here
(:func:`lzf_chunk`, written with ``write_direct_chunk``): the LZF encoder inside h5py leaves its
hash table uninitialised, so its output depended on leftovers in memory and two identical runs
wrote different bytes now and then; h5py's LZF filter decodes these chunks as any other.
Pairs are ordered by source (in the shard's listing order), then crop, then window. The
writer writes to a temporary name and renames on success; the bytes depend only on the pairs
(no timestamps), so a shard is bit-identical whoever writes it.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from evnoise._atomic import AtomicFile, close_h5_discarding, os_error_text
from evnoise.errors import InputError, OutputError

__all__ = ["FORMAT", "FORMAT_VERSION", "ShardWriter", "file_sha256", "META_COLUMNS", "read_meta", "lzf_chunk"]

FORMAT = "evnoise-pairs"
FORMAT_VERSION = 1
GZIP_LEVEL = 1

#: What h5py raises when a write fails (a full disk): OSError, or RuntimeError from a flush or a close whose text
#: names the errno ("file write failed: ..., errno = 28, ...", over two lines).
_WRITE_ERRORS = (OSError, RuntimeError)

#: Per-pair metadata columns: name -> dtype (``str`` for variable-length UTF-8).
META_COLUMNS = {
    "source": str,
    "crop_index": np.int32,
    "window_s": np.float64,
    "window_us": np.int64,
    "lux_scale": np.float64,
    "max_lux": np.float64,
    "contrast_gamma": np.float64,
    "seed": np.uint64,
    "saturated": np.int32,
    "image_index": np.int32,
}


def file_sha256(path, block: int = 1 << 22) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while True:
            chunk = fh.read(block)
            if not chunk:
                break
            h.update(chunk)
    return h.hexdigest()


#: HDF5's number of the LZF filter (h5py's)
LZF_FILTER = 32000


def lzf_chunk(data: np.ndarray) -> tuple:
    """``(bytes, skipped)``: one chunk ``data`` as HDF5's shuffle + LZF pipeline stores it, deterministically.

    The bytes are shuffled (byte ``j`` of every element together, as HDF5's shuffle filter does) and
    LZF-compressed by :func:`~._kernels.lzf_compress`, whose output depends only on ``data``.
    ``skipped`` is true when compression does not make the chunk smaller: then the shuffled bytes are
    stored as they are, with the LZF filter marked as skipped (what HDF5 does for an optional filter
    that fails, as h5py's LZF filter does on such a chunk).
    """
    from ._kernels import lzf_compress

    flat = np.ascontiguousarray(data).reshape(-1)
    size = flat.dtype.itemsize
    shuffled = flat.view(np.uint8).reshape(-1, size).T.reshape(-1) if size > 1 else flat.view(np.uint8)
    shuffled = np.ascontiguousarray(shuffled)
    out = np.empty(shuffled.size, dtype=np.uint8)
    n = int(lzf_compress(shuffled, out)) if shuffled.size else 0
    if n == 0:
        return shuffled.tobytes(), True
    return out[:n].tobytes(), False


class ShardWriter:
    """Write one shard, pair by pair; atomic (temporary file renamed by :meth:`close`).

    Parameters
    ----------
    path : pathlib.Path
        Final file name (replaced if it exists: shards are regenerated on resume).
    pair_shape : (h, w)
        Size of a pair after binning.
    compression : {"gzip", "lzf", None}
        Filter of ``counts`` and ``image``.
    attrs : dict
        Root attributes (strings and numbers; dicts are stored as JSON).
    """

    def __init__(self, path, pair_shape, compression, attrs: dict):
        import h5py

        self.path = Path(path)
        self.h, self.w = (int(s) for s in pair_shape)
        self._out = AtomicFile(self.path, overwrite=True, what="shard")
        self._tmp = self._out.tmp
        self.n = 0
        self.n_images = 0
        self._meta = {k: [] for k in META_COLUMNS}
        self._boxes = []
        self._closed = False
        self._held = []  # datasets made by close(): kept open until the file is closed or discarded
        try:
            self._file = h5py.File(self._tmp, "w-", libver="earliest")
        except OSError as exc:  # h5py's text spans two lines and names the temporary file
            self._out.discard()
            raise OutputError(f"cannot write shard {self.path}: {os_error_text(exc)}") from None
        try:
            f = self._file
            f.attrs["format"] = FORMAT
            f.attrs["format_version"] = np.int64(FORMAT_VERSION)
            for key, value in attrs.items():
                f.attrs[key] = json.dumps(value, sort_keys=True) if isinstance(value, (dict, list)) else value
            filt = {} if compression is None else {"compression": compression, "shuffle": True}
            if compression == "gzip":
                filt["compression_opts"] = GZIP_LEVEL
            self._counts = f.create_dataset("counts", shape=(0, 2, self.h, self.w), maxshape=(None, 2, self.h, self.w),
                                            dtype=np.uint16, chunks=(1, 2, self.h, self.w), **filt)
            self._image = f.create_dataset("image", shape=(0, self.h, self.w), maxshape=(None, self.h, self.w),
                                           dtype=np.float32, chunks=(1, self.h, self.w), **filt)
            self._lzf_mask = None  # with LZF: the filter-mask bit that marks LZF as skipped in a chunk
            if compression == "lzf":
                dcpl = self._counts.id.get_create_plist()
                order = [dcpl.get_filter(k)[0] for k in range(dcpl.get_nfilters())]
                self._lzf_mask = 1 << order.index(LZF_FILTER)
        except _WRITE_ERRORS as exc:
            self.abort()
            raise OutputError(f"cannot write shard {self.path}: {os_error_text(exc)}") from None
        except BaseException:
            self.abort()
            raise

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None:
            self.abort()
        return False

    def _put(self, ds, row: int, value) -> None:
        """Store ``value`` as row ``row`` (one whole chunk) of ``ds``; LZF chunks are encoded by :func:`lzf_chunk`."""
        if self._lzf_mask is None:
            ds[row] = value
            return
        value = np.asarray(value, dtype=ds.dtype)
        if value.shape != ds.chunks[1:]:
            raise ValueError(f"a row of {ds.name} has shape {ds.chunks[1:]}, got {value.shape}")
        data, skipped = lzf_chunk(value)
        ds.id.write_direct_chunk((row,) + (0,) * value.ndim, data, self._lzf_mask if skipped else 0)

    def add_image(self, image: np.ndarray) -> int:
        """Store an image (float32 (h, w)); returns its row, to pass as ``image_index`` to :meth:`append`."""
        m = self.n_images
        try:
            self._image.resize((m + 1, self.h, self.w))
            self._put(self._image, m, image)
        except _WRITE_ERRORS as exc:
            self.abort()
            raise OutputError(f"writing shard {self.path} failed: {os_error_text(exc)}") from None
        self.n_images = m + 1
        return m

    def append(self, counts: np.ndarray, crop_box, **meta) -> None:
        """Add one pair: ``counts`` uint16 (2, h, w), its crop box and metadata (``image_index`` included)."""
        if not 0 <= int(meta["image_index"]) < self.n_images:
            raise OutputError(f"image_index {meta['image_index']} does not name a stored image")
        i = self.n
        try:
            self._counts.resize((i + 1, 2, self.h, self.w))
            self._put(self._counts, i, counts)
        except _WRITE_ERRORS as exc:
            self.abort()
            raise OutputError(f"writing shard {self.path} failed: {os_error_text(exc)}") from None
        for key in META_COLUMNS:
            self._meta[key].append(meta[key])
        self._boxes.append(tuple(int(v) for v in crop_box))
        self.n = i + 1

    def close(self) -> Path:
        """Write the metadata columns, close, and rename to the final name."""
        import h5py

        if self._closed:
            return self.path

        def close():
            # each dataset is held (not closed one by one): on a full disk the close of one fails inside h5py's
            # deallocation, where the error is lost and the file was left broken (the discarding close crashed)
            f, held = self._file, self._held
            for key, dtype in META_COLUMNS.items():
                values = self._meta[key]
                if dtype is str:
                    data = np.array(values, dtype=object) if values else np.zeros(0, dtype=object)
                    held.append(f.create_dataset(key, data=data, dtype=h5py.string_dtype()))
                else:
                    held.append(f.create_dataset(key, data=np.asarray(values, dtype=dtype).reshape(len(values))))
            held.append(f.create_dataset("crop_box",
                                         data=np.asarray(self._boxes, dtype=np.int32).reshape(len(self._boxes), 4)))
            f.flush()  # a failure (a full disk) leaves the file open for abort() to discard cleanly
            held.clear()
            f.close()

        self._out.finish(close, self.abort, catch=_WRITE_ERRORS, one_line=True)
        self._closed = True
        return self.path

    def abort(self) -> None:
        self._closed = True
        file, self._file = getattr(self, "_file", None), None
        if file is not None:  # a full disk: a failed close crashed the process at exit (close_h5_discarding)
            close_h5_discarding(file, self._out, [getattr(self, "_counts", None), getattr(self, "_image", None)])
        getattr(self, "_held", []).clear()  # their file is closed: releasing them writes nothing
        self._out.discard()


def read_meta(f, path) -> dict:
    """All metadata columns of an open shard as NumPy arrays (``source`` as a list of str)."""
    out = {}
    try:
        n = f["counts"].shape[0]
        for key in META_COLUMNS:
            ds = f[key]
            if ds.ndim < 1 or ds.shape[0] != n:  # checked before reading: a declared length is not memory to take
                raise InputError(f"{path}: column {key!r} has shape {ds.shape} for {n} pairs")
            if key == "source":
                out[key] = [s.decode("utf-8") if isinstance(s, bytes) else str(s) for s in ds[()]]
            else:
                out[key] = np.asarray(ds[()])
        out["crop_box"] = np.asarray(f["crop_box"][()])
    except (KeyError, OSError) as exc:
        raise InputError(f"{path} is not a complete evnoise pairs shard: {exc}") from None
    for key, value in out.items():
        if len(value) != n:
            raise InputError(f"{path}: column {key!r} has {len(value)} entries for {n} pairs")
    m = f["image"].shape[0]
    if n and (out["image_index"].min() < 0 or out["image_index"].max() >= m):
        raise InputError(f"{path}: image_index points outside the {m} stored images")
    return out
