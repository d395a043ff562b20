"""make-dataset on sources that yield nothing: an error, and no folder that looks like a dataset."""

from __future__ import annotations

import pytest

from evnoise.cli import main


@pytest.fixture
def unreadable_images(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    (folder / "a.png").write_bytes(b"not an image")
    (folder / "b.jpg").write_bytes(b"\xff\xd8 truncated")
    return folder


def test_only_unreadable_images_is_an_error_and_leaves_nothing(unreadable_images, tmp_path, capsys):
    out = tmp_path / "ds"
    code = main(["make-dataset", str(unreadable_images), "--out", str(out), "--crop", "64", "-q", "--seed", "1"])
    err = capsys.readouterr().err
    assert code == 2
    assert "no pair could be made" in err and "a.png" in err
    assert not out.exists()


def test_existing_empty_folder_is_kept_but_holds_no_manifest(unreadable_images, tmp_path, capsys):
    out = tmp_path / "ds"
    out.mkdir()
    code = main(["make-dataset", str(unreadable_images), "--out", str(out), "--crop", "64", "-q", "--seed", "1"])
    assert code == 2
    assert out.is_dir()
    assert not (out / "manifest.json").exists()
    assert not (out / "shards").exists()


def test_info_json_of_a_dataset_has_numbers_not_text(tmp_path, capsys):
    """Issue 17: ``info --json`` wrote ``"size": "69.4 kB"``; numbers are JSON numbers, units in the keys."""
    import json

    out = tmp_path / "dl"
    assert main(["make-dataset", "--procedural", "dead-leaves", "--count", "4", "--crop", "64", "--out", str(out),
                 "--seed", "1", "-q"]) == 0
    capsys.readouterr()
    assert main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert "size" not in info
    assert isinstance(info["size_bytes"], int) and info["size_bytes"] == sum(
        p.stat().st_size for p in (out / "shards").iterdir())
    assert info["windows_s"] == [1.0]
    assert sum(v["pairs"] for v in info["splits"].values()) == info["pairs"] == 4


@pytest.mark.parametrize("content, why", [("objects", "holds Python objects"), ("garbage", "not a NumPy .npz archive")])
def test_train_on_a_bad_npz_names_the_problem_not_numpys_pickle_advice(tmp_path, capsys, content, why):
    """Issue 17 follow-up: numpy's "allow_pickle" / "pickle.load()" advice leaked into the one error line."""
    pytest.importorskip("torch")
    import numpy as np

    bad = tmp_path / "pairs.npz"
    if content == "objects":
        np.savez(bad, counts=np.array([{"x": 1}], dtype=object))
    else:
        bad.write_bytes(b"garbage, not a zip archive")
    code = main(["train", str(bad), "--out", str(tmp_path / "m.pt")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert why in err and "pickle" not in err
    assert not (tmp_path / "m.pt").exists()


def _tiny_dataset(tmp_path, capsys):
    out = tmp_path / "dl"
    assert main(["make-dataset", "--procedural", "dead-leaves", "--count", "2", "--crop", "64", "--out", str(out),
                 "--seed", "1", "-q"]) == 0
    capsys.readouterr()
    return out, sorted((out / "shards").glob("*.h5"))[0]


@pytest.mark.parametrize("damage", ["external link", "external storage", "declared column"])
def test_a_shard_that_points_outside_itself_or_declares_too_much_is_refused(tmp_path, capsys, damage):
    """A shard's datasets are read only from the shard itself (as an events.h5 file's: no external links, external
    storage or virtual datasets), and a metadata column's declared length is checked before it is read."""
    import h5py
    import numpy as np

    out, shard = _tiny_dataset(tmp_path, capsys)
    secret = tmp_path / "secret.bin"
    secret.write_bytes(np.arange(64, dtype=np.float64).tobytes())
    with h5py.File(shard, "r+") as f:
        if damage == "external link":
            with h5py.File(tmp_path / "other.h5", "w") as g:
                g["c"] = np.zeros_like(f["counts"][()])
            del f["counts"]
            f["counts"] = h5py.ExternalLink(str(tmp_path / "other.h5"), "c")
        elif damage == "external storage":
            n = f["window_s"].shape[0]
            del f["window_s"]
            f.create_dataset("window_s", shape=(n,), dtype=np.float64, external=[(str(secret), 0, 8 * n)])
        else:
            del f["window_s"]
            f.create_dataset("window_s", shape=(10**10,), dtype=np.float64, chunks=(1024,))
    code = main(["info", str(out)])
    err = capsys.readouterr().err.strip()
    assert code != 0 and len(err.splitlines()) == 1, err
    assert shard.name in err and ("another file" in err or "external file" in err or "shape" in err), err


def _good_npz_arrays():
    import numpy as np

    return {"counts": np.ones((2, 2, 4, 4), np.uint16), "images": np.ones((2, 4, 4), np.float32),
            "window_s": np.ones(2)}


@pytest.mark.parametrize("change, expect", [
    ({"params_json": "not json"}, "params_json, max_lux or window_s"),
    ({"max_lux": [1.0, 2.0]}, "params_json, max_lux or window_s"),
    ({"window_s": ["a", "b"]}, "params_json, max_lux or window_s"),
    ({"counts": 3}, "counts must be (N, 2, h, w)"),
    ({"counts": "nan"}, "counts must be whole numbers >= 0"),
    ({"counts": "huge header"}, "declares shape (1000000000000,)"),
])
def test_a_damaged_npz_pairs_file_is_one_clear_error(tmp_path, change, expect):
    """Found by a hostile-file review: tracebacks (JSON, TypeError), a 7 TiB allocation from a header's declared
    shape, and NaN counts silently read as 0."""
    import io
    import zipfile

    import numpy as np

    from evnoise.errors import InputError
    from evnoise.reconstruct.data import NpzPairs

    arrays = _good_npz_arrays()
    key, value = next(iter(change.items()))
    if value == "nan":
        arrays["counts"] = np.full((2, 2, 4, 4), np.nan)
    elif value != "huge header":
        arrays[key] = np.asarray(value)
    path = tmp_path / "pairs.npz"
    np.savez(path, **arrays)
    if value == "huge header":  # a member whose header declares 10**12 values over a few bytes of data
        buf = io.BytesIO()
        np.lib.format.write_array_header_1_0(buf, {"descr": "<f8", "fortran_order": False, "shape": (10**12,)})
        with zipfile.ZipFile(path, "a") as z:
            z.writestr("sources.npy", buf.getvalue() + b"\0" * 64)
    with pytest.raises(InputError, match=re_escape(expect)):
        NpzPairs(path)


def re_escape(text):
    import re

    return re.escape(text)


def test_an_npz_pairs_file_reads_only_its_own_arrays(tmp_path):
    """Only the pairs' own arrays are read (NPZ_KEYS): an archive with another member still reads as pairs."""
    import numpy as np

    from evnoise.reconstruct.data import NpzPairs

    path = tmp_path / "pairs.npz"
    np.savez_compressed(path, extra=np.zeros(10**8, np.uint8), **_good_npz_arrays())
    pairs = NpzPairs(path)
    assert len(pairs) == 2 and pairs[0]["counts"].shape == (2, 4, 4)


@pytest.mark.parametrize("damage", [("format_version", "abc"), ("format_version", [1]), ("config", None),
                                    ("totals", "x"), ("pair", {"counts": {"shape": [2, 3], "binning": 2}}),
                                    ("skipped", 5), ("splits", {"bogus": {}})])
def test_a_damaged_manifest_is_one_error_line_naming_it(tmp_path, capsys, damage):
    """Found by a hostile-file review: ValueError, TypeError and KeyError tracebacks from info and the reader."""
    import json

    out, _ = _tiny_dataset(tmp_path, capsys)
    manifest = out / "manifest.json"
    data = json.loads(manifest.read_text())
    key, value = damage
    if value is None:
        del data[key]
    else:
        data[key] = value
    manifest.write_text(json.dumps(data))
    code = main(["info", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert "manifest.json is damaged" in err, err


def test_a_failure_before_any_shard_is_made_leaves_no_folder_it_created(tmp_path, capsys, monkeypatch):
    """A new output folder whose first shard fails (here the disk fills while the first image is stored) is
    removed with its empty ``shards/`` and progress files: nothing was made, nothing looks like a dataset."""
    from evnoise.errors import OutputError
    from evnoise.generators import shards

    def disk_full(self, image):
        self.abort()
        raise OutputError(f"writing shard {self.path} failed: No space left on device")

    monkeypatch.setattr(shards.ShardWriter, "add_image", disk_full)
    out = tmp_path / "ds"
    code = main(["make-dataset", "--procedural", "dead-leaves", "--count", "2", "--crop", "64", "--out", str(out),
                 "--seed", "1", "-q", "--workers", "1"])
    assert code != 0
    assert "No space left on device" in capsys.readouterr().err
    assert not out.exists()


def test_a_failure_before_any_shard_keeps_a_folder_the_user_made(tmp_path, capsys, monkeypatch):
    from evnoise.errors import OutputError
    from evnoise.generators import shards

    def disk_full(self, image):
        self.abort()
        raise OutputError(f"writing shard {self.path} failed: No space left on device")

    monkeypatch.setattr(shards.ShardWriter, "add_image", disk_full)
    out = tmp_path / "ds"
    out.mkdir()
    code = main(["make-dataset", "--procedural", "dead-leaves", "--count", "2", "--crop", "64", "--out", str(out),
                 "--seed", "1", "-q", "--workers", "1"])
    assert code != 0
    capsys.readouterr()
    assert out.is_dir() and list(out.iterdir()) == [] or sorted(p.name for p in out.iterdir()) == [".evnoise-progress"]


#: What h5py raises on a full disk: HDF5's text over two lines, naming the temporary file and the errno.
_HDF5_FULL = ("{what} (file write failed: time = Sun Nov 29 08:37:19 2026\n, filename = '{name}', file descriptor = 4, "
              "errno = 28, error message = 'No space left on device', buf = 0x561e54988918, total write size = 96, "
              "bytes this sub-write = 96, offset = 0)")


@pytest.mark.parametrize("stage", ["create", "layout", "flush"])
def test_a_full_disk_while_writing_a_shard_is_one_clean_line_and_leaves_no_dataset(tmp_path, capsys, monkeypatch,
                                                                                     stage):
    """A full disk met by h5py when the shard file is created (OSError), while its datasets are laid out (OSError)
    or at its last flush (RuntimeError): one line with the errno's text and the shard's name, not HDF5's two-line
    text (printed with a literal \\n) nor a traceback; nothing is left that looks like a dataset."""
    import errno

    import h5py

    real_file = h5py.File

    def create(name, mode="r", *args, **kwargs):
        if mode == "w-":
            raise OSError(errno.ENOSPC, _HDF5_FULL.format(what="Unable to synchronously create file", name=name))
        return real_file(name, mode, *args, **kwargs)

    def layout(self, name, *args, **kwargs):
        text = _HDF5_FULL.format(what="Unable to synchronously create dataset", name=self.file.filename)
        raise OSError(errno.ENOSPC, text)

    def flush(self):
        raise RuntimeError(_HDF5_FULL.format(what="Can't flush cache", name=self.filename))

    if stage == "create":
        monkeypatch.setattr(h5py, "File", create)
    elif stage == "layout":
        monkeypatch.setattr(h5py.Group, "create_dataset", layout)
    else:
        monkeypatch.setattr(h5py.File, "flush", flush)
    out = tmp_path / "ds"
    code = main(["make-dataset", "--procedural", "dead-leaves", "--count", "2", "--crop", "64", "--out", str(out),
                 "--seed", "1", "-q", "--workers", "1"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, (code, err)
    assert err.startswith("evnoise: error: ") and "No space left on device" in err, err
    assert str(out / "shards") in err and ".h5" in err, err
    for inner in ("\\n", "errno =", ".tmp", "filename =", "Traceback"):
        assert inner not in err, err
    assert not out.exists()  # nothing was made: the folder this run created is gone (no temporary file either)
