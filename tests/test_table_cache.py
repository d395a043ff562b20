"""Issue 33, part 2: the closed form's Chebyshev tables persist on disk, verified on load, never trusted.

Every test points ``EVNOISE_CACHE`` at its own temporary folder.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from evnoise import _cache
from evnoise._kernels import chebyshev

C = float(np.expm1(0.17))
B = 42.0
UNITS = (-40, 16)
#: photon counts in three unit panels (one of them rippled enough to be subdivided)
LAM = np.concatenate([np.linspace(0.2, 0.36, 50), np.linspace(3.0, 7.0, 200), np.linspace(150.0, 400.0, 200)])


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("EVNOISE_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("EVNOISE_TABLE_CACHE", raising=False)
    return tmp_path / "cache" / "tables"


def _table():
    return chebyshev.LogPTable(C, B, *UNITS)


def _no_build(monkeypatch):
    def fail(*args):
        raise AssertionError("a unit was built although the cache holds it")

    monkeypatch.setattr(chebyshev, "build_unit_panel", fail)


def _fresh_values():
    """Values of a table built here, with the cache off."""
    old = os.environ.get("EVNOISE_TABLE_CACHE")
    os.environ["EVNOISE_TABLE_CACHE"] = "0"
    try:
        table = _table()
        return table.evaluate(LAM), table
    finally:
        if old is None:
            del os.environ["EVNOISE_TABLE_CACHE"]
        else:
            os.environ["EVNOISE_TABLE_CACHE"] = old


def _same_arrays(a, b):
    return all(np.array_equal(x.view(np.uint8), y.view(np.uint8)) for x, y in zip(a, b))


def test_cache_folder_follows_the_environment(tmp_path, monkeypatch):
    monkeypatch.delenv("EVNOISE_TABLE_CACHE", raising=False)
    monkeypatch.setenv("EVNOISE_CACHE", str(tmp_path / "a"))
    assert _cache.table_cache_dir() == tmp_path / "a" / "tables"
    monkeypatch.delenv("EVNOISE_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert _cache.table_cache_dir() == tmp_path / "xdg" / "evnoise" / "tables"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert _cache.table_cache_dir() == Path.home() / ".cache" / "evnoise" / "tables"
    for off in ("0", "off", "OFF", "no", "false"):
        monkeypatch.setenv("EVNOISE_TABLE_CACHE", off)
        assert _cache.table_cache_dir() is None


def test_loaded_table_is_bit_identical_to_a_built_one(cache, monkeypatch):
    fresh, built = _fresh_values()
    assert not cache.exists()  # the cache was off
    first = _table()
    assert np.array_equal(first.evaluate(LAM), fresh)
    files = list(cache.glob("table-*.npz"))
    assert len(files) == 1 and not list(cache.glob(".*"))  # no temporary file left
    _no_build(monkeypatch)
    loaded = _table()
    values = loaded.evaluate(LAM)
    assert np.array_equal(values.view(np.uint64), fresh.view(np.uint64))
    assert _same_arrays(loaded._arrays, built._arrays)
    assert np.isfinite(values).all()


def test_units_are_added_to_the_file(cache, monkeypatch):
    _table().evaluate(LAM[:50])
    _table().evaluate(LAM)  # reads the first unit, builds two more, writes all three
    _no_build(monkeypatch)
    table = _table()
    table.evaluate(LAM)
    assert sorted(table._units) == sorted({int(u) for u in np.floor(np.log(LAM))})


def _corrupt_variants(path: Path):
    """``(name, bytes)`` of files that must not be trusted, made from the valid file at ``path``."""
    good = path.read_bytes()
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    key_text = str(arrays["key"][()])
    names = ("units", "unit_start", "bounds", "coef")

    def npz_bytes(changed, fix_checksum):
        a = {k: v.copy() for k, v in arrays.items()}
        a.update(changed)
        if fix_checksum:
            a["checksum"] = np.array(_cache._checksum(key_text, {k: a[k] for k in names}))
        out = path.with_suffix(".tmpvariant")
        with open(out, "wb") as fh:
            np.savez(fh, **a)
        data = out.read_bytes()
        out.unlink()
        return data

    coef = arrays["coef"].copy()
    coef[0, 3] = np.nextafter(coef[0, 3], np.inf)  # one ulp
    gap = arrays["bounds"].copy()
    gap[0, 1] = np.nextafter(gap[0, 1], -np.inf)
    nan = arrays["coef"].copy()
    nan[0, 0] = np.nan
    other_key = key_text.replace('"format":', '"formar":')
    return [
        ("garbage", b"not a table at all" * 10),
        ("empty", b""),
        ("truncated", good[: len(good) // 2]),
        ("one ulp changed, old checksum", npz_bytes({"coef": coef}, False)),
        ("panels with a gap, checksum recomputed", npz_bytes({"bounds": gap}, True)),
        ("a NaN coefficient, checksum recomputed", npz_bytes({"coef": nan}, True)),
        ("another key", npz_bytes({"key": np.array(other_key)}, False)),
        ("a pickle inside", npz_bytes({"units": np.array([object()], dtype=object)}, False)),
    ]


def test_a_corrupt_or_foreign_file_is_ignored_and_rebuilt(cache):
    fresh, _ = _fresh_values()
    _table().evaluate(LAM)
    (path,) = cache.glob("table-*.npz")
    for name, data in _corrupt_variants(path):
        path.write_bytes(data)
        built = []
        real = chebyshev.build_unit_panel

        def counting(*args, built=built, real=real):
            built.append(args[0])
            return real(*args)

        chebyshev.build_unit_panel = counting
        try:
            values = _table().evaluate(LAM)
        finally:
            chebyshev.build_unit_panel = real
        assert built, name  # not trusted: built again
        assert np.array_equal(values.view(np.uint64), fresh.view(np.uint64)), name
        # and the file was replaced by a valid one
        assert _cache.load_arrays(_table().cache_key(), ("units", "unit_start", "bounds", "coef")) is not None, name


def test_a_file_for_another_threshold_is_not_read(cache, monkeypatch):
    _table().evaluate(LAM)
    (path,) = cache.glob("table-*.npz")
    other = chebyshev.LogPTable(float(np.expm1(0.2)), B, *UNITS)
    path.rename(_cache.table_path(other.cache_key(), cache))
    assert other._read_disk() == {}


def test_opt_out_writes_nothing(cache, monkeypatch):
    monkeypatch.setenv("EVNOISE_TABLE_CACHE", "off")
    _table().evaluate(LAM)
    assert not cache.exists()


def test_an_unwritable_cache_is_only_slower(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache folder would be")
    monkeypatch.setenv("EVNOISE_CACHE", str(blocker))
    monkeypatch.delenv("EVNOISE_TABLE_CACHE", raising=False)
    fresh, _ = _fresh_values()
    assert np.array_equal(_table().evaluate(LAM), fresh)


def test_key_names_what_the_table_depends_on():
    key = _table().cache_key()
    for field in ("evnoise", "source", "numpy", "numba", "llvmlite", "machine", "cpu", "c", "b", "degree"):
        assert field in key
    assert key["c"] == C.hex() and key != chebyshev.LogPTable(C, B + 1.0, *UNITS).cache_key()


_WRITER = """
import sys
import numpy as np
from evnoise._kernels import chebyshev
c, b, lo, hi = float(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])
chebyshev.LogPTable(c, b, -40, 16).evaluate(np.geomspace(lo, hi, 50))
"""


def test_concurrent_writers_leave_a_valid_file(cache):
    """Processes that build different units of one table at once: the file is whole, never half-written."""
    env = {**os.environ}
    ranges = [(0.2, 0.36), (3.0, 7.0), (150.0, 400.0), (0.05, 0.1)]
    procs = [subprocess.Popen([sys.executable, "-c", _WRITER, repr(C), repr(B), repr(lo), repr(hi)], env=env)
             for lo, hi in ranges]
    assert all(p.wait(timeout=300) == 0 for p in procs)
    assert not list(cache.glob(".*"))  # every temporary file renamed or removed
    (path,) = cache.glob("table-*.npz")
    arrays = _cache.load_arrays(_table().cache_key(), ("units", "unit_start", "bounds", "coef"))
    assert arrays is not None and chebyshev.arrays_to_units(arrays, *UNITS)
    fresh, _ = _fresh_values()
    assert np.array_equal(_table().evaluate(LAM), fresh)


def _table_names():
    return ("units", "unit_start", "bounds", "coef")


def test_a_file_declaring_more_than_a_table_is_refused_before_it_is_read(cache, monkeypatch):
    """A small file whose members inflate to far more than any table (a zip bomb) is ignored without
    allocating for it: its members' declared sizes are checked first."""
    import zipfile

    _table().evaluate(LAM)
    (path,) = cache.glob("table-*.npz")
    with np.load(path, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, a in arrays.items():
            if name != "coef":
                archive.writestr(f"{name}.npy", _npy_bytes(a))
        archive.writestr("coef.npy", b"\0" * (_cache.MAX_FILE_BYTES * 4))  # inflates to 64 MiB
    assert path.stat().st_size < 1 << 20
    read = []
    monkeypatch.setattr(np, "load", lambda *a, **k: read.append(a) or pytest.fail("np.load reached"))
    assert _cache.load_arrays(_table().cache_key(), _table_names()) is None
    assert not read


def _npy_bytes(a):
    import io

    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def test_a_pipe_or_a_link_at_the_cache_path_is_not_followed(cache, tmp_path):
    """A named pipe is not waited on (the read would block forever) and a link is not followed."""
    _table().evaluate(LAM)
    (path,) = cache.glob("table-*.npz")
    elsewhere = tmp_path / "elsewhere.npz"
    path.rename(elsewhere)
    path.symlink_to(elsewhere)
    assert _cache.load_arrays(_table().cache_key(), _table_names()) is None
    path.unlink()
    os.mkfifo(path)
    # in a child process, so that a regression hangs a process with a time limit, not the test run
    code = ("import sys; from evnoise import _cache; from evnoise._kernels import chebyshev; "
            f"t = chebyshev.LogPTable({C!r}, {B!r}, {UNITS[0]}, {UNITS[1]}); "
            "sys.exit(0 if _cache.load_arrays(t.cache_key(), ('units', 'unit_start', 'bounds', 'coef')) is None "
            "else 1)")
    env = dict(os.environ)
    done = subprocess.run([sys.executable, "-c", code], env=env, timeout=120)
    assert done.returncode == 0


def test_a_failed_write_leaves_no_temporary(cache, monkeypatch):
    def broken(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez", broken)
    with pytest.raises(KeyboardInterrupt):
        _cache.save_arrays(_table().cache_key(), {"units": np.zeros(1)})
    assert not [p for p in cache.iterdir() if p.name.endswith(".tmp")]


def test_the_folder_stays_bounded_and_keeps_the_recently_used_tables(cache, monkeypatch):
    """A sweep over many keys (calibration tries hundreds of thresholds) never grows the folder past its cap:
    the least recently used tables go first (a load marks a table used), stale temporaries go, nothing else."""
    monkeypatch.setattr(_cache, "MAX_TABLE_FILES", 10)
    monkeypatch.setattr(_cache, "PRUNE_TO_FILES", 6)
    arrays = {"units": np.arange(3.0)}
    keys = [{"eps": str(k)} for k in range(10)]
    for age, key in enumerate(keys):  # file k last used 100 - k seconds ago (key 0 the oldest)
        path = _cache.save_arrays(key, arrays)
        os.utime(path, (1e9 + age, 1e9 + age))
    assert len(list(cache.glob("table-*.npz"))) == 10
    assert _cache.load_arrays(keys[0], ("units",)) is not None  # the oldest is used again: now the newest
    stale = cache / f".{_cache.table_path({'x': '1'}, cache).name}.{os.getpid()}-0a1b2c3d.tmp"
    fresh = cache / f".{_cache.table_path({'x': '2'}, cache).name}.{os.getpid()}-0a1b2c3e.tmp"
    for tmp in (stale, fresh):
        tmp.write_bytes(b"partial")
    os.utime(stale, (1e9, 1e9))
    other = cache / "notes.txt"
    other.write_text("not the cache's")
    link = cache / f"table-{'0' * 32}.npz"
    link.symlink_to(other)
    _cache.save_arrays({"eps": "new"}, arrays)  # the 11th table: the folder is pruned to 6
    left = {p.name for p in cache.glob("table-*.npz") if not p.is_symlink()}
    expected = {_cache.table_path(k, cache).name for k in (*keys[6:], keys[0], {"eps": "new"})}
    assert left == expected
    assert not stale.exists() and fresh.exists() and other.read_text() == "not the cache's" and link.is_symlink()
    assert _cache.load_arrays(keys[1], ("units",)) is None  # a removed table is only a miss (rebuilt by its caller)


def test_the_folder_stays_bounded_in_bytes_too(cache, monkeypatch):
    """Few but large tables (certified panels are ~150 kB each) are bounded by size: the least recently used go
    first until the folder is back under the byte bound, whatever the count bound says."""
    arrays = {"units": np.arange(4000.0)}  # ~32 kB a file
    path0 = _cache.save_arrays({"eps": "0"}, arrays)
    size = path0.stat().st_size
    monkeypatch.setattr(_cache, "MAX_TABLE_BYTES", 5 * size + size // 2)  # room for five
    monkeypatch.setattr(_cache, "PRUNE_TO_BYTES", 3 * size + size // 2)  # pruned down to three
    keys = [{"eps": str(k)} for k in range(5)]
    for age, key in enumerate(keys):
        path = _cache.save_arrays(key, arrays)
        os.utime(path, (1e9 + age, 1e9 + age))
    assert len(list(cache.glob("table-*.npz"))) == 5  # key 0 was saved again: five files, under the bound
    _cache.save_arrays({"eps": "new"}, arrays)  # the sixth: over the bound, the three newest stay
    left = {p.name for p in cache.glob("table-*.npz")}
    assert left == {_cache.table_path(k, cache).name for k in (keys[3], keys[4], {"eps": "new"})}
