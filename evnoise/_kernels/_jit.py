"""The one place that decides how Numba compiles evnoise's kernels.

Every kernel is compiled through :func:`kernel` so that options are uniform:
``cache=True`` (compiled code is reused across processes), ``nogil=True`` (kernels can
run in Python threads), ``error_model="numpy"`` (division by zero gives inf/nan instead of
raising, which is what the closed forms expect and is faster), and no ``fastmath``
(the numerics rely on IEEE semantics: inf, nan, exact rounding of log1p/expm1).
"""

from __future__ import annotations

import errno
import logging

import numba

log = logging.getLogger(__name__)

_OPTIONS = dict(cache=True, nogil=True, error_model="numpy", fastmath=False)

#: errors of a cache folder without room: the kernel runs uncached (compiled again next time) rather than fail
_NO_ROOM = {errno.ENOSPC, errno.EFBIG, getattr(errno, "EDQUOT", errno.ENOSPC)}
_warned = []
_warned_uncached = []


def _room_tolerant_cache(dispatcher):
    """Let ``dispatcher`` run when its compiled code cannot be saved for lack of room (a full disk, a file-size
    limit): Numba raises that ``OSError`` from the call (after removing its temporary file), and the command
    failed with it, although the kernel was compiled and only its copy on disk is missing."""
    cache = getattr(dispatcher, "_cache", None)
    save = getattr(cache, "save_overload", None)
    if save is None:
        return dispatcher

    def save_overload(sig, data):
        try:
            save(sig, data)
        except OSError as exc:
            if exc.errno not in _NO_ROOM:
                raise
            if not _warned:
                _warned.append(True)
                log.warning("compiled kernels are not cached (%s: %s); they are compiled again on the next run",
                            getattr(cache, "_cache_path", "the cache folder"), exc.strerror or exc)

    cache.save_overload = save_overload
    return dispatcher


def warnings_given() -> tuple[bool, bool]:
    """Which of this module's once-per-process warnings this process has given (for :func:`note_warnings_given`)."""
    return bool(_warned), bool(_warned_uncached)


def note_warnings_given(given: tuple[bool, bool]) -> None:
    """Count the warnings ``given`` by another process as given here: a pool worker started by a process that
    said them would say each again, once per worker."""
    for said, store in zip(given, (_warned, _warned_uncached)):
        if said and not store:
            store.append(True)


def _warn_uncached() -> None:
    """Warn once that the kernels are compiled without an on-disk cache (no folder for it can be written)."""
    if not _warned_uncached:
        _warned_uncached.append(True)
        log.warning("compiled kernels are not cached: no writable cache folder (set NUMBA_CACHE_DIR to a writable "
                    "folder); they are compiled again on each run")


def kernel(func=None, *, parallel: bool = False, inline: bool = False):
    """Compile ``func`` with evnoise's standard Numba options (usable with or without arguments).

    ``inline=True`` inlines the function into its callers at Numba-IR level (for small helpers
    on hot paths that pass arrays around, where a call would cost reference counting).
    """

    def wrap(f):
        extra = {"inline": "always"} if inline else {}
        try:
            return _room_tolerant_cache(numba.njit(parallel=parallel, **_OPTIONS, **extra)(f))
        except RuntimeError as exc:
            if "no locator available" not in str(exc):
                raise
        # no writable cache folder (NUMBA_CACHE_DIR, __pycache__ beside the kernels, the user's cache folder):
        # Numba refuses cache=True when the kernel is defined; compile without a cache rather than fail
        _warn_uncached()
        return numba.njit(parallel=parallel, **dict(_OPTIONS, cache=False), **extra)(f)

    return wrap(func) if func is not None else wrap
