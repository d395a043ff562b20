"""evnoise's on-disk cache of computed arrays (the closed form's Chebyshev tables), shared by processes.

A fresh process (``evnoise simulate``, a DataLoader worker) would otherwise rebuild the tables the closed
form uses (about a CPU-second per threshold and bias); with the cache it reads them back. What is cached
is only ever a speed-up, never trusted:

- **Where**: ``tables/`` in evnoise's cache folder (:func:`cache_dir`:
  ``$EVNOISE_CACHE``, else ``$XDG_CACHE_HOME/evnoise``, else ``~/.cache/evnoise``).
- **Off**: ``EVNOISE_TABLE_CACHE=0`` (or ``off``, ``no``, ``false``) neither reads nor writes it.
- **Key**: a dict of strings naming everything the arrays depend on; its SHA-256 names the file and
  the whole key is stored in it and compared on load (a file written for another key, another
  format version, or by other code is ignored).
- **Verified**: a SHA-256 of the key and every array's dtype, shape and bytes is stored and checked
  on load; the caller checks the arrays' structure too. A file that fails any check is ignored (and
  replaced by the next save).
- **Written atomically**: to a unique temporary name in the same folder, then ``os.replace``: a reader
  sees an old file or a new one, never half of one; of concurrent writers the last one wins, and what
  the others added is rebuilt when it is next needed.
- **Bounded**: at most :data:`MAX_TABLE_FILES` tables and :data:`MAX_TABLE_BYTES` bytes (a log-spaced table is
  about 35 kB, a table's certified panels above lam = 1e4 about 150 kB). A save that finds more removes the
  least recently used (a load marks its file used) down to :data:`PRUNE_TO_FILES` and :data:`PRUNE_TO_BYTES`, and
  temporary files older than :data:`STALE_TEMPORARY_S` (left by a writer that was killed). A sweep over
  thresholds, as calibration does, so never fills a disk; a removed table is rebuilt when next needed.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

#: Version of the file layout (in every key: a new layout never reads an old file).
FORMAT = 1
#: Largest cached file read, and largest total its members may declare (a table is tens of kB): a file
#: declaring more is ignored before anything is allocated for it.
MAX_FILE_BYTES = 16 << 20
_OFF = ("0", "off", "no", "false")
#: Most tables kept in the folder; a save beyond removes the least recently used down to PRUNE_TO_FILES.
MAX_TABLE_FILES = 2000
PRUNE_TO_FILES = 1800
#: Most bytes of tables kept in the folder; a save beyond removes the least recently used down to PRUNE_TO_BYTES.
MAX_TABLE_BYTES = 200 << 20
PRUNE_TO_BYTES = 180 << 20
#: Age (seconds) after which a temporary file in the folder is a killed writer's (a save takes milliseconds).
STALE_TEMPORARY_S = 3600.0


def cache_dir() -> Path:
    """evnoise's cache folder: ``$EVNOISE_CACHE``, else ``$XDG_CACHE_HOME/evnoise``, else ``~/.cache/evnoise``.

    It holds the closed form's tables (``tables/``) and the LPIPS weights. A relative ``XDG_CACHE_HOME`` is
    ignored, as the XDG base-directory specification says.
    """
    env = os.environ.get("EVNOISE_CACHE")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME", "")
    base = Path(xdg).expanduser() if xdg and Path(xdg).expanduser().is_absolute() else Path.home() / ".cache"
    return base / "evnoise"


def table_cache_dir() -> Path | None:
    """The folder of cached tables, or None when ``EVNOISE_TABLE_CACHE`` turns the cache off."""
    if os.environ.get("EVNOISE_TABLE_CACHE", "").strip().lower() in _OFF:
        return None
    return cache_dir() / "tables"


def _key_text(key: dict) -> str:
    return json.dumps({"format": FORMAT, **key}, sort_keys=True, separators=(",", ":"))


def _checksum(text: str, arrays: dict) -> str:
    h = hashlib.sha256(text.encode())
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"|{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(memoryview(a).cast("B"))
    return h.hexdigest()


def table_path(key: dict, folder: Path) -> Path:
    """The file of ``key`` in ``folder`` (named by the key's hash)."""
    return folder / f"table-{hashlib.sha256(_key_text(key).encode()).hexdigest()[:32]}.npz"


def load_arrays(key: dict, names: tuple) -> dict | None:
    """The arrays ``names`` stored for ``key``, or None (no cache, no file, or a file that fails a check).

    The checks here: the file is a NumPy ``.npz`` read without pickles, holds exactly ``names`` plus the
    key and checksum, its key is ``key`` and its checksum matches. The caller checks what the arrays mean.
    """
    folder = table_cache_dir()
    if folder is None:
        return None
    path = table_path(key, folder)
    try:
        arrays, text, stored = _read_npz(path, names, _key_text(key))
    except FileNotFoundError:
        return None
    except Exception as exc:  # noqa: BLE001 -- a damaged file of any kind is ignored, never trusted
        log.debug("ignoring cached table %s: %s", path, exc)
        return None
    if text != _key_text(key) or stored != _checksum(text, arrays):
        log.debug("ignoring cached table %s: key or checksum does not match", path)
        return None
    try:  # mark it used: pruning removes the least recently used tables first
        os.utime(path, follow_symlinks=False)
    except (OSError, NotImplementedError):  # a read-only cache, or no lutimes here: only the order suffers
        pass
    return arrays


def _read_npz(path: Path, names: tuple, want_key: str):
    """``(arrays, key text, checksum)`` of a cached file, read only if it is a plain file of bounded size whose
    uncompressed members declare a bounded total and whose key is ``want_key`` (checked before the arrays are
    read). Never follows a link, never waits on a pipe or device."""
    import stat
    import zipfile

    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0))
    with os.fdopen(fd, "rb") as fh:
        info = os.fstat(fh.fileno())
        if not stat.S_ISREG(info.st_mode) or info.st_size > MAX_FILE_BYTES:
            raise ValueError("not a plain file of a table's size")
        with zipfile.ZipFile(fh) as archive:
            members = archive.infolist()
            if {m.filename for m in members} != {f"{n}.npy" for n in (*names, "key", "checksum")}:
                raise ValueError(f"members {sorted(m.filename for m in members)}")
            if any(m.compress_type != zipfile.ZIP_STORED for m in members) or \
                    sum(m.file_size for m in members) > MAX_FILE_BYTES:
                raise ValueError("compressed members, or more data than a table holds")
        fh.seek(0)
        with np.load(fh, allow_pickle=False) as npz:
            text = str(npz["key"][()])
            if text != want_key:
                raise ValueError("written for another key")
            stored = str(npz["checksum"][()])
            return {name: npz[name] for name in names}, text, stored


def save_arrays(key: dict, arrays: dict) -> Path | None:
    """Store ``arrays`` for ``key`` (atomically); returns the file, or None (cache off, or it cannot be written)."""
    folder = table_cache_dir()
    if folder is None:
        return None
    path = table_path(key, folder)
    text = _key_text(key)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{os.urandom(4).hex()}.tmp")
    replaced = False
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with open(tmp, "xb") as fh:
            np.savez(fh, key=np.array(text), checksum=np.array(_checksum(text, arrays)), **arrays)
        os.replace(tmp, path)
        replaced = True
    except OSError as exc:  # a read-only or full disk: the cache is only a speed-up
        log.debug("cannot write cached table %s: %s", path, exc)
        return None
    finally:
        if not replaced:  # any failure (an error, Ctrl-C) leaves no temporary behind
            try:
                tmp.unlink()
            except OSError:
                pass
    prune(folder)
    return path


def prune(folder: Path) -> list:
    """Keep the table folder bounded: when it holds more than :data:`MAX_TABLE_FILES` tables or
    :data:`MAX_TABLE_BYTES` bytes of them, remove the least recently used (oldest modification time; a load
    updates it) down to :data:`PRUNE_TO_FILES` and :data:`PRUNE_TO_BYTES`;
    remove temporary files older than :data:`STALE_TEMPORARY_S` seconds. Only plain files of the cache's
    own naming are touched (never a link, nothing outside ``folder``). Returns the paths removed; errors
    (a file another process removed first, a read-only folder) are ignored."""
    import re
    import stat
    import time

    table_name = re.compile(r"table-[0-9a-f]{32}\.npz")
    temporary_name = re.compile(r"\.table-[0-9a-f]{32}\.npz\.\d+-[0-9a-f]+\.tmp")
    tables, removed = [], []
    now = time.time()
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        try:
            info = entry.stat(follow_symlinks=False)
        except OSError:
            continue
        if not stat.S_ISREG(info.st_mode):
            continue
        if table_name.fullmatch(entry.name):
            tables.append((info.st_mtime_ns, entry.name, entry.path, info.st_size))
        elif temporary_name.fullmatch(entry.name) and now - info.st_mtime > STALE_TEMPORARY_S:
            removed.append(entry.path)
    total = sum(size for *_, size in tables)
    if len(tables) > MAX_TABLE_FILES or total > MAX_TABLE_BYTES:
        tables.sort()
        kept = len(tables)
        for _, _, path, size in tables:  # oldest first, until both bounds hold
            if kept <= PRUNE_TO_FILES and total <= PRUNE_TO_BYTES:
                break
            removed.append(path)
            kept -= 1
            total -= size
    gone = []
    for path in removed:
        try:
            os.unlink(path)
            gone.append(Path(path))
        except OSError:
            pass
    return gone
