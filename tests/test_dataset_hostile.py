"""Hostile datasets, pairs files and images (a fuzzing review): one clear error, checked before memory is taken."""

from __future__ import annotations

import hashlib
import json
import re
import shutil
import zipfile

import numpy as np
import pytest

from evnoise.cli import main
from evnoise.errors import InputError


@pytest.fixture(scope="module")
def _made_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("made") / "dl"
    assert main(["make-dataset", "--procedural", "dead-leaves", "--count", "2", "--sensor", "128x96", "--crop", "64",
                 "--out", str(out), "--seed", "1", "-q", "--workers", "1"]) == 0
    return out


@pytest.fixture
def dataset(_made_dataset, tmp_path, capsys):
    """A fresh copy of a tiny dataset (pairs of 32x32 binned pixels) to damage."""
    out = tmp_path / "ds"
    shutil.copytree(_made_dataset, out)
    capsys.readouterr()
    return out


def _edit_manifest(root, change) -> None:
    path = root / "manifest.json"
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def _reseal(root, shard) -> None:
    """Give the manifest the shard's new checksum (a hostile dataset is self-consistent)."""
    digest = hashlib.sha256(shard.read_bytes()).hexdigest()

    def change(m):
        for s in m["shards"]:
            if s["file"].endswith(shard.name):
                s["sha256"], s["bytes"] = digest, shard.stat().st_size

    _edit_manifest(root, change)


def _one_error(capsys, argv) -> str:
    code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, (code, err)
    return err


# -- 1. shard bomb: a shard's pairs are checked against the manifest and the budget before they are read ---------
def test_a_shard_whose_pairs_are_larger_than_the_manifest_says_is_refused(dataset, capsys):
    import h5py

    from evnoise.generators import PairDataset

    shard = sorted((dataset / "shards").glob("*.h5"))[0]
    with h5py.File(shard, "r+") as f:
        n = f["counts"].shape[0]
        del f["counts"]
        f.create_dataset("counts", shape=(n, 2, 640, 640), dtype="u2", chunks=(1, 1, 640, 640), compression="gzip")
    _reseal(dataset, shard)
    err = _one_error(capsys, ["info", str(dataset)])
    assert shard.name in err and "(2, 2, 640, 640)" in err and "32, 32" in err, err
    split = shard.name.split("-")[0]
    with pytest.raises(InputError, match=re.escape(shard.name)):
        PairDataset(dataset, split)[0]


def test_a_shard_image_of_another_dtype_or_shape_is_refused(dataset, capsys):
    import h5py

    shard = sorted((dataset / "shards").glob("*.h5"))[0]
    with h5py.File(shard, "r+") as f:
        m = f["image"].shape[0]
        del f["image"]
        f.create_dataset("image", shape=(m, 32, 32), dtype="f8")
    err = _one_error(capsys, ["info", str(dataset)])
    assert shard.name in err and "'image'" in err and "float64" in err, err


def test_a_shard_chunk_over_the_budget_is_refused(dataset, capsys, monkeypatch):
    import h5py

    from evnoise.generators import PairDataset

    shard = sorted((dataset / "shards").glob("*.h5"))[0]
    with h5py.File(shard, "r+") as f:
        counts = f["counts"][()]
        del f["counts"]  # the right shape, but one chunk (decompressed whole on any read) declared 2048x2048
        f.create_dataset("counts", data=counts, maxshape=(None, 2, None, None), chunks=(1, 2, 2048, 2048),
                         compression="gzip")
    monkeypatch.setenv("EVNOISE_MAX_MEMORY", "4M")
    split = shard.name.split("-")[0]
    with pytest.raises(InputError, match="chunk"):
        PairDataset(dataset, split)[0]


def test_pairs_the_manifest_declares_over_the_budget_are_refused(dataset, monkeypatch):
    from evnoise.generators import PairDataset

    def change(m):  # self-consistent: a 40000x40000 sensor's pairs
        m["config"]["sensor_shape"], m["config"]["crop_shape"] = [40000, 40000], None
        m["pair"]["counts"]["shape"], m["pair"]["image"]["shape"] = [2, 20000, 20000], [20000, 20000]

    _edit_manifest(dataset, change)
    monkeypatch.setenv("EVNOISE_MAX_MEMORY", "64M")
    with pytest.raises(InputError, match="20000x20000 pairs"):
        PairDataset(dataset, "train")


# -- 2. .npz pairs bomb ------------------------------------------------------------------------------------------
def _zero_member(zf, name, shape, dtype) -> None:
    dtype = np.dtype(dtype)
    with zf.open(name, "w", force_zip64=True) as fh:
        np.lib.format.write_array_header_2_0(fh, {"descr": np.lib.format.dtype_to_descr(dtype),
                                                  "fortran_order": False, "shape": shape})
        fh.write(bytes(int(np.prod(shape)) * dtype.itemsize))


def test_an_npz_that_inflates_past_the_budget_is_refused_before_reading(tmp_path, monkeypatch):
    from evnoise.reconstruct.data import NpzPairs

    path = tmp_path / "bomb.npz"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        _zero_member(zf, "counts.npy", (64, 2, 256, 256), "u4")  # 32 MiB of zeros, a few kB on disk
        _zero_member(zf, "images.npy", (64, 256, 256), "f4")
        with zf.open("window_s.npy", "w") as fh:
            np.lib.format.write_array(fh, np.ones(64))
    assert path.stat().st_size < 1 << 20
    monkeypatch.setenv("EVNOISE_MAX_MEMORY", "64M")
    monkeypatch.setattr(np.lib.format, "read_array", _no_read)
    with pytest.raises(InputError, match="would need .* more than the .* EVNOISE_MAX_MEMORY"):
        NpzPairs(path)


def _no_read(*args, **kwargs):
    raise AssertionError("an array was read before the checks")


@pytest.mark.parametrize("missing", ["images", "window_s"])
def test_an_npz_missing_a_required_array_fails_before_reading_any(tmp_path, monkeypatch, missing):
    from evnoise.reconstruct.data import NpzPairs

    arrays = {"counts": np.ones((2, 2, 4, 4), np.uint16), "images": np.ones((2, 4, 4), np.float32),
              "window_s": np.ones(2)}
    del arrays[missing]
    path = tmp_path / "pairs.npz"
    np.savez(path, **arrays)
    monkeypatch.setattr(np.lib.format, "read_array", _no_read)
    with pytest.raises(InputError, match=f"no array '{missing}'"):
        NpzPairs(path)


def test_npz_images_that_do_not_match_the_counts_fail_before_reading(tmp_path, monkeypatch):
    from evnoise.reconstruct.data import NpzPairs

    path = tmp_path / "pairs.npz"
    np.savez(path, counts=np.ones((2, 2, 4, 4), np.uint16), images=np.ones((2, 5, 4), np.float32),
             window_s=np.ones(2))
    monkeypatch.setattr(np.lib.format, "read_array", _no_read)
    with pytest.raises(InputError, match="do not match counts"):
        NpzPairs(path)


# -- 3. manifest fields: types, finite, in range, checked in one place -------------------------------------------
@pytest.mark.parametrize("field, value", [
    ("white_lux", "abc"), ("white_lux", float("nan")), ("white_lux", -1.0), ("binning", "two"), ("binning", 0),
    ("windows_s", [-1e308]), ("windows_s", [1.0, "x"]), ("crops_per_image", 0), ("params", [1, 2]),
    ("sensor_shape", [96, "w"]), ("crop_shape", [64]), ("max_lux", ["a", 1]),
])
def test_a_manifest_field_of_the_wrong_type_or_range_is_one_error_naming_it(dataset, capsys, field, value):
    from evnoise.generators import PairDataset

    _edit_manifest(dataset, lambda m: m["config"].__setitem__(field, value))
    err = _one_error(capsys, ["info", str(dataset)])
    assert "manifest.json is damaged" in err and repr(field) in err, err
    with pytest.raises(InputError, match=re.escape(repr(field))):
        PairDataset(dataset, "train")


@pytest.mark.parametrize("field, value", [
    ("seed", "x"), ("seed", -1), ("seed", 1.5), ("splits", 5), ("splits", [0.8, "x", 0.1]), ("splits", [0, 0, 0]),
    ("splits", [0.5, 0.5]), ("shard_size", -1), ("shard_size", "64"), ("compression", 7), ("compression", "zip"),
    ("fit", None), ("fit", "stretch"), ("mode", []), ("mode", "photons"), ("preset", 3), ("preset", ""),
    ("params", {"eps_pos": "x"}), ("params", {"no_such_parameter": 1}),
])
def test_every_config_field_info_shows_is_checked_and_named(dataset, capsys, field, value):
    """Fields ``evnoise info`` reads (seed, splits, shard_size, compression, fit, mode, preset, the parameters) were
    not checked: a hand-edited manifest gave a TypeError traceback or a summary quoting nonsense."""
    from evnoise.generators import PairDataset

    _edit_manifest(dataset, lambda m: m["config"].__setitem__(field, value))
    err = _one_error(capsys, ["info", str(dataset)])
    assert "manifest.json is damaged" in err and f"config field {field!r}" in err, err
    with pytest.raises(InputError, match=re.escape(f"config field {field!r}")):
        PairDataset(dataset, "train")


@pytest.mark.parametrize("path, value, named", [
    (("totals", "saturated_bins"), "x", "'totals'"), (("totals", "saturated_bins"), None, "'totals'"),
    (("sources",), 5, "'sources'"), (("sources",), [{"kind": "folder", "path": 3}], "'sources'"),
    (("sources",), [{"kind": "dead-leaves"}], "'sources'"),
    (("sources",), [{"kind": "files", "paths": "a"}], "'sources'"),
    (("sources",), None, "'sources'"), (("skipped",), [{"source": ["a"], "reason": "r"}], "'skipped'"),
    (("sampler",), {"a": 1}, "'sampler'"), (("evnoise_version",), [1], "'evnoise_version'"),
])
def test_every_other_manifest_entry_info_shows_is_checked_and_named(dataset, capsys, path, value, named):
    """The totals' saturated bins, the sources, the skipped sources' names, the sampler and the version."""
    def change(m):
        owner = m
        for key in path[:-1]:
            owner = owner[key]
        if value is None:
            del owner[path[-1]]
        else:
            owner[path[-1]] = value

    _edit_manifest(dataset, change)
    err = _one_error(capsys, ["info", str(dataset)])
    assert "manifest.json is damaged" in err and named in err, err


def test_a_manifest_without_a_crop_shape_is_read_as_the_sensor_not_a_traceback(dataset, capsys):
    """crop_shape is optional in the checks of the config, but the pair check read cfg["crop_shape"]: KeyError."""
    _edit_manifest(dataset, lambda m: m["config"].pop("crop_shape"))
    err = _one_error(capsys, ["info", str(dataset)])
    assert "manifest.json is damaged" in err and "sensor, binning" in err, err


def test_a_manifest_pair_shape_that_its_config_does_not_give_is_refused(dataset, capsys):
    def change(m):
        m["pair"]["counts"]["shape"], m["pair"]["image"]["shape"] = [2, 16, 16], [16, 16]

    _edit_manifest(dataset, change)
    err = _one_error(capsys, ["info", str(dataset)])
    assert "manifest.json is damaged" in err and "[2, 16, 16]" in err and "[2, 32, 32]" in err, err


# -- 4. TIFF tile bomb: the tile's declared size is checked, not only the image's --------------------------------
def _tiled_tiff(path, tile: int, side: int = 16) -> None:
    """A ``side x side`` 8-bit grey TIFF stored as one deflate tile declared ``tile x tile`` (zeros)."""
    import struct
    import zlib

    data = zlib.compress(bytes(tile * tile), 9)
    body = bytearray(b"II*\x00" + struct.pack("<I", 0)) + data
    if len(body) % 2:
        body += b"\0"
    ifd_at = len(body)
    tags = [(256, 4, side), (257, 4, side), (258, 3, 8), (259, 3, 8), (262, 3, 1), (277, 3, 1), (284, 3, 1),
            (322, 4, tile), (323, 4, tile), (324, 4, 8), (325, 4, len(data))]
    body += struct.pack("<H", len(tags))
    for tag, kind, value in tags:
        short = kind == 3
        body += struct.pack("<HHIHH", tag, kind, 1, value, 0) if short else struct.pack("<HHII", tag, kind, 1, value)
    body += struct.pack("<I", 0)
    body[4:8] = struct.pack("<I", ifd_at)
    path.write_bytes(bytes(body))


def test_a_tiff_tile_over_the_pixel_limit_is_refused(tmp_path, monkeypatch, capsys):
    from evnoise.radiometry import load_luminance

    path = tmp_path / "tiles.tif"
    _tiled_tiff(path, 2048)
    with pytest.raises(InputError, match="tiles of 2048x2048"):
        load_luminance(path, max_pixels=1_000_000)
    monkeypatch.setenv("EVNOISE_MAX_IMAGE_PIXELS", "1000000")
    err = _one_error(capsys, ["simulate", str(path), "--out", str(tmp_path / "ev.h5"), "--duration", "0.01",
                              "--sensor", "64x48"])
    assert "tiles of 2048x2048" in err and not (tmp_path / "ev.h5").exists(), err


def test_a_tiff_tile_over_the_memory_budget_is_refused(tmp_path, monkeypatch):
    from evnoise.radiometry import load_luminance

    path = tmp_path / "tiles.tif"
    _tiled_tiff(path, 4096)  # 16 MB decoded, under the default pixel limit
    monkeypatch.setenv("EVNOISE_MAX_MEMORY", "4M")
    with pytest.raises(InputError, match="4096x4096 tiles would need"):
        load_luminance(path)


def test_an_ordinary_tiled_tiff_still_reads(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    from evnoise.radiometry import load_luminance

    path = tmp_path / "ok.tif"
    tifffile.imwrite(path, np.full((40, 50), 128, np.uint8), tile=(16, 16))
    values, _ = load_luminance(path)
    assert values.shape == (40, 50)


# -- 5. JPEG scan bomb: thousands of whole-image scans ---------------------------------------------------------
def _jpeg_with_scans(path, scans: int, side: int = 64) -> None:
    """A ``side x side`` grey progressive JPEG with ``scans`` AC scans that each cover the whole image."""
    import struct

    def seg(marker, payload):
        return b"\xff" + bytes([marker]) + struct.pack(">H", len(payload) + 2) + payload

    def bits(values):  # (value, nbits) pairs -> entropy-coded bytes, 1-padded, FF stuffed
        acc = "".join(format(v, f"0{n}b") for v, n in values)
        acc += "1" * (-len(acc) % 8)
        out = bytearray()
        for i in range(0, len(acc), 8):
            out.append(int(acc[i:i + 8], 2))
            if out[-1] == 0xFF:
                out.append(0)
        return bytes(out)

    blocks = (side // 8) ** 2
    eob = blocks.bit_length() - 1  # one end-of-band run EOBn of 2**n + extra blocks covers them all
    one = [0] * 16
    one[0] = 1
    jpg = b"\xff\xd8" + seg(0xDB, b"\x00" + bytes([1] * 64))
    jpg += seg(0xC2, struct.pack(">BHHB", 8, side, side, 1) + b"\x01\x11\x00")
    jpg += seg(0xC4, b"\x00" + bytes(one) + b"\x00") + seg(0xC4, b"\x10" + bytes(one) + bytes([eob << 4]))
    jpg += seg(0xDA, b"\x01\x01\x00" + bytes([0, 0, 0])) + bits([(0, 1)] * blocks)
    ac = seg(0xDA, b"\x01\x01\x00" + bytes([1, 63, 0])) + bits([(0, 1), (blocks - (1 << eob), eob)])
    path.write_bytes(jpg + ac * scans + b"\xff\xd9")


def test_a_jpeg_with_thousands_of_scans_is_refused_before_decoding(tmp_path):
    from evnoise import radiometry
    from evnoise.radiometry import load_luminance

    limit = getattr(radiometry, "MAX_JPEG_SCANS", 1000)
    path = tmp_path / "scans.jpg"
    _jpeg_with_scans(path, limit + 5)
    with pytest.raises(InputError, match=f"more than {limit} scans"):
        load_luminance(path)


def test_an_ordinary_progressive_jpeg_still_reads(tmp_path):
    from PIL import Image

    from evnoise.radiometry import load_luminance

    path = tmp_path / "ok.jpg"
    Image.fromarray(np.linspace(0, 255, 64 * 48).reshape(48, 64).astype(np.uint8)).save(path, progressive=True)
    values, _ = load_luminance(path)
    assert values.shape == (48, 64)
    few = tmp_path / "few.jpg"
    _jpeg_with_scans(few, 20)
    assert load_luminance(few)[0].shape == (64, 64)
