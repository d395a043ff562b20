"""Image reading, linearisation, luminance and the mapping to lux (evnoise.radiometry)."""

from __future__ import annotations

import logging
import struct
import zlib

import numpy as np
import pytest

import evnoise as ev
from evnoise import InputError, ParameterError
from evnoise.radiometry import (
    DEFAULT_MAX_LUX,
    fit_to_sensor,
    list_frames,
    natural_sort_key,
    read_image,
    srgb_to_linear,
)

colour = pytest.importorskip("colour")
PIL_Image = pytest.importorskip("PIL.Image")
tifffile = pytest.importorskip("tifffile")
OpenEXR = pytest.importorskip("OpenEXR")


# --------------------------------------------------------------------------------------
# helpers: files of every supported kind
# --------------------------------------------------------------------------------------
def write_png16(path, arr):
    """A 16-bit grey or RGB PNG written by hand (Pillow cannot write 16-bit RGB)."""
    arr = np.asarray(arr, dtype=">u2")
    h, w = arr.shape[:2]
    colour_type = 2 if arr.ndim == 3 else 0
    raw = b"".join(b"\x00" + arr[i].tobytes() for i in range(h))

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", w, h, 16, colour_type, 0, 0, 0)
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")
    path.write_bytes(png)
    return path


def write_exr(path, channels, **header):
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **header}
    with OpenEXR.File(hdr, {k: np.ascontiguousarray(v) for k, v in channels.items()}) as f:
        f.write(str(path))
    return path


def colour_luminance(rgb_encoded):
    """Reference: colour-science's sRGB decoding and RGB -> XYZ, the Y component."""
    xyz = colour.RGB_to_XYZ(rgb_encoded, colour.RGB_COLOURSPACES["sRGB"], apply_cctf_decoding=True)
    return xyz[..., 1]


@pytest.fixture
def rng():
    return np.random.default_rng(20240607)


# --------------------------------------------------------------------------------------
# sRGB decoding and luminance against colour-science
# --------------------------------------------------------------------------------------
def test_srgb_decoding_matches_colour_on_every_8_and_16_bit_code():
    for bits in (8, 16):
        codes = np.arange(1 << bits) / ((1 << bits) - 1)
        ours = srgb_to_linear(codes)
        ref = colour.models.eotf_sRGB(codes)
        # the two differ only in which branch takes V = 0.04045 exactly (values agree to 1e-8)
        np.testing.assert_allclose(ours, ref, rtol=1e-12, atol=1e-8)
        assert ours[0] == 0.0 and ours[-1] == 1.0


def test_srgb_decoding_matches_colour_on_random_values(rng):
    v = rng.random(10_000)
    np.testing.assert_allclose(srgb_to_linear(v), colour.models.eotf_sRGB(v), rtol=1e-12, atol=1e-8)


def test_rgb_png_luminance_matches_colour(tmp_path, rng):
    rgb = rng.integers(0, 256, size=(12, 17, 3), dtype=np.uint8)
    PIL_Image.fromarray(rgb).save(tmp_path / "rgb.png")
    y = read_image(tmp_path / "rgb.png")
    assert y.dtype == np.float64 and y.shape == (12, 17)
    np.testing.assert_allclose(y, colour_luminance(rgb / 255.0), rtol=1e-10, atol=1e-8)


def test_grey_png_8_bit(tmp_path):
    grey = np.arange(256, dtype=np.uint8).reshape(16, 16)
    PIL_Image.fromarray(grey).save(tmp_path / "g.png")
    np.testing.assert_allclose(read_image(tmp_path / "g.png"), colour.models.eotf_sRGB(grey / 255.0),
                               rtol=1e-12, atol=1e-8)


def test_grey_png_16_bit_keeps_full_precision(tmp_path, rng):
    grey = rng.integers(0, 65536, size=(9, 11), dtype=np.uint16)
    PIL_Image.fromarray(grey).save(tmp_path / "g16.png")
    y = read_image(tmp_path / "g16.png")
    np.testing.assert_allclose(y, colour.models.eotf_sRGB(grey / 65535.0), rtol=1e-12, atol=1e-8)


def test_rgb_png_16_bit_is_not_truncated_to_8_bits(tmp_path, rng):
    rgb = rng.integers(0, 65536, size=(7, 5, 3), dtype=np.uint16)
    write_png16(tmp_path / "rgb16.png", rgb)
    y = read_image(tmp_path / "rgb16.png")
    np.testing.assert_allclose(y, colour_luminance(rgb / 65535.0), rtol=1e-10, atol=1e-9)


def test_jpeg_uniform_grey(tmp_path):
    PIL_Image.fromarray(np.full((16, 24), 128, dtype=np.uint8)).save(tmp_path / "g.jpg", quality=95)
    y = read_image(tmp_path / "g.jpg")
    assert y.shape == (16, 24)
    np.testing.assert_allclose(y, colour.models.eotf_sRGB(128 / 255.0), rtol=0.02)


def test_jpeg_exif_orientation_is_applied(tmp_path):
    img = PIL_Image.fromarray(np.zeros((10, 30, 3), dtype=np.uint8))
    exif = PIL_Image.Exif()
    exif[0x0112] = 6  # rotate 90 degrees for display
    img.save(tmp_path / "rot.jpg", exif=exif)
    assert read_image(tmp_path / "rot.jpg").shape == (30, 10)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("planar", [False, True])
def test_tiff_rgb(tmp_path, rng, dtype, planar):
    top = np.iinfo(dtype).max
    rgb = rng.integers(0, top + 1, size=(6, 8, 3)).astype(dtype)
    data = np.moveaxis(rgb, -1, 0) if planar else rgb
    tifffile.imwrite(tmp_path / "rgb.tif", data, photometric="rgb",
                     planarconfig="separate" if planar else "contig")
    y = read_image(tmp_path / "rgb.tif")
    np.testing.assert_allclose(y, colour_luminance(rgb / top), rtol=1e-10, atol=1e-9)


def test_tiff_grey_16_bit_and_miniswhite(tmp_path, rng):
    grey = rng.integers(0, 65536, size=(5, 7)).astype(np.uint16)
    tifffile.imwrite(tmp_path / "g.tif", grey, photometric="minisblack")
    np.testing.assert_allclose(read_image(tmp_path / "g.tif"), srgb_to_linear(grey / 65535.0))
    tifffile.imwrite(tmp_path / "w.tif", grey, photometric="miniswhite")
    np.testing.assert_allclose(read_image(tmp_path / "w.tif"), srgb_to_linear((65535 - grey) / 65535.0))


def test_float_tiff_is_linear(tmp_path, rng):
    lin = rng.random((4, 6)).astype(np.float32) * 50
    tifffile.imwrite(tmp_path / "f.tif", lin)
    np.testing.assert_array_equal(read_image(tmp_path / "f.tif"), lin.astype(np.float64))
    np.testing.assert_allclose(ev.image_to_lux(tmp_path / "f.tif", lux_scale=2.0), 2.0 * lin)


# --------------------------------------------------------------------------------------
# OpenEXR
# --------------------------------------------------------------------------------------
def test_exr_y_channel_half(tmp_path, rng):
    y = (rng.random((5, 9)) * 100).astype(np.float16)
    write_exr(tmp_path / "y.exr", {"Y": y})
    np.testing.assert_array_equal(read_image(tmp_path / "y.exr"), y.astype(np.float64))


def test_exr_rgb_float_uses_rec709_weights(tmp_path, rng):
    rgb = rng.random((4, 6, 3)).astype(np.float32) * 3
    write_exr(tmp_path / "rgb.exr", {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2]})
    expected = rgb.astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])
    np.testing.assert_allclose(read_image(tmp_path / "rgb.exr"), expected, rtol=1e-12)


def test_exr_chromaticities_set_the_luminance_weights(tmp_path):
    # Rec. 2020 primaries, D65: luminance weights 0.2627, 0.6780, 0.0593 (ITU-R BT.2020)
    ones = np.ones((2, 2), dtype=np.float32)
    chroma = (0.708, 0.292, 0.170, 0.797, 0.131, 0.046, 0.3127, 0.3290)
    for k, channel in enumerate("RGB"):
        channels = {c: ones * (c == channel) for c in "RGB"}
        write_exr(tmp_path / f"{channel}.exr", channels, chromaticities=chroma)
        got = read_image(tmp_path / f"{channel}.exr")[0, 0]
        assert got == pytest.approx((0.2627, 0.6780, 0.0593)[k], abs=5e-4)


@pytest.mark.parametrize("chroma", [(0.0,) * 8, (0.3, 0.3, 0.3, 0.3, 0.3, 0.3, 0.3127, 0.329),
                                    (0.708, 0.292, 0.170, 0.797, 0.131, float("nan"), 0.3127, 0.3290)])
def test_exr_chromaticities_that_describe_no_rgb_space_are_named(tmp_path, chroma):
    """A y of 0, primaries on one point or line, a NaN: one InputError naming the attribute (found by a hostile-file
    review: ZeroDivisionError, LinAlgError, and NaN weights reported as NaN pixels)."""
    ones = np.ones((2, 2), dtype=np.float32)
    path = write_exr(tmp_path / "odd.exr", {c: ones for c in "RGB"}, chromaticities=chroma)
    with pytest.raises(InputError, match=r"odd\.exr: its chromaticities attribute .* does not describe RGB"):
        read_image(path)


def test_exr_with_nan_names_the_file(tmp_path):
    y = np.ones((3, 4), dtype=np.float32)
    y[1, 2] = np.nan
    path = write_exr(tmp_path / "nan.exr", {"Y": y})
    with pytest.raises(InputError, match=r"nan\.exr.*1 NaN"):
        ev.image_to_lux(path)


def test_exr_clip_invalid_logs_a_warning(tmp_path, caplog):
    y = np.array([[1.0, np.nan, -2.0, np.inf, 4.0]], dtype=np.float32)
    path = write_exr(tmp_path / "bad.exr", {"Y": y})
    with caplog.at_level(logging.WARNING, logger="evnoise"):
        lux = ev.image_to_lux(path, clip_invalid=True, lux_scale=10.0)
    np.testing.assert_array_equal(lux, [[10.0, 0.0, 0.0, 40.0, 40.0]])
    assert "bad.exr" in caplog.text and "clipped" in caplog.text


def test_exr_without_luminance_channels(tmp_path):
    path = write_exr(tmp_path / "z.exr", {"Z": np.ones((2, 2), dtype=np.float32)})
    with pytest.raises(InputError, match=r"z\.exr.*'Y' or 'R', 'G', 'B'"):
        read_image(path)


# --------------------------------------------------------------------------------------
# bad files
# --------------------------------------------------------------------------------------
def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="not found.*nothere.png"):
        read_image(tmp_path / "nothere.png")


def test_folder_is_not_an_image(tmp_path):
    with pytest.raises(InputError, match="folder"):
        read_image(tmp_path)


@pytest.mark.parametrize("content", [b"", b"not an image at all" * 10, b"\x89PNG\r\n\x1a\n" + b"\x00" * 40,
                                     b"\x76\x2f\x31\x01" + b"\x00" * 50, b"II*\x00" + b"\x01" * 50])
def test_corrupt_files_name_the_file(tmp_path, content):
    path = tmp_path / "broken.png"
    path.write_bytes(content)
    with pytest.raises(InputError, match="broken.png"):
        read_image(path)


def test_truncated_png(tmp_path, rng):
    PIL_Image.fromarray(rng.integers(0, 256, (64, 64), dtype=np.uint8)).save(tmp_path / "full.png")
    data = (tmp_path / "full.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="cut.png"):
        read_image(tmp_path / "cut.png")


# --------------------------------------------------------------------------------------
# image_to_lux
# --------------------------------------------------------------------------------------
def test_default_max_lux_maps_white_to_18_lux():
    lux = ev.image_to_lux(np.array([[0, 255]], dtype=np.uint8))
    np.testing.assert_array_equal(lux, [[0.0, DEFAULT_MAX_LUX]])
    assert DEFAULT_MAX_LUX == 18.0


def test_max_lux_and_encodings():
    grey = np.array([[0, 64, 128, 255]], dtype=np.uint8)
    v = grey / 255.0
    np.testing.assert_allclose(ev.image_to_lux(grey, max_lux=100.0), 100.0 * srgb_to_linear(v))
    np.testing.assert_allclose(ev.image_to_lux(grey, max_lux=100.0, encoding="gamma2.2"), 100.0 * v**2.2)
    np.testing.assert_allclose(ev.image_to_lux(grey, max_lux=100.0, encoding="linear"), 100.0 * v)
    with pytest.raises(ParameterError, match="encoding"):
        ev.image_to_lux(grey, encoding="rec2020")


def test_uint16_and_float_arrays():
    np.testing.assert_allclose(ev.image_to_lux(np.array([[65535]], dtype=np.uint16), max_lux=5.0), [[5.0]])
    lin = np.array([[0.5, 2.0]])
    np.testing.assert_array_equal(ev.image_to_lux(lin), lin)  # floats are linear: lux by default
    np.testing.assert_array_equal(ev.image_to_lux(lin, lux_scale=3.0), 3.0 * lin)


def test_rgb_array_uses_luminance():
    rgb = np.zeros((1, 3, 3), dtype=np.uint8)
    rgb[0, 0, 0] = rgb[0, 1, 1] = rgb[0, 2, 2] = 255
    np.testing.assert_allclose(ev.image_to_lux(rgb, max_lux=1.0)[0], [0.2126, 0.7152, 0.0722])


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), "bright"])
def test_bad_max_lux(bad):
    with pytest.raises(ParameterError, match="max_lux"):
        ev.image_to_lux(np.zeros((2, 2), dtype=np.uint8), max_lux=bad)


def test_scale_option_must_fit_the_kind_of_image():
    with pytest.raises(ParameterError, match="lux_scale.*max_lux"):
        ev.image_to_lux(np.zeros((2, 2), dtype=np.uint8), lux_scale=2.0)
    with pytest.raises(ParameterError, match="max_lux.*lux_scale"):
        ev.image_to_lux(np.zeros((2, 2)), max_lux=2.0)


@pytest.mark.parametrize("arr", [np.zeros((2, 2), dtype=np.int32), np.zeros((2, 2), dtype=bool),
                                 np.zeros((2, 2, 2, 2)), np.zeros((3, 4, 5)), np.array(["a"])])
def test_bad_arrays(arr):
    with pytest.raises(InputError):
        ev.image_to_lux(arr)


def test_negative_and_nan_arrays():
    with pytest.raises(InputError, match="negative"):
        ev.image_to_lux(np.array([[1.0, -0.5]]))
    with pytest.raises(InputError, match="NaN"):
        ev.image_to_lux(np.array([[1.0, np.nan]]), name="frame 3")


def test_sensor_shape_is_applied_on_linear_values(tmp_path):
    # a black/white checkerboard averages to the mean of the *linear* values, 0.5 * max_lux
    board = (np.indices((64, 64)).sum(axis=0) % 2 * 255).astype(np.uint8)
    PIL_Image.fromarray(board).save(tmp_path / "board.png")
    lux = ev.image_to_lux(tmp_path / "board.png", sensor_shape=(8, 8), fit="resize", max_lux=10.0)
    assert lux.shape == (8, 8)
    np.testing.assert_allclose(lux, 5.0, rtol=2e-3)  # (averaging the encoded values would give 2.1)


# --------------------------------------------------------------------------------------
# fitting to the sensor
# --------------------------------------------------------------------------------------
def test_crop_takes_the_centre():
    img = np.arange(6 * 8, dtype=float).reshape(6, 8)
    np.testing.assert_array_equal(fit_to_sensor(img, (2, 4), mode="crop"), img[2:4, 2:6])
    with pytest.raises(InputError, match="smaller"):
        fit_to_sensor(img, (10, 4), mode="crop")


def test_resize_keeps_constant_images_and_means(rng):
    np.testing.assert_allclose(fit_to_sensor(np.full((30, 50), 7.5), (9, 13), mode="resize"), 7.5, rtol=1e-6)
    img = rng.random((64, 96)) * 20
    small = fit_to_sensor(img, (32, 48), mode="resize")
    assert small.shape == (32, 48) and small.dtype == np.float64
    assert small.min() >= 0
    assert small.mean() == pytest.approx(img.mean(), rel=1e-3)
    big = fit_to_sensor(img, (128, 192), mode="resize")
    assert big.shape == (128, 192) and big.min() >= 0


def test_cover_keeps_the_aspect_ratio():
    # a 100x200 (H x W) image with a vertical edge at its centre, to a 50x50 sensor
    img = np.zeros((100, 200))
    img[:, 100:] = 1.0
    out = fit_to_sensor(img, (50, 50), mode="cover")
    assert out.shape == (50, 50)
    # scaled by 1/2 to 50x100 and the central 50 columns kept: the edge stays in the middle
    assert out[:, :20].max() < 1e-6 and out[:, 30:].min() > 1 - 1e-6
    same = np.arange(20.0).reshape(4, 5)
    for mode in ("cover", "crop", "resize"):
        np.testing.assert_array_equal(fit_to_sensor(same, (4, 5), mode=mode), same)


def test_fit_rejects_bad_arguments():
    with pytest.raises(ParameterError, match="fit mode"):
        fit_to_sensor(np.ones((4, 4)), (2, 2), mode="stretch")
    with pytest.raises(InputError, match="shape"):
        fit_to_sensor(np.ones((4, 4)), (0, 2))


# --------------------------------------------------------------------------------------
# frame folders
# --------------------------------------------------------------------------------------
def test_natural_sort():
    names = ["frame10.png", "frame2.png", "Frame1.png", "frame_0003.png", "frame1b.png", "a.png"]
    assert sorted(names, key=natural_sort_key) == [
        "a.png", "Frame1.png", "frame1b.png", "frame2.png", "frame10.png", "frame_0003.png"]
    assert sorted(["img100.exr", "img99.exr", "img9.exr"], key=natural_sort_key) == [
        "img9.exr", "img99.exr", "img100.exr"]


def test_list_frames(tmp_path):
    for name in ("f10.png", "f2.PNG", "f1.exr", ".hidden.png", "notes.txt"):
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "sub").mkdir()
    assert [p.name for p in list_frames(tmp_path)] == ["f1.exr", "f2.PNG", "f10.png"]
    (tmp_path / "sub.png").mkdir()  # named like a frame: it would drop one (an error, not a skip)
    with pytest.raises(InputError, match="sub.png is named like a frame but is a folder"):
        list_frames(tmp_path)


def test_list_frames_errors(tmp_path):
    with pytest.raises(InputError, match="no image files"):
        list_frames(tmp_path)
    with pytest.raises(InputError, match="not found"):
        list_frames(tmp_path / "missing")
    (tmp_path / "file.png").write_bytes(b"x")
    with pytest.raises(InputError, match="not a folder"):
        list_frames(tmp_path / "file.png")


def test_bundled_example_image():
    from importlib import resources

    path = resources.files("evnoise.data") / "example.png"
    y = read_image(str(path))
    assert y.shape == (720, 1280)
    assert y.min() == 0.0 and y.max() == 1.0  # the step wedge spans black to white
    assert len(np.unique(y)) > 100  # gradients: many grey levels


def test_example_image_is_reproducible():
    from importlib import resources

    from evnoise.data.make_example import render

    path = resources.files("evnoise.data") / "example.png"
    with PIL_Image.open(str(path)) as im:
        stored = np.asarray(im)
    np.testing.assert_array_equal(render(), stored)


def test_a_volumetric_tiff_is_refused_not_read_as_a_sideways_image(tmp_path):
    """A TIFF of axes ZYX (an image depth of 5) was read as a 16x5 image of 3 colour columns (found by a hostile-file
    review); 2-D images with or without samples per pixel still read."""
    tifffile = pytest.importorskip("tifffile")
    tifffile.imwrite(tmp_path / "vol.tif", np.ones((5, 16, 16), np.uint8), volumetric=True)
    with pytest.raises(InputError, match=r"vol\.tif: a TIFF whose first image has axes 'ZYX'"):
        read_image(tmp_path / "vol.tif")
    tifffile.imwrite(tmp_path / "planar.tif", np.ones((3, 16, 20), np.uint8), photometric="rgb",
                     planarconfig="separate")
    assert read_image(tmp_path / "planar.tif").shape == (16, 20)


@pytest.mark.parametrize("photometric", ["minisblack", "miniswhite"])
def test_one_bit_tiff_reads_as_pillow_decodes_it(tmp_path, photometric):
    """A bilevel TIFF was refused ("unsupported pixel type bool") while a 1-bit PNG was read: both are black
    and full-scale white, as Pillow decodes them (MINISWHITE inverted)."""
    tifffile = pytest.importorskip("tifffile")
    from PIL import Image

    bits = np.zeros((6, 9), dtype=bool)
    bits[1:4, 2:7] = True
    tifffile.imwrite(tmp_path / "bilevel.tif", bits, photometric=photometric)
    expected = np.asarray(Image.open(tmp_path / "bilevel.tif").convert("L"), dtype=np.float64) / 255
    np.testing.assert_array_equal(ev.read_image(tmp_path / "bilevel.tif"), expected)
    assert set(np.unique(expected)) == {0.0, 1.0}


def _exr_part(channels, name):
    OpenEXR = pytest.importorskip("OpenEXR")
    return OpenEXR.Part({"type": OpenEXR.scanlineimage, "compression": OpenEXR.ZIP_COMPRESSION},
                        {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}, name=name)


def test_multipart_exr_reads_the_first_part_holding_an_image(tmp_path):
    """A depth part before the RGB one: part 0 alone was read ("EXR has channels ['Z']")."""
    OpenEXR = pytest.importorskip("OpenEXR")
    rng = np.random.default_rng(3)
    r, g, b = (rng.uniform(0, 5, (4, 6)) for _ in range(3))
    parts = [_exr_part({"Z": np.ones((4, 6))}, "depth"), _exr_part({"R": r, "G": g, "B": b}, "beauty"),
             _exr_part({"Y": np.full((4, 6), 9.0)}, "other")]
    with OpenEXR.File(parts) as f:
        f.write(str(tmp_path / "multi.exr"))
    rgb = np.stack([c.astype(np.float32).astype(np.float64) for c in (r, g, b)], axis=-1)
    np.testing.assert_allclose(ev.read_image(tmp_path / "multi.exr"), rgb @ np.array([0.2126, 0.7152, 0.0722]),
                               rtol=1e-12)


def test_multipart_exr_without_an_image_part_names_every_part(tmp_path):
    OpenEXR = pytest.importorskip("OpenEXR")
    parts = [_exr_part({"Z": np.ones((4, 6))}, "depth"), _exr_part({"A": np.ones((4, 6))}, "mask")]
    with OpenEXR.File(parts) as f:
        f.write(str(tmp_path / "multi.exr"))
    with pytest.raises(InputError, match=r"no part of this 2-part EXR has channels .* \(parts: Z; A\)"):
        ev.read_image(tmp_path / "multi.exr")
