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


def test_finish_commits_or_aborts_with_one_clean_line(tmp_path):
    out = AtomicFile(tmp_path / "c.bin", what="thing")
    out.create()
    aborted = []

    def abort():
        aborted.append(1)
        out.discard()

    assert out.finish(lambda: out.tmp.write_bytes(b"x"), abort) == tmp_path / "c.bin" and not aborted

    out = AtomicFile(tmp_path / "d.bin", what="thing")
    out.create()

    def failing_close():
        raise OSError("disk  full\nreally")

    with pytest.raises(OutputError, match=r"^cannot finish thing .*d.bin: disk full really$"):
        out.finish(failing_close, abort, one_line=True)
    assert aborted == [1] and sorted(p.name for p in tmp_path.iterdir()) == ["c.bin"]
    with pytest.raises(ValueError):  # not of type `catch`: re-raised as it is, after the abort
        AtomicFile(tmp_path / "e.bin").finish(lambda: (_ for _ in ()).throw(ValueError("x")), abort)
    assert aborted == [1, 1]
