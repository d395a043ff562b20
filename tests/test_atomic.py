"""AtomicFile: the one home of temporary-name / rename / remove used by every writer."""

import pytest

from evnoise._atomic import AtomicFile, atomic_output
from evnoise.errors import OutputError


def test_commit_renames_and_leaves_nothing_else(tmp_path):
    out = AtomicFile(tmp_path / "a.txt", what="thing")
    out.create()
    out.tmp.write_text("hello")
    assert out.tmp.name.startswith(".a.txt.") and out.tmp.name.endswith(".tmp")
    assert not (tmp_path / "a.txt").exists()
    out.commit()
    assert out.done
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]
    assert (tmp_path / "a.txt").read_text() == "hello"


def test_refuses_a_file_that_appeared_and_discard_removes_tmp(tmp_path):
    out = AtomicFile(tmp_path / "a.txt", overwrite=False, what="thing")
    out.create()
    (tmp_path / "a.txt").write_text("other")
    with pytest.raises(OutputError, match="thing .*a.txt appeared while writing; not replacing it"):
        out.commit()
    out.discard()
    out.discard()  # twice is harmless
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]
    assert (tmp_path / "a.txt").read_text() == "other"


def test_create_in_missing_folder_is_one_clean_error(tmp_path):
    out = AtomicFile(tmp_path / "no" / "a.txt", what="thing")
    with pytest.raises(OutputError, match="cannot write thing"):
        out.create()


def test_suffix_and_atomic_output_failure(tmp_path):
    assert AtomicFile(tmp_path / "p.png", suffix=".tmp.png").tmp.name.endswith(".tmp.png")
    with pytest.raises(RuntimeError):
        with atomic_output(tmp_path / "b.txt") as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
