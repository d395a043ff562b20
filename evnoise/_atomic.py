"""Atomic file output: write under a temporary name in the target folder, rename on success.

A failure (an exception inside the ``with`` block, or the rename itself) removes the temporary
file, so nothing half-written ever carries the final name.
"""

from __future__ import annotations

import os
import secrets
from contextlib import contextmanager
from pathlib import Path

from .errors import EvnoiseError, OutputError


def temporary_name(path: Path) -> Path:
    """A hidden, unique temporary name next to ``path``."""
    return path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")


@contextmanager
def atomic_output(path, *, overwrite: bool = True, what: str = "file"):
    """Yield a temporary path to write; on success it is renamed to ``path``.

    Raises :class:`~evnoise.OutputError` (naming ``what`` and the path) when the folder does not
    exist, when ``path`` exists and ``overwrite`` is false, or when writing fails.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise OutputError(f"cannot write {what} {path}: directory {folder} does not exist")
    if path.exists() and not overwrite:
        raise OutputError(f"{what} {path} already exists; pass --overwrite (overwrite=True in Python) to replace it")
    tmp = temporary_name(path)
    try:
        yield tmp
        if not overwrite and path.exists():
            raise OutputError(f"{what} {path} appeared while writing; not replacing it")
        os.replace(tmp, path)
    except EvnoiseError:
        tmp.unlink(missing_ok=True)
        raise
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise OutputError(f"cannot write {what} {path}: {exc}") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text_atomic(path, text: str, *, overwrite: bool = True, what: str = "file") -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the path."""
    with atomic_output(path, overwrite=overwrite, what=what) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)
