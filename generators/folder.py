"""The output folder of ``make_dataset``: its layout, the lock, and what earlier runs left there.

Layout (see :mod:`.dataset`): ``manifest.json`` (written last), ``shards/``, the progress folder
``.evnoise-progress/`` while a run is under way, and an optional ``preview.png``. The helpers
here prepare the folder, lock it for one run at a time, and read back the records of shards
finished earlier so that a run resumes (each checked against its size and SHA-256).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import stat
from pathlib import Path

from evnoise._atomic import os_error_text, write_text_atomic
from evnoise.errors import InputError, OutputError

from .shards import file_sha256

__all__ = ["MANIFEST", "PREVIEW", "SHARDS_DIR", "PROGRESS_DIR", "write_json", "read_json", "FolderLock",
           "prepare_folder", "check_own_parts", "dataset_member", "discard_empty", "stored_seed",
           "shard_verified", "remove_stale_temporaries"]

MANIFEST = "manifest.json"
#: a picture of a few pairs, written by ``evnoise make-dataset`` (not part of the data, not verified)
PREVIEW = "preview.png"
SHARDS_DIR = "shards"
PROGRESS_DIR = ".evnoise-progress"


def write_json(path: Path, data, *, what: str = "JSON file") -> None:
    """Write ``data`` as indented, key-sorted JSON, atomically; ``what`` names the file in an error
    ("manifest", "progress record", ...)."""
    write_text_atomic(path, json.dumps(data, indent=1, sort_keys=True) + "\n", what=what)


def read_json(path: Path):
    """The JSON content of ``path``, or None if it cannot be read or parsed."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):  # RecursionError: arrays nested past the recursion limit
        return None


class FolderLock:
    """An exclusive lock on the output folder (one run at a time)."""

    def __init__(self, path: Path):
        self.path = path
        self.fh = None

    def __enter__(self):
        try:
            import fcntl
        except ImportError:  # pragma: no cover - not POSIX
            return self
        try:
            # O_NOFOLLOW: a link planted as the lock file must not make us create a file elsewhere
            self.fh = os.fdopen(os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_APPEND | os.O_NOFOLLOW, 0o644), "a+")
            fcntl.flock(self.fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self.fh.close()
            raise OutputError(f"another evnoise make-dataset run is writing to {self.path.parent.parent}") from None
        except OSError as exc:
            raise OutputError(f"cannot lock {self.path}: {os_error_text(exc)}") from None
        return self

    def __exit__(self, *exc):
        if self.fh is not None:
            self.fh.close()
        return False


def prepare_folder(root: Path, overwrite: bool) -> None:
    """Create ``root`` or check it (writable, empty or an evnoise dataset); ``overwrite`` clears a dataset there."""
    if root.exists() and not root.is_dir():
        raise OutputError(f"output {root} exists and is not a folder")
    if not root.exists():
        parent = root.parent if str(root.parent) else Path(".")
        if not parent.is_dir():
            raise OutputError(f"cannot create output folder {root}: {parent} does not exist")
        try:
            root.mkdir()
        except OSError as exc:
            raise OutputError(f"cannot create output folder {root}: {exc.strerror or exc}") from None
    if not os.access(root, os.W_OK | os.X_OK):
        raise OutputError(f"output folder {root} is not writable")
    check_own_parts(root)
    ours = {MANIFEST, SHARDS_DIR, PROGRESS_DIR, PREVIEW}
    others = [p.name for p in root.iterdir() if p.name not in ours]
    has_dataset = (root / MANIFEST).exists() or (root / PROGRESS_DIR).exists()
    if others and not has_dataset:
        raise OutputError(f"output folder {root} is not empty and holds no evnoise dataset "
                          f"({', '.join(sorted(others)[:3])}{', ...' if len(others) > 3 else ''}); "
                          "choose a new or empty folder")
    if overwrite and has_dataset:
        _clear(root)


def dataset_member(root, name) -> Path:
    """The path of file ``name`` (as a manifest or progress record states it) inside dataset folder ``root``.

    The one check of every file name a dataset names: a relative path with no ``..`` part that, with
    any links resolved, stays inside ``root``. A manifest from someone else could otherwise make
    ``evnoise info`` or ``train`` read any local file (``"../x.h5"``, ``"/etc/..."``). Raises
    :class:`~evnoise.InputError`.
    """
    root = Path(root)
    if not isinstance(name, str) or not name or "\x00" in name:
        raise InputError(f"dataset {root} names a shard file {name!r}, which is not a file name")
    rel = Path(name)
    if rel.is_absolute() or ".." in rel.parts or rel.drive:
        raise InputError(f"dataset {root} names the shard file {name!r}, outside the dataset folder; "
                         "only files inside it are read")
    path = root / rel
    try:
        inside = path.resolve().is_relative_to(root.resolve())
    except (OSError, RuntimeError, ValueError):
        inside = False
    if not inside:
        raise InputError(f"dataset {root} names the shard file {name!r}, which leads outside the dataset "
                         "folder (a symbolic link); only files inside it are read")
    return path


def check_own_parts(root: Path) -> None:
    """Refuse a dataset folder whose own parts (``manifest.json``, ``shards/``, the progress folder,
    ``preview.png``, or anything inside ``shards/`` and the progress folder) are symbolic links, or
    whose ``shards/`` or progress folder is not a folder: a run deletes and writes there, and must
    never do so outside the folder it was named (a link would lead it anywhere)."""
    for name in (MANIFEST, SHARDS_DIR, PROGRESS_DIR, PREVIEW):
        part = root / name
        if part.is_symlink():
            raise OutputError(f"{part} is a symbolic link; evnoise writes and deletes only inside the output "
                              f"folder and follows no link there: remove it, or choose another folder")
    for name in (SHARDS_DIR, PROGRESS_DIR):
        part = root / name
        if not part.exists():
            continue
        if not part.is_dir():
            raise OutputError(f"{part} exists and is not a folder; remove it, or choose another folder")
        try:
            links = [p for p in part.iterdir() if p.is_symlink()]
        except OSError as exc:
            raise OutputError(f"cannot list {part}: {exc.strerror or exc}") from None
        if links:
            raise OutputError(f"{links[0]} is a symbolic link; evnoise writes and deletes only inside the output "
                              f"folder and follows no link there: remove it, or choose another folder")


#: the temporary names evnoise's atomic writers use (``evnoise._atomic.temporary_name``):
#: ``.<final name>.<pid>-<hex>.tmp`` (also ``.tmp.png``), and the older ``.<final name>.<pid>.tmp``
_TEMPORARY = re.compile(r"\..+\.(\d+)(?:-[0-9a-f]+)?\.tmp(?:\.[a-z]+)?")


def _pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists and can still write (a process of another user counts; so does
    this one). A zombie (a process that has ended but that its parent, often a container's PID 1, has
    not reaped yet) writes nothing more: it counts as gone. Where ``/proc`` is missing, a zombie
    counts as alive (its file is kept, as for any writer we cannot judge)."""
    if pid <= 0:
        return True  # not a PID we can judge: keep the file
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # PermissionError: it exists; anything else: do not guess
        return True
    return not _is_zombie(pid)


def _is_zombie(pid: int) -> bool:
    """Whether Linux's ``/proc`` says ``pid`` has ended and waits to be reaped (state Z or X)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            stat_line = f.read(4096)
    except OSError:
        return False
    end = stat_line.rfind(b")")  # the command name may hold spaces and parentheses
    state = stat_line[end + 2: end + 3] if end >= 0 else b""
    return state in (b"Z", b"X")


def remove_stale_temporaries(root: Path) -> list:
    """Remove what killed runs left in dataset folder ``root``: temporary files of evnoise's own naming
    (a shard, a record, the manifest or the preview being written) whose writer process is gone.

    Only ``root`` itself, ``shards/`` and the progress folder are looked at (no recursion; a part that
    is a link is skipped, see :func:`check_own_parts`); only regular files (never a link) whose name
    matches the pattern are removed, and only when no process with the PID in the name is alive (a
    writer still at work, such as a worker of a killed run that is ending, keeps its file). Returns
    the paths removed."""
    removed = []
    for folder in (root, root / SHARDS_DIR, root / PROGRESS_DIR):
        try:
            if folder.is_symlink() or not folder.is_dir():
                continue
            entries = list(os.scandir(folder))
        except OSError:
            continue
        for entry in entries:
            m = _TEMPORARY.fullmatch(entry.name)
            if m is None:
                continue
            try:
                if not stat.S_ISREG(entry.stat(follow_symlinks=False).st_mode) or _pid_alive(int(m.group(1))):
                    continue
                os.unlink(entry.path)
            except OSError:
                continue
            removed.append(Path(entry.path))
    return removed


def discard_empty(root: Path, created: bool) -> None:
    """Remove the files of a run that made no pair (every source unreadable), so that no empty
    folder looks like a dataset; the folder itself goes too when this run created it."""
    shutil.rmtree(root / SHARDS_DIR, ignore_errors=True)
    (root / PREVIEW).unlink(missing_ok=True)
    if created:
        for p in root.iterdir():
            if p.name != PROGRESS_DIR:
                return  # something else appeared: leave the folder
        shutil.rmtree(root, ignore_errors=True)


def _clear(root: Path) -> None:
    """Remove an existing dataset's files (only evnoise's own)."""
    (root / MANIFEST).unlink(missing_ok=True)
    (root / PREVIEW).unlink(missing_ok=True)
    shards = root / SHARDS_DIR
    if shards.is_dir():
        for p in shards.iterdir():
            if p.suffix == ".h5" or p.name.endswith(".tmp"):
                p.unlink()
    progress = root / PROGRESS_DIR
    if progress.is_dir():
        shutil.rmtree(progress)


def stored_seed(root: Path):
    """The seed of the dataset (finished or under way) in ``root``, or None."""
    for path in (root / MANIFEST, root / PROGRESS_DIR / "plan.json"):
        data = read_json(path) if path.exists() else None
        if isinstance(data, dict) and isinstance(data.get("config"), dict) and "seed" in data["config"]:
            return data["config"]["seed"]
    return None


def shard_verified(root: Path, rec: dict) -> bool:
    """Whether the shard file of record ``rec`` exists with the recorded size and SHA-256."""
    try:
        path = dataset_member(root, rec["file"])
    except (InputError, KeyError, TypeError):
        return False
    try:
        if not path.is_file() or path.stat().st_size != rec["bytes"]:
            return False
        return file_sha256(path) == rec["sha256"]
    except OSError:
        return False
