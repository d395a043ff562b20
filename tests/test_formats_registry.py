"""One home per file format (issue 30, item 4): ``evnoise.formats.FORMATS``.

A toy format registered at run time must be detected, read and written through its entry alone,
and show in every table derived from the registry (suffixes, OUTPUT_FORMATS, the command line's
choices and help); importing the registry imports no reader. The modules this work touched form
no import cycle (an AST walk that counts imports inside functions too).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import evnoise as ev
from evnoise import formats
from evnoise.errors import InputError, ParameterError
from evnoise.events import make_events
from evnoise.readers import EventSource

ROOT = Path(__file__).resolve().parents[1]
TOY_MAGIC = b"TOYEV1\n"
TOY_RECORD = np.dtype([("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])


class ToySource(EventSource):
    """Reader of the toy format: magic, then ``<u2`` width and height, then fixed records."""

    format = "toy"

    def __init__(self, path, *, sensor=None):
        super().__init__(path, sensor=sensor)
        with open(self.path, "rb") as fh:
            fh.read(len(TOY_MAGIC))
            width, height = np.frombuffer(fh.read(4), "<u2")
        self._set_shape((int(height), int(width)))

    def _chunks(self, t_start_us, t_end_us):
        rec = np.fromfile(self.path, TOY_RECORD, offset=len(TOY_MAGIC) + 4)
        if rec.size:
            yield make_events(rec["t"], rec["x"], rec["y"], rec["p"])


class ToyWriter:
    """Writer of the toy format (not atomic: enough for the test)."""

    instances = 0

    def __init__(self, path, shape, attrs=None, *, overwrite=False, compression=None, t_end_us=None,
                 t_offset_us=None):
        ToyWriter.instances += 1
        self.path = Path(path)
        self._fh = open(self.path, "wb")
        self._fh.write(TOY_MAGIC + np.array([shape[1], shape[0]], "<u2").tobytes())

    def write(self, events):
        rec = np.empty(events.size, TOY_RECORD)
        for k in "txyp":
            rec[k] = events[k]
        self._fh.write(rec.tobytes())

    def close(self):
        self._fh.close()
        return self.path

    def abort(self):
        self._fh.close()
        self.path.unlink(missing_ok=True)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *exc):
        self.close() if exc_type is None else self.abort()
        return False


TOY = formats.FileFormat("toy", (".toy",), "toy events", magic=(TOY_MAGIC,), reader=ToySource, writer=ToyWriter,
                         clock="µs from the start")


@pytest.fixture
def toy():
    formats.register(TOY)
    try:
        yield TOY
    finally:
        formats.unregister("toy")


def _events():
    return make_events(np.array([5, 17, 40]), np.array([1, 2, 3]), np.array([0, 1, 2]), np.array([1, 0, 1]))


def test_a_registered_format_is_written_detected_and_read_through_its_entry(tmp_path, toy):
    from evnoise.io import OUTPUT_FORMATS, output_format
    from evnoise.readers import SUFFIXES, detect_format, is_event_file, open_events

    path = tmp_path / "a.toy"
    assert output_format(path) == "toy" and OUTPUT_FORMATS[".toy"] == "toy"
    before = ToyWriter.instances
    ev.write_events(path, _events(), (4, 6))
    assert ToyWriter.instances == before + 1
    assert SUFFIXES[".toy"] == ("toy",) and is_event_file(path)
    assert detect_format(path) == "toy"
    with open_events(path) as src:
        assert isinstance(src, ToySource) and src.shape == (4, 6)
    events, meta = ev.read_events(path, t_start_us=10)
    np.testing.assert_array_equal(events["t"], [17, 40])
    assert meta["format"] == "toy" and meta["sensor"] == "6x4"
    assert formats.describe("toy") == "toy events" and formats.clock_note("toy") == "µs from the start"


def test_detection_checks_the_magic_bytes_of_a_registered_format(tmp_path, toy):
    from evnoise.readers import detect_format

    fake = tmp_path / "b.toy"
    fake.write_bytes(b"not toy at all")
    with pytest.raises(InputError, match="not a valid toy events file"):
        detect_format(fake)
    renamed = tmp_path / "c.csv"
    renamed.write_bytes(TOY_MAGIC + b"\x01\x00\x01\x00")
    with pytest.raises(InputError, match="the content is toy events but the suffix .csv says"):
        detect_format(renamed)


def test_the_command_line_choices_and_help_come_from_the_registry(toy):
    assert formats.output_format_names()[-1] == "toy"
    assert ".toy" in formats.output_formats_help() and "toy events" in formats.output_formats_help()


def test_unregistering_removes_the_format_everywhere(tmp_path):
    formats.register(TOY)
    formats.unregister("toy")
    from evnoise.io import OUTPUT_FORMATS

    assert ".toy" not in OUTPUT_FORMATS and "toy" not in formats.output_format_names()
    with pytest.raises(ParameterError, match="unknown event file suffix '.toy'"):
        ev.write_events(tmp_path / "x.toy", _events(), (4, 6))


def test_a_format_name_is_registered_once():
    with pytest.raises(ValueError, match="already registered"):
        formats.register(formats.FileFormat("csv", (".csv2",), "another CSV"))


def test_the_built_in_tables():
    assert formats.output_format_names() == ("h5", "aedat4", "evt3", "dat", "es", "csv")
    assert formats.output_formats() == {".h5": "h5", ".hdf5": "h5", ".aedat4": "aedat4", ".raw": "evt3",
                                        ".dat": "dat", ".es": "es", ".csv": "csv"}
    assert formats.input_suffixes()[".aedat"] == ("aedat2", "aedat4")  # jAER's format first
    assert formats.format_for_suffix("rec.TXT").name == "csv" and formats.format_for_suffix("x.png") is None
    assert formats.describe("evt2.1") == "Prophesee RAW EVT 2.1"


def test_every_reader_and_writer_named_in_the_registry_exists():
    for f in formats.FORMATS:
        for target in (f.reader, f.writer, f.probe):
            if target is not None:
                assert callable(formats.resolve(target)), (f.name, target)


def test_importing_the_registry_imports_no_reader_or_writer():
    code = ("import sys, evnoise.formats; "
            "print(sorted(m for m in sys.modules if m.startswith(('evnoise.readers', 'evnoise.io', 'h5py', 'faery'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "[]"


# import cycles through these modules: tests/test_one_home.py::test_no_import_cycle_anywhere walks the whole tree
