import json
import re
from dataclasses import replace

import numpy as np
import pytest
import tifffile

from rangeseg_cli.batch import io
from rangeseg_cli.config import InputConfig, load_config
from rangeseg_cli.errors import InputError
from rangeseg_cli.stages.rangeimage import clipped_value, to_heights


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_png_round_trip(tmp_path, write_png, dtype):
    a = (np.arange(32 * 40).reshape(32, 40) % 250).astype(dtype)
    path = write_png(tmp_path / "a.png", a)
    out = io.read_image(path)
    assert out.dtype == dtype
    np.testing.assert_array_equal(out, a)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_tiff_round_trip(tmp_path, dtype):
    a = (np.arange(20 * 20).reshape(20, 20)).astype(dtype)
    tifffile.imwrite(tmp_path / "a.tif", a)
    np.testing.assert_array_equal(io.read_image(tmp_path / "a.tif"), a)


def test_pgm_and_npy_and_single_channel(tmp_path):
    import imageio.v3 as iio

    a = (np.arange(20 * 24).reshape(20, 24) % 200).astype(np.uint8)
    iio.imwrite(tmp_path / "a.pgm", a)
    np.testing.assert_array_equal(io.read_image(tmp_path / "a.pgm"), a)
    np.save(tmp_path / "b.npy", a[:, :, None].astype(np.float64))
    np.testing.assert_array_equal(io.read_image(tmp_path / "b.npy"), a)


def _pgm(magic: str, maxval: int, a: np.ndarray) -> bytes:
    """A PGM file's bytes: P5 (binary, big-endian) or P2 (plain), with a comment."""
    header = f"{magic}\n# made by a test\n{a.shape[1]} {a.shape[0]}\n{maxval}\n".encode()
    if magic == "P5":
        return header + a.astype(">u2" if maxval > 255 else "u1").tobytes()
    return header + "\n".join(" ".join(map(str, row)) for row in a).encode() + b"\n"


@pytest.mark.parametrize("magic", ["P5", "P2"])
def test_16_bit_pgm_is_uint16_and_its_top_value_is_clipped(tmp_path, magic):
    # Pillow reads a 16-bit PGM as int32, whose top (2^31-1) no pixel holds: 65535 stayed valid
    a = (1000 + 50 * np.mgrid[0:32, 0:32][1]).astype(np.uint16)
    a[10:20, 10:20] = 65535
    path = tmp_path / "a.pgm"
    path.write_bytes(_pgm(magic, 65535, a))
    out = io.read_image(path)
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, a)
    assert clipped_value(out.dtype, InputConfig()) == 65535
    z = to_heights(out, InputConfig())
    assert np.isnan(z[10:20, 10:20]).all() and np.count_nonzero(np.isnan(z)) == 100


def test_pgm_written_by_pillow_reads_as_the_png_of_the_same_values(tmp_path):
    from PIL import Image

    a = (1000 + 50 * np.mgrid[0:32, 0:32][1]).astype(np.uint16)
    a[0, 0] = 65535
    Image.fromarray(a).save(tmp_path / "a.pgm")
    Image.fromarray(a).save(tmp_path / "a.png")
    pgm, png = io.read_image(tmp_path / "a.pgm"), io.read_image(tmp_path / "a.png")
    assert pgm.dtype == png.dtype == np.uint16
    np.testing.assert_array_equal(pgm, png)


@pytest.mark.parametrize("magic, maxval, dtype", [("P5", 4095, np.uint16), ("P2", 4095, np.uint16),
                                                   ("P5", 100, np.uint8), ("P2", 100, np.uint8)])
def test_pgm_of_another_maxval_keeps_its_raw_values(tmp_path, magic, maxval, dtype):
    # Pillow rescaled them to 0..65535 (or 0..255): 12-bit depth in mm came back x16
    a = (np.arange(32 * 32).reshape(32, 32) % (maxval + 1)).astype(dtype)
    path = tmp_path / "a.pnm"
    path.write_bytes(_pgm(magic, maxval, a))
    out = io.read_image(path)
    assert out.dtype == dtype
    np.testing.assert_array_equal(out, a)


@pytest.mark.parametrize("data, message", [
    (b"P5\n32 32\n65535\n" + bytes(100), "PGM data truncated"),
    (b"P2\n32 32\n255\n" + b"1 " * 100, "PGM data truncated or not numbers 0 to 65535"),
    (b"P2\n32 32\n255\n" + b"-1 " * 1024, "not numbers 0 to 65535"),
    (b"P5\n32 32\n0\n" + bytes(1024), "PGM maxval 0; allowed: 1 to 65535"),
    (b"P5\n32 32\n70000\n" + bytes(2048), "PGM maxval 70000"),
    (b"P5\n32 32\n100\n" + bytes([200]) * 1024, "pixel value 200 above the header's maxval 100"),
    (b"P5\n32 x\n255\n" + bytes(1024), "malformed PGM header"),
    (b"P5\n99999999 99999999\n255\n" + bytes(1024), "PGM data truncated"),
])
def test_malformed_pgm_is_a_one_line_error_naming_the_file(tmp_path, data, message):
    path = tmp_path / "bad.pgm"
    path.write_bytes(data)
    with pytest.raises(InputError, match=rf"bad.pgm: not a readable image \(.*"
                                         rf"{re.escape(message)}") as info:
        io.read_image(path)
    assert "\n" not in str(info.value)


def test_grey_image_pillow_widens_to_int32_comes_back_as_uint16(tmp_path, monkeypatch,
                                                                 write_png):
    # as older Pillow did with 16-bit PNGs; the clipped value must be 65535, not 2^31-1
    import imageio.v3 as iio

    a = np.full((20, 20), 65535, np.int32)
    monkeypatch.setattr(iio, "imread", lambda *args, **kwargs: a)
    path = write_png(tmp_path / "a.png", np.zeros((20, 20), np.uint16))
    out = io.read_image(path)
    assert out.dtype == np.uint16 and clipped_value(out.dtype, InputConfig()) == 65535
    monkeypatch.setattr(iio, "imread", lambda *args, **kwargs: a - 70000)  # no 16-bit values
    assert io.read_image(path).dtype == np.int32


def test_rgb_too_small_empty_and_corrupt_files_are_named_errors(tmp_path, write_png):
    rgb = write_png(tmp_path / "rgb.png", np.zeros((20, 20, 3), np.uint8))
    with pytest.raises(InputError, match=r"rgb.png: has 3 channels"):
        io.read_image(rgb)
    small = write_png(tmp_path / "small.png", np.zeros((8, 30), np.uint8))
    with pytest.raises(InputError, match=r"small.png: size 30x8 pixels \(width x height\) is too small; "
                                         r"at least 16x16"):
        io.read_image(small)
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(InputError, match=r"empty.png: empty file"):
        io.read_image(tmp_path / "empty.png")
    (tmp_path / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    with pytest.raises(InputError, match=r"bad.png: not a readable image") as info:
        io.read_image(tmp_path / "bad.png")
    assert "\n" not in str(info.value)
    (tmp_path / "text.pgm").write_text("hello, not an image\n")
    with pytest.raises(InputError, match=r"text.pgm: not a readable image \(its content is no "
                                         r"image format rangeseg reads: PNG, PGM/PNM"):
        io.read_image(tmp_path / "text.pgm")  # not imageio's "Could not find a backend"
    np.save(tmp_path / "cube.npy", np.zeros((20, 20, 20)))
    with pytest.raises(InputError, match=r"cube.npy: shape \(20, 20, 20\)"):
        io.read_image(tmp_path / "cube.npy")


def test_to_heights_depth_units_and_invalid_values():
    raw = np.full((16, 16), 5000, np.uint16)
    raw[0, 0] = 0
    cfg = replace(load_config(preset="tenth-mm-depth").input, fill_holes=0)  # kept a hole
    z = to_heights(raw, cfg)
    assert np.isnan(z[0, 0])
    assert z[1, 1] == pytest.approx(-500.0)  # 500 mm away -> height -500 mm
    assert raw[0, 0] == 0  # input not modified


def test_nan_and_inf_are_invalid_and_all_invalid_is_an_error():
    raw = np.ones((16, 16))
    raw[0, 0], raw[0, 1] = np.nan, np.inf
    z = to_heights(raw, InputConfig(fill_holes=0))
    assert np.isnan(z[0, :2]).all() and np.isfinite(z[1:]).all()
    with pytest.raises(InputError, match="no valid pixel"):
        to_heights(np.full((16, 16), np.nan), InputConfig())


def test_find_images_keeps_relative_paths_and_skips_outputs(tmp_path, write_png):
    a = np.zeros((16, 16), np.uint8)
    (tmp_path / "in" / "x").mkdir(parents=True)
    write_png(tmp_path / "in" / "x" / "b.png", a)
    write_png(tmp_path / "in" / "b.png", a)
    (tmp_path / "in" / "notes.txt").write_text("hi")
    np.save(tmp_path / "in" / "b.labels.npy", a)
    out = tmp_path / "in" / "out"
    out.mkdir()
    write_png(out / "c.png", a)
    images, skipped = io.find_images([tmp_path / "in"], exclude=out)
    assert [r.as_posix() for _, r in images] == ["b", "x/b"]
    assert {p.name for p in skipped} == {"notes.txt", "b.labels.npy"}


def test_atomic_writers_leave_no_temporary_files(tmp_path):
    io.write_npy(tmp_path / "a.npy", np.arange(4))
    io.write_json(tmp_path / "a.json", {"b": np.float32(1.23456789), "a": [np.int64(2)],
                                        "c": float("nan")})
    io.write_png(tmp_path / "a.png", np.zeros((4, 4), np.uint8))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "a.npy", "a.png"]
    text = (tmp_path / "a.json").read_text()
    assert text.index('"a"') < text.index('"b"') and "1.23457" in text and "null" in text


def test_absurd_heights_are_a_clear_error_not_an_overflow():
    raw = np.zeros((16, 16))
    raw[3, 3] = 1.7e308
    with pytest.raises(InputError, match=r"height 1.7e\+308 is outside the supported range"):
        to_heights(raw, InputConfig())


def test_outputs_get_the_usual_permissions_not_mkstemps_0600(tmp_path):
    import os
    import stat

    io.write_npy(tmp_path / "a.npy", np.arange(3))
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE((tmp_path / "a.npy").stat().st_mode) == 0o666 & ~umask


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int16])
def test_the_top_of_an_integer_range_is_clipped_not_measured(dtype):
    top = np.iinfo(dtype).max
    raw = np.full((16, 16), 100, dtype)
    raw[4:8, 4:8] = top  # a plateau beyond the sensor's range
    z = to_heights(raw, InputConfig())
    assert np.isnan(z[4:8, 4:8]).all() and np.isfinite(z).sum() == 256 - 16
    kept = to_heights(raw, InputConfig(clipped_invalid=False))
    assert np.isfinite(kept).all() and kept[5, 5] == top
    assert (raw[4:8, 4:8] == top).all()  # input not modified


def test_floating_point_images_have_no_clipped_value():
    raw = np.full((16, 16), 255.0)
    assert np.isfinite(to_heights(raw, InputConfig())).all()


def test_an_image_clipped_everywhere_is_a_one_line_error(tmp_path, write_png):
    with pytest.raises(InputError, match=r"no valid pixel .*top of an integer type's range, clipped"):
        to_heights(np.full((16, 16), 255, np.uint8), InputConfig(), name="white.png")
    (tmp_path / "in").mkdir()
    write_png(tmp_path / "in" / "white.png", np.full((16, 16), 255, np.uint8))
    from click.testing import CliRunner

    from rangeseg_cli.cli.main import main

    result = CliRunner().invoke(main, ["run", str(tmp_path / "in"), "-o", str(tmp_path / "out")])
    assert result.exit_code != 0
    assert "white.png: no valid pixel" in result.output and "Traceback" not in result.output


def test_the_manifest_counts_the_clipped_pixels(tmp_path, write_png):
    from click.testing import CliRunner

    from rangeseg_cli.cli.main import main

    (tmp_path / "in").mkdir()
    image = np.full((32, 32), 40, np.uint8)
    image[8:24, 8:24] = 120
    write_png(tmp_path / "in" / "plain.png", image)
    image[10:14, 10:15] = 255  # 20 pixels beyond the range
    write_png(tmp_path / "in" / "clipped.png", image)
    result = CliRunner().invoke(main, ["run", str(tmp_path / "in"), "-o",
                                       str(tmp_path / "out"), "-q"])
    assert result.exit_code == 0, result.output
    images = json.loads((tmp_path / "out" / "rangeseg-run.json").read_text())["images"]
    assert images["clipped"]["clipped_pixels"] == 20
    assert "clipped_pixels" not in images["plain"]
    labels = np.load(tmp_path / "out" / "clipped.labels.npy")
    assert (labels[10:14, 10:15] == 0).all()


def test_a_png_beyond_the_readers_pixel_limit_is_named_too_big_not_damaged(tmp_path, write_png,
                                                                           monkeypatch):
    # Pillow refuses images of over 179 MP as "decompression bombs"; its message was
    # passed on as "a damaged or truncated PNG file", which the file is not
    from PIL import Image

    from rangeseg_cli.batch.io import read_image
    from rangeseg_cli.errors import InputError

    path = tmp_path / "big.png"
    write_png(path, np.zeros((40, 50), np.uint8))
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 500)  # 2,000 pixels: over twice it
    with pytest.raises(InputError) as caught:
        read_image(path)
    message = str(caught.value)
    assert "damaged" not in message
    assert (f"{path}: not a readable image (2,000 pixels, beyond the 1,000 the PNG reader "
            "takes in one image;") in message
    assert message.endswith("crop or downsample it, or save it as NPY or TIFF)")
