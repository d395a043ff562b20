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
