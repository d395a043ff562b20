"""gzip + shuffle of HDF5 chunks in threads, written in order with ``write_direct_chunk`` (internal).

HDF5 runs a dataset's filters (shuffle, then deflate) in the writing thread, one chunk after the
other, and h5py holds a global lock while it does: the compression of ``events.h5`` was two
thirds of ``evnoise simulate``'s time. Here every whole chunk of a field is shuffled and
deflated by a thread pool (``zlib`` releases the GIL) and the compressed bytes are handed to
HDF5 as they are, in order, with the same filter pipeline declared on the dataset: a reader
decodes them like any other chunk (plain h5py, DSEC's tools, evlib). The last, partial chunk
is padded with zeros, as HDF5 stores edge chunks, and the dataset's extent cut to the events.

The byte shuffle is HDF5's: byte ``j`` of every element, for ``j = 0 .. itemsize - 1`` in turn
(no-op for one-byte elements); deflate is zlib's format (``compress2``), as HDF5's filter writes.
"""

from __future__ import annotations

import zlib
from collections import deque
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ._pool import hand_over, take


def shuffle_deflate(values: np.ndarray, level: int) -> bytes:
    """One chunk's bytes as HDF5's shuffle + deflate filters store them."""
    raw = np.ascontiguousarray(values)
    size = raw.dtype.itemsize
    if size > 1:
        raw = raw.view(np.uint8).reshape(-1, size).T.copy()  # byte j of every element, j = 0, 1, ...
    return zlib.compress(raw.tobytes(), level)


class ParallelGzipChunks:
    """Append arrays to chunked, gzip + shuffle datasets through a thread pool (see the module doc).

    Parameters
    ----------
    datasets : dict
        ``{name: h5py.Dataset}``, 1-D, resizable, chunked by ``chunk`` elements, created with
        ``compression="gzip", shuffle=True``.
    chunk : int
        Elements per chunk.
    level : int
        Deflate level (the dataset's ``compression_opts``).
    threads : int
        Worker threads; at most ``4 * threads`` chunks are in flight (memory stays bounded).
    """

    def __init__(self, datasets: dict, chunk: int, level: int, threads: int):
        self.datasets = datasets
        self.chunk = int(chunk)
        self.level = int(level)
        self.threads = max(1, int(threads))
        self._pool = ThreadPoolExecutor(max_workers=self.threads, thread_name_prefix="evnoise-gzip")
        # per field: the pieces not yet handed to the pool (less than a chunk in all), kept as they
        # came, so that many small appends cost their own size, not a chunk's copy each
        self._pieces = {name: [] for name in datasets}
        self._pending = 0
        self._queued = {name: 0 for name in datasets}  # elements handed to the pool, per field
        self._in_flight: deque = deque()

    def append(self, arrays: dict) -> None:
        """Append ``{name: 1-D array}`` (every field the same length) after what was appended before."""
        n = 0
        for name, values in arrays.items():
            values = np.asarray(values, dtype=self.datasets[name].dtype)
            n = values.size
            if n:
                self._pieces[name].append(values)
        self._pending += n
        if self._pending < self.chunk:
            return
        for name, pieces in self._pieces.items():
            data = np.concatenate(pieces) if len(pieces) > 1 else pieces[0]
            whole = data.size - data.size % self.chunk
            for start in range(0, whole, self.chunk):
                self._submit(name, self._queued[name], data[start:start + self.chunk])
                self._queued[name] += self.chunk
            self._pieces[name] = [data[whole:].copy()] if whole < data.size else []
        self._pending %= self.chunk

    def finish(self, n: int) -> None:
        """Write the last partial chunks (zero-padded), every chunk in flight, and set the extent to ``n``."""
        for name, pieces in self._pieces.items():
            if pieces:
                tail = np.concatenate(pieces)
                padded = np.zeros(self.chunk, dtype=tail.dtype)
                padded[:tail.size] = tail
                self._submit(name, self._queued[name], padded)
                self._queued[name] += tail.size
                self._pieces[name] = []
        self._pending = 0
        self._drain(0)
        for ds in self.datasets.values():
            ds.resize((int(n),))
        self.close()

    def close(self) -> None:
        """Stop the threads (what is in flight is dropped: for an aborted file)."""
        self._in_flight.clear()
        self._pool.shutdown(wait=True, cancel_futures=True)

    def _submit(self, name: str, offset: int, values: np.ndarray) -> None:
        self._in_flight.append((name, offset, hand_over(self._pool.submit(shuffle_deflate, values, self.level))))
        self._drain(4 * self.threads)

    def _drain(self, keep: int) -> None:
        """Write finished chunks in order until at most ``keep`` are in flight."""
        while len(self._in_flight) > keep:
            name, offset, outcome = self._in_flight.popleft()
            data = take(outcome)  # not Future.result: see evnoise._pool
            ds = self.datasets[name]
            if ds.shape[0] < offset + 1:
                ds.resize((offset + self.chunk,))
            ds.id.write_direct_chunk((offset,), data, filter_mask=0)
