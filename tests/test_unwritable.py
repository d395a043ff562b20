"""Unwritable places: a cache folder the user cannot write must not fail a command.

The checks run as any user: the condition is simulated (Numba finds no cache folder it can write), not made with
file modes, which root ignores.
"""

from __future__ import annotations

import numba.core.caching
import numpy as np


def _kernel_source():
    def add_two(x):
        return x + 2.0

    return add_two


def test_a_kernel_compiles_without_a_writable_cache_folder(monkeypatch, caplog):
    """With NUMBA_CACHE_DIR, the home folder and ``__pycache__`` beside the kernels all unwritable, Numba refuses
    ``cache=True`` when a kernel is defined ("cannot cache function ...: no locator available"), and every command
    failed at import with "the cache of compiled kernels is damaged ...; delete the folder ..."."""
    from evnoise._kernels import _jit

    monkeypatch.setattr(numba.core.caching.CacheImpl, "_locator_classes", [])  # no folder is writable
    monkeypatch.setattr(_jit, "_warned_uncached", [], raising=False)
    with caplog.at_level("WARNING"):
        first = _jit.kernel(_kernel_source())
        second = _jit.kernel(_kernel_source())
    assert first(np.float64(1.5)) == 3.5
    assert second(np.float64(0.5)) == 2.5
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "not cached" in warnings[0]
    assert "--" not in warnings[0]


def test_a_cache_failure_without_a_folder_reads_as_one_sentence():
    """A Numba cache error whose traceback names no folder read "delete the folder the Numba cache folder (...)"
    (seen when no cache folder could be written, before kernels fell back to no cache)."""
    from evnoise.cli import _known_failure

    where = {}
    code = compile("def load():\n    raise RuntimeError('cannot cache function')\n",
                   "/somewhere/numba/core/caching.py", "exec")
    exec(code, where)  # a frame of Numba's caching module, with no cache object in it
    try:
        where["load"]()
    except RuntimeError as exc:
        text = _known_failure(exc)
    assert text is not None and "the cache of compiled kernels is damaged" in text
    assert "the folder the Numba" not in text
    assert "delete the Numba cache folder (NUMBA_CACHE_DIR" in text


WORKER_LOGGING = """
import logging, multiprocessing, os
from concurrent.futures import ProcessPoolExecutor
from evnoise._kernels import _jit
from evnoise.generators import dataset

handler = logging.StreamHandler()
handler.setFormatter(logging.Formatter("evnoise: %(levelname)s: %(message)s"))
logging.basicConfig(level=logging.WARNING, handlers=[handler], force=True)
_jit.note_warnings_given((False, True))  # this process said: kernels not cached
with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"), initializer=dataset._start_worker,
                         initargs=(os.getpid(), dataset._parent_logging())) as pool:
    pool.submit(logging.getLogger("evnoise.generators").warning, "a worker's warning").result()
    pool.submit(logging.getLogger("evnoise.generators").info, "a worker's note").result()
    pool.submit(_jit._warn_uncached).result()
"""


def test_dataset_workers_log_as_the_command_does():
    """make-dataset's spawned workers started without logging: their warnings came out bare (Python's last-resort
    handler), and the uncached-kernels warning the command had given came again from each worker."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", WORKER_LOGGING], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stderr.splitlines()
    assert lines == ["evnoise: WARNING: a worker's warning"], proc.stderr
