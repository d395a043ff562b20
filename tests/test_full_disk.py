"""A full disk or a file-size limit while a command writes: one ``evnoise: error:`` line and exit 2, never a crash
or a traceback, no temporary file left, and no output that looks complete (found by a sweep of every writing
command on a small tmpfs and under ``ulimit -f``).

A test cannot mount a file system (it may not run as root): a child process under ``RLIMIT_FSIZE`` (with SIGXFSZ
ignored, as Python ignores it, so that a write past the limit fails with EFBIG as on a full disk), or writes made
to fail with ``ENOSPC`` in this process.
"""

from __future__ import annotations

import errno
import os
import subprocess
import sys

import numpy as np
import pytest

from _cli_helpers import one_error_line, run_cli, small_events_file
from evnoise.errors import OutputError

needs_rlimit = pytest.mark.skipif(sys.platform != "linux", reason="needs RLIMIT_FSIZE and SIGXFSZ (Linux)")

DATASET = ["make-dataset", "--procedural", "dead-leaves", "--count", "4", "--crop", "64", "--seed", "1", "-q",
           "--workers", "1"]
SIMULATE = ["simulate", "--example", "--duration", "0.2", "--sensor", "320x180", "--seed", "1", "-q"]


def _cli(cwd, argv, limit=None, timeout=600):
    """``python -m evnoise ARGV`` in a child, its files limited to ``limit`` bytes (``None``: no limit)."""
    def child():  # pragma: no cover - runs in the child
        import resource
        import signal

        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
        if limit is not None:
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return subprocess.run([sys.executable, "-m", "evnoise", *map(str, argv)], capture_output=True, text=True,
                          timeout=timeout, preexec_fn=child, cwd=cwd, env={**os.environ, "PYTHONFAULTHANDLER": ""})


def _failed_cleanly(proc, expect="") -> str:
    """Exit 2 (not a signal: -11 was the crash), one error line (warnings aside), no traceback; returns the line."""
    lines = [line for line in proc.stderr.splitlines() if line.strip() and not line.startswith("evnoise: WARNING:")]
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-3000:])
    assert len(lines) == 1 and lines[0].startswith("evnoise: error: "), proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and "[Errno" not in lines[0] and "os error" not in lines[0], lines[0]
    assert expect in lines[0], lines[0]
    return lines[0]


def _files(folder) -> list:
    return sorted(os.path.relpath(os.path.join(root, name), folder)
                  for root, dirs, names in os.walk(folder) for name in [*dirs, *names])


# -- the discarded HDF5 file under a file-size limit -------------------------------------------------------------
@needs_rlimit
@pytest.mark.parametrize("command, output, limits", [("make-dataset", "ds", (2_000, 25_600)),
                                                     ("simulate", "ev.h5", (0, 4_000))])
def test_an_hdf5_output_past_a_file_size_limit_exits_2_without_a_crash(tmp_path, command, output, limits):
    """Under ``ulimit -f`` a shard or an events.h5 that could not be written was discarded through a memfd, a
    regular file that the limit binds too: HDF5's last writes failed there, the close failed, and the process
    crashed at exit (-11 after its clean error line, with h5py tracebacks before it); with ``ulimit -f 0`` Numba's
    five-line warning about its semaphore came before the error line. The folder a run created is gone again."""
    argv = DATASET if command == "make-dataset" else SIMULATE
    warm = _cli(tmp_path, [*argv, "--out", tmp_path / f"warm-{output}"])  # compiled kernels cached before the limit
    assert warm.returncode == 0, warm.stderr[-3000:]
    for limit in limits:
        work = tmp_path / f"limit-{limit}"
        work.mkdir()
        proc = _cli(work, [*argv, "--out", work / output], limit=limit)
        _failed_cleanly(proc, "File too large")
        assert _files(work) == [], (limit, _files(work))


# -- faery's formats: a last write lost on close -----------------------------------------------------------------
_CUT_SHORT = """
import os, resource, sys
import numpy as np
import evnoise as ev
from evnoise.errors import OutputError
rng = np.random.default_rng(0)
n = 20_000
events = ev.events.make_events(np.sort(rng.integers(0, 2_000_000, n)), rng.integers(0, 320, n),
                               rng.integers(0, 180, n), rng.integers(0, 2, n))
folder = sys.argv[1]
for suffix in sys.argv[2:]:
    path = os.path.join(folder, "events" + suffix)
    ev.write_events(path, events, (180, 320), t_end_us=2_000_000)
    size = os.path.getsize(path)
    os.unlink(path)
    for short in (1, 100):
        # soft limit only: raised again below (a write past it fails with EFBIG; Python ignores SIGXFSZ)
        resource.setrlimit(resource.RLIMIT_FSIZE, (size - short, resource.RLIM_INFINITY))
        try:
            ev.write_events(path, events, (180, 320), t_end_us=2_000_000)
        except OutputError as exc:
            print(suffix, short, "error", str(exc))
        else:
            print(suffix, short, "written", os.path.getsize(path), "of", size)
        finally:
            resource.setrlimit(resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
        print(suffix, short, "left", sorted(os.listdir(folder)))
"""


@needs_rlimit
def test_a_file_cut_short_by_its_last_write_is_an_error_not_an_output(tmp_path):
    """faery's encoders flush their buffer when dropped and ignore a failure there: a file whose last buffer did not
    fit (a full disk, a file-size limit) was renamed to its final name, short, and the command said it wrote it."""
    pytest.importorskip("faery")
    suffixes = [".aedat4", ".raw", ".dat", ".es", ".csv"]
    proc = subprocess.run([sys.executable, "-c", _CUT_SHORT, str(tmp_path), *suffixes], capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [line.split(" ", 3) for line in proc.stdout.splitlines()]
    assert len(rows) == 2 * 2 * len(suffixes), proc.stdout
    for suffix, short, kind, rest in rows:
        if kind == "left":
            assert rest == "[]", (suffix, short, rest)  # neither the output nor a temporary file
        else:
            assert kind == "error", (suffix, short, rest)
            assert "File too large" in rest and "os error" not in rest and "\n" not in rest, rest


@needs_rlimit
def test_the_error_of_a_faery_format_gives_the_errno_text(tmp_path):
    """faery's Rust errors end in "(os error 27)": the line ended so ("File too large (os error 27)")."""
    pytest.importorskip("faery")
    warm = _cli(tmp_path, [*SIMULATE, "--out", tmp_path / "warm.csv"])
    assert warm.returncode == 0, warm.stderr[-3000:]
    work = tmp_path / "limited"
    work.mkdir()
    line = _failed_cleanly(_cli(work, [*SIMULATE, "--out", work / "ev.csv"], limit=5_000), "File too large")
    assert line.endswith(": File too large"), line
    assert _files(work) == []


# -- make-dataset's progress files -------------------------------------------------------------------------------
def _fail_writing(monkeypatch, name_end):
    """Make ``Path.write_text`` of files whose (temporary) name holds ``name_end`` fail as on a full disk."""
    from pathlib import Path

    real = Path.write_text

    def write_text(self, *args, **kwargs):
        if name_end in self.name:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(self))
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", write_text)


def _small_dataset(out):
    from evnoise.generators import PairConfig, make_dataset
    from evnoise.generators.sources import DeadLeaves

    return make_dataset([DeadLeaves(2)], out, PairConfig(sensor_shape=(64, 64), seed=1), workers=1,
                        progress=False)


def test_a_progress_record_that_cannot_be_written_is_named_so_with_the_errno_text(tmp_path, monkeypatch):
    """The record of a finished shard was called a "manifest" and the line kept "[Errno 28]" and the temporary
    file's name: "cannot write manifest .../train-00000.done.json: [Errno 28] No space left on device: '...tmp'"."""
    _fail_writing(monkeypatch, ".done.json")
    with pytest.raises(OutputError) as info:
        _small_dataset(tmp_path / "ds")
    text = str(info.value)
    assert text.startswith("cannot write progress record ") and ".done.json" in text, text
    assert text.endswith(": No space left on device") and "[Errno" not in text and ".tmp" not in text, text


def test_a_progress_plan_that_cannot_be_written_leaves_no_folder(tmp_path, monkeypatch):
    """plan.json was written before the clean-up's reach: a full disk then left the folder with a lock and an
    empty shards/ (and the message called the plan a "manifest")."""
    _fail_writing(monkeypatch, "plan.json")
    with pytest.raises(OutputError) as info:
        _small_dataset(tmp_path / "ds")
    text = str(info.value)
    assert text.startswith("cannot write progress plan ") and text.endswith(": No space left on device"), text
    assert _files(tmp_path) == []


# -- Numba's cache without room ----------------------------------------------------------------------------------
def _kernel_source():
    def add_one(x):
        return x + 1.0

    return add_one


def test_a_kernel_runs_when_its_compiled_code_cannot_be_cached(monkeypatch, caplog):
    """With a cold cache on a full disk (or under ``ulimit -f``) Numba's failure to save the compiled code failed
    the command: "the cache of compiled kernels is damaged (OSError: [Errno 27] File too large); delete ..."."""
    from evnoise._kernels._jit import kernel

    compiled = kernel(_kernel_source())

    def no_room(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(compiled._cache, "_save_overload", no_room)
    with caplog.at_level("WARNING"):
        assert compiled(np.float64(1.5)) == 2.5
    assert compiled(np.float64(2.0)) == 3.0

    def other_error(*args, **kwargs):
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    again = kernel(_kernel_source())
    monkeypatch.setattr(again._cache, "_save_overload", other_error)
    with pytest.raises(OSError, match="Input/output error"):  # only a lack of room is passed over
        again(np.int64(1))


# -- a picture or an output beside another one -------------------------------------------------------------------
def test_simulate_png_on_a_full_disk_names_the_png_not_its_temporary_file(tmp_path, monkeypatch, capsys):
    """"cannot write PNG file /x/.o.png.123-ab12cd34.tmp: [Errno 28] No space left on device": the temporary name
    and the errno's number."""
    from evnoise.cli import simulate

    def full(counts, path, **kwargs):
        with open(path, "wb") as fh:
            fh.write(b"\x89PNG")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr(simulate, "save_count_png", full)
    code, _, err = run_cli(capsys, "simulate", "--example", "--duration", "0.2", "--sensor", "32x18", "--seed", "1",
                           "-q", "--out", tmp_path / "o.h5", "--png", tmp_path / "o.png")
    one_error_line(code, err, f"cannot write PNG file {tmp_path / 'o.png'}: No space left on device")
    assert ".tmp" not in err and "[Errno" not in err
    assert _files(tmp_path) == []


@pytest.mark.parametrize("failing", ["signal", "noise"])
def test_separate_writes_both_outputs_or_neither(tmp_path, monkeypatch, failing):
    """The noise file was renamed, then the signal file's close failed on the full disk: the noise file stayed,
    alone, and looked like a finished run's."""
    from evnoise.io import CsvFileWriter, EventWriter
    from evnoise.separation import separate_file

    pytest.importorskip("faery")
    src = small_events_file(tmp_path / "in.h5", n=2000)
    cls = EventWriter if failing == "signal" else CsvFileWriter
    real = cls.close

    def close(self):
        if self._closed:
            return real(self)
        self.abort()
        raise OutputError(f"cannot finish {self.path}: No space left on device")

    monkeypatch.setattr(cls, "close", close)
    with pytest.raises(OutputError, match="No space left on device"):
        separate_file(src, tmp_path / "signal.h5", tmp_path / "noise.csv")
    assert _files(tmp_path) == ["in.h5"]


def test_reconstruct_step_on_a_full_disk_removes_the_frames_it_wrote(tmp_path, monkeypatch, capsys):
    """--step stopped at the third PNG and left the first two: a shorter series that looked finished."""
    pytest.importorskip("torch")
    from evnoise.reconstruct import imaging

    src = small_events_file(tmp_path / "in.h5", shape=(36, 64), n=4000, duration_us=2_000_000)
    real = imaging.write_png
    calls = []

    def write_png(path, image, *args, **kwargs):
        calls.append(path)
        if len(calls) == 3:
            raise OutputError(f"cannot write PNG file {path}: No space left on device")
        return real(path, image, *args, **kwargs)

    monkeypatch.setattr(imaging, "write_png", write_png)
    code, _, err = run_cli(capsys, "reconstruct", src, "-o", tmp_path / "r.png", "--window", "0.5", "--step", "0.25",
                           "--frames", "4", "-q")
    one_error_line(code, err, "No space left on device")
    assert len(calls) == 3 and _files(tmp_path) == ["in.h5"]


# -- the one-line texts --------------------------------------------------------------------------------------------
def test_error_texts_give_the_errno_words_whatever_the_library():
    from evnoise._atomic import errno_of, os_error_text

    assert os_error_text(RuntimeError("writing failed: No space left on device (os error 28)")) == os.strerror(28)
    assert os_error_text(RuntimeError("File too large (os error 27)")) == os.strerror(27)
    assert os_error_text(OSError(errno.ENOSPC, "No space", "/x/.f.tmp")) == os.strerror(errno.ENOSPC)
    assert os_error_text(RuntimeError("x must be\n  below 3")) == "x must be below 3"
    assert errno_of(RuntimeError("file write failed: ..., errno = 28, ...")) == 28
    assert errno_of(RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 123 vs 456")) is None
