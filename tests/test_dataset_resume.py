"""Killed ``make-dataset`` runs (issue 35, §4): every finished shard is recorded as it completes, a
re-run keeps exactly the recorded shards and gives the bytes of an uninterrupted run, no worker
outlives a killed run, an interrupted state with every shard recorded finishes, and temporaries
that killed runs left in ``--out`` are removed (only there, only of evnoise's naming, only when
their writer is gone).

The CLI runs in a subprocess that is killed once its first shard records appear. Nothing here
asserts a duration: waits for a state (a record, a process gone) have generous limits that only
keep a broken run from hanging the suite.
"""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from evnoise.generators import DeadLeaves, PairConfig, make_dataset
from evnoise.generators.dataset import MANIFEST, PROGRESS_DIR

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc, sends POSIX signals")

#: a tiny job of many one-source shards (4 pairs each): a kill lands while most are still to make
N_SOURCES = 40
ARGS = ["make-dataset", "--procedural", "dead-leaves", "--count", str(N_SOURCES), "--sensor", "128x96", "--crop",
        "64", "--window", "0.25,0.5,1,2", "--shard-size", "4", "--seed", "5", "--split", "0.8,0.1,0.1", "-q"]
#: how long a state may take to appear before the test gives up (never an assertion on speed)
PATIENCE_S = 120.0


def _cli(out, *extra, workers=2) -> list:
    return [sys.executable, "-m", "evnoise", *ARGS, "--out", os.fspath(out), "--workers", str(workers), *extra]


def _hashes(root) -> dict:
    root = Path(root)
    files = [root / MANIFEST, *sorted((root / "shards").glob("*.h5"))]
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


def _records(out) -> set:
    return {p.name[: -len(".done.json")] for p in (Path(out) / PROGRESS_DIR).glob("*.done.json")}


def _shard_files(out) -> set:
    return {p.stem for p in (Path(out) / "shards").glob("*.h5")}


def _children(pid: int) -> set:
    """PIDs of the live (not zombie) processes whose parent is ``pid``."""
    found = set()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if fields[0] != "Z" and int(fields[1]) == pid:
            found.add(int(entry.name))
    return found


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rindex(")") + 2:].split()[0] != "Z"


def _wait_for(condition, what: str):
    deadline = time.monotonic() + PATIENCE_S
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"gave up waiting for {what}")
        time.sleep(0.002)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    out = tmp_path_factory.mktemp("whole") / "ds"
    done = subprocess.run(_cli(out), capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return _hashes(out)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM, signal.SIGINT], ids=["kill", "term", "int"])
@pytest.mark.long
def test_killed_two_worker_run_resumes_keeping_recorded_shards(uninterrupted, tmp_path, sig):
    out = tmp_path / "ds"
    log = tmp_path / "stderr.txt"
    workers = set()
    with open(log, "wb") as err:
        proc = subprocess.Popen(_cli(out), stdout=subprocess.DEVNULL, stderr=err)
    try:
        _wait_for(lambda: _records(out) or proc.poll() is not None, "the first shard record")
        workers = _children(proc.pid)  # the pool's workers and multiprocessing's resource tracker
        proc.send_signal(sig)
        proc.wait(timeout=PATIENCE_S)
        assert not (out / MANIFEST).exists(), \
            f"the run ended before the signal (exit {proc.returncode}): {log.read_text()}"
        # no process of the killed run lives on (they held the caller's stdout forever)
        _wait_for(lambda: not any(_alive(p) for p in workers), f"the workers {sorted(workers)} to end")
    finally:
        for pid in [proc.pid, *workers]:  # only if the test failed: leave nothing behind
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
        proc.wait()
    recorded, files = _records(out), _shard_files(out)
    total = len(uninterrupted) - 1
    # shards are recorded as they complete: some are, not all (before: none until every shard was done)
    assert 0 < len(recorded) < total
    assert recorded <= files
    # a shard finished but not yet recorded when the signal came: at most one per worker
    assert len(files - recorded) <= 2, sorted(files - recorded)
    kept = {name: (out / "shards" / f"{name}.h5").stat() for name in recorded}
    rerun = subprocess.run(_cli(out), capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0, rerun.stderr
    for name, before in kept.items():  # a recorded shard is verified and kept, not made again
        after = (out / "shards" / f"{name}.h5").stat()
        assert (after.st_ino, after.st_mtime_ns) == (before.st_ino, before.st_mtime_ns), name
    assert _hashes(out) == uninterrupted
    assert not (out / PROGRESS_DIR).exists()
    assert not [p.name for p in (out / "shards").iterdir() if p.name.startswith(".")]


# the small in-process job of the next tests
SMALL = PairConfig(sensor_shape=(24, 32), crop_shape=(16, 16), crops_per_image=2, windows_s=(0.25, 1.0),
                   shard_size=4, seed=11, splits=(0.6, 0.2, 0.2))


def test_interrupted_with_every_shard_recorded_finishes_with_workers(tmp_path, monkeypatch):
    """Killed after the last shard record, before the manifest: a re-run with workers only writes it."""
    import evnoise.generators.dataset as dataset

    reference = tmp_path / "ref"
    make_dataset(DeadLeaves(5), reference, SMALL, workers=1)
    out = tmp_path / "ds"

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(dataset, "_manifest", killed)
        with pytest.raises(KeyboardInterrupt):
            make_dataset(DeadLeaves(5), out, SMALL, workers=1)
    assert not (out / MANIFEST).exists() and len(_records(out)) == len(_shard_files(out)) > 0
    result = make_dataset(DeadLeaves(5), out, SMALL, workers=2)  # was: "max_workers must be greater than 0"
    assert result.generated == [] and len(result.reused) == len(_shard_files(out))
    assert _hashes(out) == _hashes(reference)
    assert not (out / PROGRESS_DIR).exists()


@pytest.mark.parametrize("samples", ["4", -1, 10**6, None, True])
def test_a_record_with_a_bad_pair_count_is_made_again(tmp_path, samples):
    """A record whose file checks out but whose pair count is not a whole number the shard can hold (a hand-edited
    or hostile manifest) was kept, and its count summed into the totals: a TypeError traceback, or a manifest with
    wrong totals. Now the shard is made again."""
    import json

    reference = tmp_path / "ref"
    make_dataset(DeadLeaves(5), reference, SMALL, workers=1)
    out = tmp_path / "ds"
    make_dataset(DeadLeaves(5), out, SMALL, workers=1)
    manifest = json.loads((out / MANIFEST).read_text())
    manifest["shards"][0]["samples"] = samples
    (out / MANIFEST).write_text(json.dumps(manifest))
    (out / manifest["shards"][1]["file"]).unlink()  # something to make: the manifest is written again
    result = make_dataset(DeadLeaves(5), out, SMALL, workers=1, progress=True)
    assert manifest["shards"][0]["name"] in result.generated
    assert _hashes(out) == _hashes(reference)


#: a caller whose workers never finish their shard: the interruption must not wait for them
STUCK_SCRIPT = """
import os, signal, sys, threading, time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evnoise.generators import PairConfig, make_dataset


@dataclass(frozen=True)
class StuckSource:
    marks: str
    kind = "stuck"

    def items(self):
        return [f"stuck/{k}" for k in range(6)]

    def load(self, item_id, ctx):
        Path(self.marks, str(os.getpid())).touch()  # this worker is inside its shard, its file open
        time.sleep(3600)
        return np.full(ctx.sensor_shape, 0.5), "display"

    def spec(self):
        return {"kind": self.kind}


if __name__ == "__main__":
    out, marks = Path(sys.argv[1]), Path(sys.argv[2])

    def interrupt_when_both_workers_are_stuck():
        while len(list(marks.iterdir())) < 2:
            time.sleep(0.01)
        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C (in a notebook too: the kernel gets SIGINT)

    threading.Thread(target=interrupt_when_both_workers_are_stuck, daemon=True).start()
    config = PairConfig(sensor_shape=(24, 32), crop_shape=(16, 16), windows_s=(0.25,), shard_size=1, seed=3)
    try:
        make_dataset(StuckSource(str(marks)), out, config, workers=2)
    except KeyboardInterrupt:
        print("interrupted")
"""


def test_interrupted_library_call_ends_its_stuck_workers_and_their_temporaries(tmp_path):
    """An interruption ends the pool's workers instead of waiting for their shards (a worker inside a
    shard that never ends kept ``make_dataset`` waiting for ever), and removes the files they had open."""
    script, out, marks = tmp_path / "stuck.py", tmp_path / "ds", tmp_path / "marks"
    script.write_text(STUCK_SCRIPT)
    marks.mkdir()
    done = subprocess.run([sys.executable, os.fspath(script), os.fspath(out), os.fspath(marks)],
                          capture_output=True, text=True, timeout=PATIENCE_S)
    workers = [int(p.name) for p in marks.iterdir()]
    assert len(workers) == 2 and done.returncode == 0 and done.stdout.strip() == "interrupted", done.stderr
    assert not any(_alive(pid) for pid in workers)
    assert not list((out / "shards").iterdir())  # no shard, no temporary
    assert not (out / MANIFEST).exists()


def _dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


@pytest.mark.parametrize("complete", [True, False], ids=["finished-dataset", "interrupted"])
def test_stale_temporaries_are_removed_only_inside_out_and_only_of_dead_writers(tmp_path, monkeypatch, complete):
    import evnoise.generators.dataset as dataset

    out = tmp_path / "ds"
    if complete:
        make_dataset(DeadLeaves(5), out, SMALL, workers=1)
    else:
        with monkeypatch.context() as m:
            m.setattr(dataset, "_manifest", lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt()))
            with pytest.raises(KeyboardInterrupt):
                make_dataset(DeadLeaves(5), out, SMALL, workers=1)
    dead = _dead_pid()
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    zombie = subprocess.Popen([sys.executable, "-c", "pass"])  # ends, and is not reaped until the end
    _wait_for(lambda: Path(f"/proc/{zombie.pid}").exists() and not _alive(zombie.pid), "a zombie child")
    try:
        live = sleeper.pid
        stale = [out / "shards" / f".train-00000.h5.{dead}-0a1b2c3d.tmp",  # a shard of a SIGKILLed worker
                 out / "shards" / f".val-00000.h5.{dead}.tmp",  # the older naming
                 out / f".manifest.json.{dead}-deadbeef.tmp",
                 # a worker of a SIGKILLed run that its new parent (a container's PID 1) has not reaped yet
                 out / "shards" / f".test-00000.h5.{zombie.pid}-0a1b2c3d.tmp"]
        if not complete:
            stale.append(out / PROGRESS_DIR / f".train-00000.done.json.{dead}-00ff00ff.tmp")
        kept = [out / "shards" / f".train-00001.h5.{live}-0a1b2c3d.tmp",  # its writer is still at work
                out / "shards" / "notes.tmp",  # not evnoise's naming
                tmp_path / f".x.h5.{dead}-0a1b2c3d.tmp"]  # outside --out
        for p in stale + kept:
            p.write_bytes(b"partial")
        victim = tmp_path / "victim.txt"
        victim.write_text("keep")
        link = out / f".preview.png.{dead}-12345678.tmp"  # a link named like a temporary: not followed, kept
        link.symlink_to(victim)
        result = make_dataset(DeadLeaves(5), out, SMALL.replace(seed=None), workers=1)
        assert (out / MANIFEST).exists()
        assert result.generated == []
        for p in stale:
            assert not p.exists(), p
        for p in kept:
            assert p.read_bytes() == b"partial", p
        assert link.is_symlink() and victim.read_text() == "keep"
    finally:
        sleeper.kill()
        sleeper.wait()
        zombie.wait()


# --------------------------------------------------------------------------------------
# LZF shards: the same bytes every time
# --------------------------------------------------------------------------------------
def test_lzf_shards_are_byte_identical_between_runs_and_encoded_deterministically(tmp_path):
    """h5py's LZF encoder leaves its hash table uninitialised: now and then a shard (and so the manifest)
    differed between two identical runs. Shards' LZF chunks are now encoded by evnoise (lzf_chunk), whose
    output is a function of the chunk alone; h5py's filter decodes them."""
    import h5py

    from evnoise.generators.shards import lzf_chunk

    config = SMALL.replace(compression="lzf")
    assert PairConfig().compression == "lzf"  # the default
    make_dataset(DeadLeaves(5), tmp_path / "a", config, workers=1)
    make_dataset(DeadLeaves(5), tmp_path / "b", config, workers=2)
    first = _hashes(tmp_path / "a")
    assert _hashes(tmp_path / "b") == first
    checked = 0
    for shard in sorted((tmp_path / "a" / "shards").glob("*.h5")):
        with h5py.File(shard, "r") as f:
            for name in ("counts", "image"):
                ds = f[name]
                assert ds.compression == "lzf" and ds.shuffle
                for row in range(ds.shape[0]):
                    mask, stored = ds.id.read_direct_chunk((row,) + (0,) * (ds.ndim - 1))
                    data, skipped = lzf_chunk(ds[row])  # decoded by h5py's filter, encoded again here
                    assert (stored, bool(mask)) == (data, skipped), (shard.name, name, row)
                    checked += 1
    assert checked > 0


def test_lzf_chunk_depends_on_the_data_alone_and_round_trips(tmp_path):
    import threading

    import h5py
    import numpy as np

    from evnoise.generators.shards import ShardWriter, lzf_chunk

    rng = np.random.default_rng(3)
    counts = rng.poisson(0.4, size=(2, 24, 32)).astype(np.uint16)
    first = lzf_chunk(counts)
    lzf_chunk(rng.poisson(0.4, size=(2, 24, 32)).astype(np.uint16))  # other data before: no trace of it
    in_thread = []
    thread = threading.Thread(target=lambda: in_thread.append(lzf_chunk(counts)))
    thread.start()
    thread.join()
    assert lzf_chunk(counts) == first == in_thread[0] and not first[1]
    noise = rng.integers(0, 1 << 32, size=(24, 32), dtype=np.uint32).view(np.float32)  # random bits: incompressible
    assert lzf_chunk(noise)[1]
    path = tmp_path / "s.h5"
    with ShardWriter(path, (24, 32), "lzf", {}) as w:
        index = w.add_image(noise)
        w.append(counts, (0, 0, 48, 64), source="x", crop_index=0, window_s=1.0, window_us=1_000_000, lux_scale=1.0,
                 max_lux=1.0, contrast_gamma=1.0, seed=1, saturated=0, image_index=index)
        w.close()
    with h5py.File(path, "r") as f:
        assert np.array_equal(f["counts"][0], counts) and f["image"][0].tobytes() == noise.tobytes()
        assert f["image"].id.read_direct_chunk((0, 0, 0))[0] != 0  # the LZF filter skipped for this chunk
