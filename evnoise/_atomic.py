"""Atomic file output: write under a temporary name in the target folder, rename on success.

A failure (an exception inside the ``with`` block, or the rename itself) removes the temporary
file, so nothing half-written ever carries the final name. :class:`AtomicFile` is the one home of
the temporary-name / rename / remove steps; :func:`atomic_output` wraps it for a ``with`` block, and
writers that stay open across calls (``EventWriter``, ``ShardWriter``) hold one.
"""

from __future__ import annotations

import logging
import os
import re
import secrets
from contextlib import contextmanager
from pathlib import Path

from .errors import EvnoiseError, OutputError

log = logging.getLogger(__name__)


#: how an errno is named in the texts of errors that are not OSError: h5py's ("errno = 28"), Rust's ("(os error 28)")
_ERRNO_IN_TEXT = re.compile(r"errno = (\d+)|\(os error (\d+)\)")


def errno_of(exc: BaseException) -> int | None:
    """The errno of an OS error: its own, or the one its text names where the error is not an ``OSError`` or lost
    its errno (h5py's "errno = 28", faery's Rust errors "(os error 28)"); ``None`` if neither gives one."""
    errno = getattr(exc, "errno", None)
    if isinstance(errno, int) and errno:
        return errno
    m = _ERRNO_IN_TEXT.search(str(exc))
    return int(m.group(1) or m.group(2)) if m else None


def os_error_text(exc: BaseException) -> str:
    """An error in one line: the ``strerror`` of its errno (:func:`errno_of`: h5py's texts span lines, name the
    temporary file and sometimes come as RuntimeError; faery's end in "(os error 28)"), else its text squeezed (a
    library's own failure, e.g. a Rust panic's message)."""
    errno = errno_of(exc)
    if errno:
        return os.strerror(errno)
    return " ".join(str(exc).split()) or type(exc).__name__


def refuse_folder_name(path, what: str = "file") -> None:
    """Refuse an output name that ends in ``/`` (a folder): ``Path()`` drops the slash, and a file would be written
    under the name without it."""
    text = os.fspath(path)
    if isinstance(text, str) and text.endswith(("/", os.sep)):
        raise OutputError(f"cannot write {what} {text}: the name ends in '/', a folder; give a file name")


def temporary_name(path: Path, *, suffix: str = ".tmp") -> Path:
    """A hidden, unique temporary name next to ``path`` (ending in ``suffix``)."""
    path = Path(path)
    return path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}{suffix}")


class AtomicFile:
    """A temporary file next to ``path`` that becomes ``path`` on :meth:`commit`.

    Parameters
    ----------
    path : str or os.PathLike
        Final name.
    overwrite : bool
        When false, :meth:`commit` refuses to replace a file that appeared at ``path`` meanwhile.
    what : str
        What the file is, for error messages ("event file", "shard", ...).
    suffix : str
        Ending of the temporary name (e.g. ``".tmp.png"`` for writers that infer the format from it).

    The caller writes ``tmp`` itself (any library, kept open across calls), then calls :meth:`commit`
    (rename) or :meth:`discard` (remove). :meth:`commit` raises ``OSError`` from the rename as it is, so
    each writer keeps its own wording of that error.
    """

    def __init__(self, path, *, overwrite: bool = True, what: str = "file", suffix: str = ".tmp"):
        refuse_folder_name(path, what)
        self.path = Path(path)
        self.overwrite = overwrite
        self.what = what
        self.tmp = temporary_name(self.path, suffix=suffix)
        self.done = False

    def create(self) -> Path:
        """Create the temporary file (empty), turning an OS error into one clean :class:`OutputError` line."""
        try:
            with open(self.tmp, "xb"):
                pass
        except OSError as exc:
            raise OutputError(f"cannot write {self.what} {self.path}: {exc.strerror or exc}") from None
        return self.tmp

    def commit(self) -> Path:
        """Rename the temporary file to its final name (``OutputError`` if ``path`` appeared and not ``overwrite``)."""
        if not self.overwrite and os.path.lexists(self.path):  # a link, even a broken one, counts
            raise OutputError(f"{self.what} {self.path} appeared while writing; not replacing it")
        os.replace(self.tmp, self.path)
        self.done = True
        return self.path

    def finish(self, close, abort, *, catch=OSError, one_line: bool = False) -> Path:
        """A writer's ``close()``: run ``close`` (flush and close its handle), then :meth:`commit`.

        On failure ``abort`` is called (it closes the handle and calls :meth:`discard`) and the error
        re-raised: an :class:`~evnoise.EvnoiseError` as it is, an exception of type ``catch`` as
        ``OutputError("cannot finish {what} {path}: {exc}")`` (``one_line`` squeezes its whitespace).
        """
        try:
            close()
            return self.commit()
        except EvnoiseError:
            abort()
            raise
        except catch as exc:
            abort()
            if isinstance(exc, OSError) or errno_of(exc):
                text = os_error_text(exc)  # h5py's texts span lines and name the temporary file
            else:
                text = " ".join(str(exc).split()) if one_line else str(exc)
            raise OutputError(f"cannot finish {self.what} {self.path}: {text}") from None
        except BaseException:
            abort()
            raise

    def verify_tail(self) -> None:
        """Raise the ``OSError`` of a last write that the writing library lost, before :meth:`commit`.

        faery's Rust encoders flush their buffer when they are dropped and ignore a failure of that flush: on a
        full disk or past a file-size limit the file ended short, without an error, and became a complete-looking
        output. The write that failed left the file at the limit, or ending at a disk block with no block free;
        one more byte at its end fails then with the same error, which is raised (else the byte is cut off again).
        """
        with open(self.tmp, "r+b", buffering=0) as fh:
            size = fh.seek(0, os.SEEK_END)
            fh.write(b"\0")
            fh.truncate(size)

    def release(self) -> None:
        """Truncate the temporary file to 0 bytes (before a library that still holds it open closes it).

        A writer that failed on a full disk frees the space it took, so that the library's last flush
        on close (HDF5 writes its metadata and cached chunks then) finds room and the handle closes
        cleanly: an HDF5 file left open after a failed close is flushed again when the interpreter
        exits, and that crashed the process (exit 139). Errors are ignored: the file is discarded next.
        """
        try:
            os.truncate(self.tmp, 0)
        except OSError:
            pass

    def discard(self) -> None:
        """Remove the temporary file if it is there (a failure to remove is logged, not raised)."""
        try:
            os.unlink(self.tmp)
        except FileNotFoundError:
            pass
        except OSError as exc:
            log.warning("could not remove temporary file %s: %s", self.tmp, exc)


@contextmanager
def atomic_output(path, *, overwrite: bool = True, what: str = "file"):
    """Yield a temporary path to write; on success it is renamed to ``path``.

    Raises :class:`~evnoise.OutputError` (naming ``what`` and the path) when the folder does not
    exist, when ``path`` exists and ``overwrite`` is false, or when writing fails.
    """
    refuse_folder_name(path, what)
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise OutputError(f"cannot write {what} {path}: directory {folder} does not exist")
    if os.path.lexists(path) and not overwrite:  # a symbolic link counts, even a broken one
        raise OutputError(f"{what} {path} already exists; pass overwrite=True to replace it")
    out = AtomicFile(path, overwrite=overwrite, what=what)
    try:
        yield out.tmp
        out.commit()
    except EvnoiseError:
        out.discard()
        raise
    except OSError as exc:  # its errno's text: str(exc) reads "[Errno 28] ..." and may name the temporary file
        out.discard()
        raise OutputError(f"cannot write {what} {path}: {os_error_text(exc)}") from None
    except BaseException:
        out.discard()
        raise


def write_text_atomic(path, text: str, *, overwrite: bool = True, what: str = "file") -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the path."""
    with atomic_output(path, overwrite=overwrite, what=what) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def close_h5_discarding(file, out: AtomicFile | None = None, datasets=()) -> None:
    """Close an h5py file being thrown away (its temporary file ``out`` is discarded next), even on a full disk.

    HDF5 flushes its cached chunks and metadata when a file closes. On a full disk that flush fails, and
    a file whose close failed stays half-closed inside HDF5 (a second close fails too), which flushes it
    again when the interpreter exits and crashed the process there (exit 139, after the error line).
    So the close must succeed the first time: the resizable ``datasets`` are cut to nothing (no chunk
    left to flush), the space written is freed (:meth:`AtomicFile.release`), and the file's descriptor
    is pointed at a file that takes HDF5's last writes whatever the disk holds (:func:`_spare_descriptor`)
    before the close. Nothing here raises.
    """
    for ds in datasets:
        if ds is not None:
            try:
                ds.resize((0,) + tuple(ds.shape[1:]))
            except Exception:  # noqa: BLE001 - best effort; the file is discarded
                pass
    if out is not None:
        out.release()
    try:
        fd = file.id.get_vfd_handle()
    except Exception:  # noqa: BLE001 - not a POSIX driver, or already closed
        fd = None
    if isinstance(fd, int):
        try:
            spare = _spare_descriptor()
            try:
                os.dup2(spare, fd)
            finally:
                os.close(spare)
        except OSError:
            pass
    try:
        file.close()
    except Exception:  # noqa: BLE001 - nothing more to do
        pass


def _spare_descriptor() -> int:
    """A descriptor that takes the last writes of an HDF5 file being discarded (see :func:`close_h5_discarding`).

    Without a file-size limit: an anonymous file in memory (Linux ``memfd``), which also takes the ``ftruncate``
    HDF5 may do on close. Under a file-size limit (``ulimit -f``, ``RLIMIT_FSIZE``) a ``memfd`` is a regular file
    bound by that limit too, and the discarded file's writes lie at offsets past it (that close failed and the
    process crashed at exit, 139): then ``/dev/null``, a device the limit does not bind, where writes at any
    offset succeed and reads find nothing (HDF5 reads that as zeros).
    """
    try:
        import resource

        limited = resource.getrlimit(resource.RLIMIT_FSIZE)[0] != resource.RLIM_INFINITY
    except (ImportError, OSError, ValueError):
        limited = False
    if not limited and hasattr(os, "memfd_create"):
        return os.memfd_create("evnoise-discarded")
    return os.open(os.devnull, os.O_RDWR)
