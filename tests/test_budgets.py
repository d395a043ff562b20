"""Bounded memory whatever a file or an argument says: image decompression bombs, the size of
a simulation before it runs, and the dependencies a plain ``pip install evnoise`` pulls."""

from __future__ import annotations

import struct
import sys
import tomllib
import zlib
from pathlib import Path

import numpy as np
import pytest

from evnoise import InputError, ParameterError
from evnoise.radiometry import DEFAULT_MAX_IMAGE_PIXELS, image_to_lux, max_image_pixels, read_image

PIL_Image = pytest.importorskip("PIL.Image")
tifffile = pytest.importorskip("tifffile")
OpenEXR = pytest.importorskip("OpenEXR")

ROOT = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------------------
# crafted files: headers that declare huge images, a few hundred bytes each
# --------------------------------------------------------------------------------------
def _chunk(tag, data):
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)


def png_bomb(path, width, height, bit_depth=8, colour_type=0):
    """A PNG whose IHDR declares ``width x height``; its IDAT holds a few (compressed) rows only."""
    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0, 0)
    idat = zlib.compress(b"\x00" * 4096, 9)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b""))
    return path


def tiff_bomb(path, width, height):
    """A deflate TIFF written by tifffile (16 x 16), its ImageWidth / ImageLength tags then patched."""
    tifffile.imwrite(path, np.zeros((16, 16), np.uint8), compression="zlib", photometric="minisblack")
    with tifffile.TiffFile(path) as tif:
        tags = tif.pages[0].tags
        order = tif.byteorder
        patches = [(tags["ImageWidth"], width), (tags["ImageLength"], height)]
        patches = [(t.valueoffset, t.dtype, v) for t, v in patches]
    data = bytearray(path.read_bytes())
    for offset, dtype, value in patches:
        fmt = order + {3: "H", 4: "I"}[int(dtype)]
        struct.pack_into(fmt, data, offset, value)
    path.write_bytes(bytes(data))
    return path


def write_exr(path, channels):
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(hdr, {k: np.ascontiguousarray(v) for k, v in channels.items()}) as f:
        f.write(str(path))
    return path


class Decoded(Exception):
    """Raised by a patched decoder: the pixels were about to be decoded."""


@pytest.fixture
def no_decoding(monkeypatch):
    """Every decoder raises :class:`Decoded` (headers still parse): a size check must come first."""
    import imagecodecs
    from PIL import ImageFile

    def refuse(*args, **kwargs):
        raise Decoded("the pixels were decoded")

    monkeypatch.setattr(ImageFile.ImageFile, "load", refuse)
    monkeypatch.setattr(imagecodecs, "png_decode", refuse)
    monkeypatch.setattr(tifffile.TiffPage, "asarray", refuse)
    real_file = OpenEXR.File

    def exr_file(*args, header_only=False, **kwargs):
        if not isinstance(args[0], str):  # File(header, channels): writing
            return real_file(*args, **kwargs)
        if not header_only:
            refuse()
        return real_file(*args, header_only=True, **kwargs)

    monkeypatch.setattr(OpenEXR, "File", exr_file)


# --------------------------------------------------------------------------------------
# decompression bombs (issue 35): refused from the header, before any pixel is decoded
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind, size", [
    ("png8", (13000, 13000)),  # 164 KB in the report -> 5.6 GB, then MemoryError
    ("png16-rgb", (20000, 20000)),  # 2.3 MB, decoded by imagecodecs -> 8.9 GiB
    ("tiff-deflate", (30000, 30000)),  # 0.9 MB -> 6.7 GiB
])
def test_bomb_is_refused_from_its_header_before_decoding(tmp_path, no_decoding, kind, size):
    w, h = size
    if kind == "png8":
        path = png_bomb(tmp_path / "bomb.png", w, h)
    elif kind == "png16-rgb":
        path = png_bomb(tmp_path / "bomb.png", w, h, bit_depth=16, colour_type=2)
    else:
        path = tiff_bomb(tmp_path / "bomb.tif", w, h)
    assert path.stat().st_size < 10_000
    with pytest.raises(InputError, match=rf"declares {w}x{h} .*limit of {DEFAULT_MAX_IMAGE_PIXELS:,} pixels.*"
                                         r"EVNOISE_MAX_IMAGE_PIXELS"):
        read_image(path)
    with pytest.raises(InputError, match="decompression bombs"):
        image_to_lux(path, sensor_shape=(32, 32))


def test_exr_size_is_checked_from_its_header(tmp_path, no_decoding):
    path = write_exr(tmp_path / "y.exr", {"Y": np.ones((30, 40), np.float32)})
    with pytest.raises(InputError, match="declares 40x30 .*limit of 1,000 pixels"):
        read_image(path, max_pixels=1000)
    with pytest.raises(InputError, match="the pixels were decoded"):  # within the limit: decoded
        read_image(path, max_pixels=1200)


@pytest.mark.parametrize("kind", ["png8", "png16", "jpeg", "tiff", "tiff-rgb", "exr"])
def test_one_limit_for_every_decoder(tmp_path, monkeypatch, kind):
    rng = np.random.default_rng(0)
    grey = rng.integers(0, 255, (30, 40), dtype=np.uint8)
    path = tmp_path / f"im.{kind}"
    if kind == "png8":
        PIL_Image.fromarray(grey).save(path, format="PNG")
    elif kind == "png16":
        rgb = (rng.integers(0, 65535, (30, 40, 3))).astype(">u2")
        raw = b"".join(b"\x00" + rgb[i].tobytes() for i in range(30))
        ihdr = struct.pack(">IIBBBBB", 40, 30, 16, 2, 0, 0, 0)
        path.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(raw))
                         + _chunk(b"IEND", b""))
    elif kind == "jpeg":
        PIL_Image.fromarray(grey).save(path, format="JPEG")
    elif kind == "tiff":
        tifffile.imwrite(path, grey, compression="zlib")
    elif kind == "tiff-rgb":
        tifffile.imwrite(path, np.stack([grey] * 3, axis=-1), photometric="rgb")
    else:
        write_exr(path, {"Y": grey.astype(np.float32)})
    assert read_image(path, max_pixels=1200).shape == (30, 40)
    with pytest.raises(InputError, match="declares 40x30 .*limit of 1,199 pixels"):
        read_image(path, max_pixels=1199)
    monkeypatch.setenv("EVNOISE_MAX_IMAGE_PIXELS", "1199")
    with pytest.raises(InputError, match="limit of 1,199 pixels"):
        image_to_lux(path)
    monkeypatch.setenv("EVNOISE_MAX_IMAGE_PIXELS", "1200")
    assert image_to_lux(path).shape == (30, 40)


def test_many_channels_count_against_the_limit(tmp_path, no_decoding):
    path = tmp_path / "deep.tif"
    tifffile.imwrite(path, np.zeros((10, 10, 40), np.uint8), photometric="minisblack", planarconfig="contig")
    with pytest.raises(InputError, match="with 40 samples .*1,000 pixels"):  # 10 groups of 4 channels
        read_image(path, max_pixels=999)


def test_the_limit_can_be_raised_beyond_pillows_own(tmp_path, no_decoding):
    # 200 megapixels: Pillow alone refuses (DecompressionBombError above 2 x 89 M); a raised limit lets it decode
    path = png_bomb(tmp_path / "big.png", 20000, 10000)
    with pytest.raises(InputError, match="declares 20000x10000"):
        read_image(path)
    with pytest.raises(InputError, match="the pixels were decoded"):  # reached the (patched) decoder
        read_image(path, max_pixels=10**9)
    assert PIL_Image.MAX_IMAGE_PIXELS is not None  # Pillow's global check is back in place


@pytest.mark.parametrize("value", ["0", "-5", "many", "1.5"])
def test_a_bad_limit_is_a_parameter_error(monkeypatch, value):
    monkeypatch.setenv("EVNOISE_MAX_IMAGE_PIXELS", value)
    with pytest.raises(ParameterError, match="EVNOISE_MAX_IMAGE_PIXELS must be a positive whole number"):
        max_image_pixels()
    with pytest.raises(ParameterError, match="max_pixels"):
        max_image_pixels(0)
    assert max_image_pixels(10) == 10


def test_cli_refuses_a_bomb_in_one_line(tmp_path, no_decoding, capsys):
    from evnoise.cli import main

    path = png_bomb(tmp_path / "bomb.png", 13000, 13000)
    assert main(["simulate", str(path), "--out", str(tmp_path / "x.h5"), "--seed", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("evnoise: error:") and "EVNOISE_MAX_IMAGE_PIXELS" in err[0], err
    assert not (tmp_path / "x.h5").exists()


# --------------------------------------------------------------------------------------
# optional dependencies (issue 29): imagecodecs and colour-science are extras
# --------------------------------------------------------------------------------------
def _pyproject():
    with open(ROOT / "pyproject.toml", "rb") as fh:
        return tomllib.load(fh)["project"]


def _names(reqs):
    import re

    return {re.split(r"[<>=!~\[; ]", r, maxsplit=1)[0].lower() for r in reqs}


def test_plain_install_pulls_neither_colour_science_nor_imagecodecs():
    project = _pyproject()
    core = _names(project["dependencies"])
    assert not core & {"colour-science", "imagecodecs", "torch"}, core
    extras = project["optional-dependencies"]
    assert "imagecodecs" in _names(extras["imagecodecs"])
    assert "colour-science" in _names(extras["test-tools"])
    assert any("imagecodecs" in r and "test-tools" in r and r.startswith("evnoise[") for r in extras["test"])


def test_torch_is_a_range_that_the_tested_cpu_build_satisfies():
    from packaging.requirements import Requirement

    for extra in ("train",):
        (spec,) = [Requirement(r) for r in _pyproject()["optional-dependencies"][extra] if r.startswith("torch")]
        assert "==" not in str(spec.specifier), spec  # an exact pin clashes with any torch a user has
        assert spec.specifier.contains("2.13.0") and spec.specifier.contains("2.13.0+cpu")
        assert not spec.specifier.contains("3.0")


def test_16bit_colour_png_without_imagecodecs_names_the_extra(tmp_path, monkeypatch):
    path = tmp_path / "rgb16.png"
    rgb = np.full((4, 5, 3), 1000, dtype=">u2")
    raw = b"".join(b"\x00" + rgb[i].tobytes() for i in range(4))
    ihdr = struct.pack(">IIBBBBB", 5, 4, 16, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(raw))
                     + _chunk(b"IEND", b""))
    monkeypatch.setitem(sys.modules, "imagecodecs", None)  # import imagecodecs -> ImportError
    with pytest.raises(InputError, match=r"16-bit colour .*pip install 'evnoise\[imagecodecs\]'"):
        read_image(path)


def test_tiff_compression_without_imagecodecs_names_the_extra(tmp_path, monkeypatch):
    path = tmp_path / "g.tif"
    tifffile.imwrite(path, np.zeros((4, 5), np.uint8))

    def missing_codec(*args, **kwargs):  # what tifffile says for LZW, JPEG, ... without imagecodecs
        raise ValueError("<COMPRESSION.LZW: 5> requires the 'imagecodecs' package")

    monkeypatch.setattr(tifffile.TiffPage, "asarray", missing_codec)
    monkeypatch.setitem(sys.modules, "imagecodecs", None)
    with pytest.raises(InputError, match=r"LZW.*pip install 'evnoise\[imagecodecs\]'"):
        read_image(path)


def test_radiometry_imports_neither_colour_nor_imagecodecs():
    import subprocess

    code = ("import sys, evnoise.radiometry as r, numpy as np; r.image_to_lux(np.ones((4, 4), np.uint8)); "
            "print(sorted(m for m in ('colour', 'imagecodecs') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


# --------------------------------------------------------------------------------------
# simulate: the expected size first; a file that cannot fit on the disk is refused before the run
# --------------------------------------------------------------------------------------
def test_cli_simulate_prints_the_expected_size_and_refuses_what_cannot_fit(tmp_path, capsys):
    from evnoise.cli import main

    image = tmp_path / "grey.png"
    PIL_Image.fromarray(np.full((24, 32), 128, np.uint8)).save(image)
    assert main(["simulate", str(image), "--out", str(tmp_path / "a.h5"), "--duration", "0.5", "--seed", "1"]) == 0
    err = capsys.readouterr().err
    assert "evnoise: expecting about " in err and " events, a file of about " in err and " free)" in err
    # 1e12 s (32 x 24 pixels): about 1e15 events; refused at once, nothing simulated or written
    assert main(["-q", "simulate", str(image), "--out", str(tmp_path / "b.h5"), "--duration", "1e12"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("evnoise: error: ") and "more than the" in err[0], err
    assert "free on its disk" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.h5", "grey.png"]
