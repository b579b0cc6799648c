"""ilt.io.exr: float32 EXR round trips, metadata, refusals and atomic writes."""

import os

import numpy as np
import OpenImageIO as oiio
import pytest

from ilt.io.exr import ImageError, read_exr, write_exr


def _random_image(shape, seed=0):
    """float32 with magnitudes from 1e-30 to 1e30, both signs, and exact zeros."""
    rng = np.random.default_rng(seed)
    image = rng.standard_normal(shape) * 10.0 ** rng.integers(-30, 31, size=shape)
    image.flat[:3] = [1e-30, 1e30, 0.0]
    return image.astype(np.float32)


def _leftovers(directory):
    return sorted(p.name for p in directory.iterdir())


@pytest.mark.parametrize(
    "shape, names",
    [((7, 9), ["Y"]), ((7, 9, 3), ["R", "G", "B"]), ((7, 9, 5), ["c0", "c1", "c2", "c3", "c4"])],
)
def test_round_trip_is_bit_exact_with_default_channels(tmp_path, shape, names):
    image = _random_image(shape)
    path = write_exr(tmp_path / "a.exr", image)
    pixels, attributes = read_exr(path)
    assert pixels.dtype == np.float32 and pixels.shape == (7, 9, len(names))
    assert np.array_equal(pixels.view(np.uint32), image.reshape(pixels.shape).view(np.uint32))
    assert attributes["channels"] == names


@pytest.mark.parametrize(
    "names", [["B", "G", "R", "A"], ["Z", "R", "alpha"], [f"c{i}" for i in range(12)]]
)
def test_channel_order_survives_exr_sorting(tmp_path, names):
    # OpenEXR sorts channels by name and OIIO reads R, G, B, A first
    image = np.broadcast_to(np.arange(len(names), dtype=np.float32), (2, 3, len(names)))
    pixels, attributes = read_exr(write_exr(tmp_path / "a.exr", image, channels=names))
    assert attributes["channels"] == names
    assert np.array_equal(pixels, image)


def test_attributes_keep_their_types(tmp_path):
    attributes = {
        "units": "W/m^2/sr",
        "beam": 17,
        "exposure": 0.25,
        "gain": 0.1,  # not exact in float32: kept exact through JSON
        "plan": {"kind": "grid", "layout": [4, 8]},
        "beams": [1, 2, 3],
        "saturated": False,
        "capture:camera": "Canon EOS 20D",
    }
    path = write_exr(tmp_path / "a.exr", np.ones((2, 2), np.float32), attributes=attributes)
    _, stored = read_exr(path)
    assert stored["ilt:units"] == "W/m^2/sr"
    assert stored["ilt:beam"] == 17 and type(stored["ilt:beam"]) is int
    assert stored["ilt:exposure"] == 0.25 and type(stored["ilt:exposure"]) is float
    assert stored["ilt:gain"] == 0.1
    assert stored["ilt:plan"] == {"kind": "grid", "layout": [4, 8]}
    assert stored["ilt:beams"] == [1, 2, 3]
    assert stored["ilt:saturated"] is False
    assert stored["capture:camera"] == "Canon EOS 20D"
    assert "ilt:json" not in stored and "ilt:channels" not in stored


@pytest.mark.parametrize("compression", ["zip", "zip:1", "zips:9", "piz", "none"])
def test_file_is_float32_with_requested_compression(tmp_path, compression):
    image = _random_image((40, 50, 3))
    path = write_exr(tmp_path / "a.exr", image, compression=compression)
    inp = oiio.ImageInput.open(str(path))
    spec = inp.spec()
    inp.close()
    assert spec.format == oiio.TypeFloat and not spec.channelformats
    assert spec.getattribute("compression") == compression.partition(":")[0]  # the level is not stored
    assert np.array_equal(read_exr(path)[0], image.astype(np.float32))  # lossless, every level


@pytest.mark.parametrize("compression", ["dwaa", "dwab", "b44", "pxr24", "jpeg", "dwaa:45", "zip:0", "piz:3"])
def test_lossy_compression_is_refused(tmp_path, compression):
    with pytest.raises(ImageError, match=compression):
        write_exr(tmp_path / "a.exr", np.ones((2, 2)), compression=compression)
    assert _leftovers(tmp_path) == []


def test_write_into_missing_directory_fails_cleanly(tmp_path):
    path = tmp_path / "missing" / "a.exr"
    with pytest.raises(ImageError, match="missing"):
        write_exr(path, np.ones((2, 2)))
    assert _leftovers(tmp_path) == []


@pytest.mark.parametrize(
    "image",
    [np.ones((2, 2), complex), np.array([[True]]), np.ones(5), np.ones((2, 2, 2, 2)), np.ones((0, 3))],
)
def test_unsupported_images_are_refused(tmp_path, image):
    with pytest.raises(ImageError, match="a.exr"):
        write_exr(tmp_path / "a.exr", image)
    assert _leftovers(tmp_path) == []


def test_non_finite_pixels_are_refused_on_write(tmp_path):
    image = np.zeros((3, 4, 3))
    image[2, 1, 2] = 1e39  # overflows float32
    with pytest.raises(ImageError, match=r"x=1, y=2.*'B'"):
        write_exr(tmp_path / "a.exr", image)
    assert _leftovers(tmp_path) == []


def test_failure_after_pixels_are_written_leaves_old_file_and_no_temp(tmp_path, monkeypatch):
    path = write_exr(tmp_path / "a.exr", np.zeros((2, 2), np.float32))

    def broken_replace(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(ImageError, match="No space left"):
        write_exr(path, np.ones((2, 2), np.float32))
    monkeypatch.undo()
    assert _leftovers(tmp_path) == ["a.exr"]
    assert np.array_equal(read_exr(path)[0], np.zeros((2, 2, 1)))


def test_channel_name_mismatch_is_refused(tmp_path):
    with pytest.raises(ImageError, match="2 channel names given for 3"):
        write_exr(tmp_path / "a.exr", np.ones((2, 2, 3)), channels=["R", "G"])


def test_read_missing_file_names_it(tmp_path):
    path = tmp_path / "nothing.exr"
    with pytest.raises(ImageError, match="nothing.exr"):
        read_exr(path)


def test_read_garbage_file_names_it(tmp_path):
    path = tmp_path / "garbage.exr"
    path.write_bytes(b"this is not an image" * 10)
    with pytest.raises(ImageError, match="garbage.exr"):
        read_exr(path)


def _write_with_oiio(path, pixels, names, fmt="float"):
    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], fmt)
    spec.channelnames = tuple(names)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(pixels) and out.close()


def test_read_reports_first_nan_pixel_and_channel(tmp_path):
    pixels = np.ones((4, 5, 3), np.float32)
    pixels[1, 3, 1] = np.nan
    pixels[2, 0, 0] = np.inf
    path = tmp_path / "nan.exr"
    _write_with_oiio(path, pixels, ["R", "G", "B"])
    with pytest.raises(ImageError, match=r"nan\.exr.*x=3, y=1.*'G'.*2 non-finite"):
        read_exr(path)


def test_read_refuses_integer_channels_and_other_formats(tmp_path):
    path = tmp_path / "uint.exr"
    _write_with_oiio(path, np.ones((2, 2, 1), np.float32), ["Y"], fmt="uint")
    with pytest.raises(ImageError, match="uint.exr.*not float"):
        read_exr(path)
    png = tmp_path / "a.png"
    _write_with_oiio(png, np.ones((2, 2, 1), np.float32), ["Y"], fmt="uint8")
    with pytest.raises(ImageError, match="a.png.*not OpenEXR"):
        read_exr(png)


def test_half_files_from_other_tools_are_read_as_float32(tmp_path):
    path = tmp_path / "half.exr"
    _write_with_oiio(path, np.full((2, 3, 1), 0.5, np.float32), ["Y"], fmt="half")
    pixels, attributes = read_exr(path)
    assert pixels.dtype == np.float32 and np.all(pixels == 0.5)
    assert attributes["channels"] == ["Y"]


def test_the_same_image_gives_the_same_bytes(tmp_path):
    """No write-time stamp (OpenImageIO's DateTime) in the header: two runs, two machines
    or two executors writing the same pixels write the same file."""
    import time

    image = np.arange(12, dtype=np.float32).reshape(3, 4)
    write_exr(tmp_path / "a.exr", image, attributes={"beam": 3})
    time.sleep(1.05)
    write_exr(tmp_path / "b.exr", image, attributes={"beam": 3})
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()
    assert "DateTime" not in read_exr(tmp_path / "a.exr")[1]


def test_rows_read_only_those_rows_as_the_whole_read_has_them(tmp_path):
    """read_exr(rows=...) gives the same pixels as the whole image's rows (a block of ZIP
    scanlines is 16 rows: windows across and inside blocks), checks the size first, names
    a NaN's pixel by its image row, and refuses rows outside the image."""
    image = np.random.default_rng(0).random((50, 37, 2)).astype(np.float32)
    path = write_exr(tmp_path / "a.exr", image, channels=["G", "R"])
    for r0, r1 in ((0, 50), (3, 9), (15, 17), (31, 50)):
        part, attributes = read_exr(path, rows=(r0, r1))
        np.testing.assert_array_equal(part, image[r0:r1])
        assert attributes["channels"] == ["G", "R"]
    with pytest.raises(ImageError, match=r"frame is 37 x 50 pixels, expected 40 x 50"):
        read_exr(path, rows=(0, 5), shape=(50, 40))
    for rows in ((5, 5), (-1, 3), (40, 51)):
        with pytest.raises(ImageError, match="not within its 50"):
            read_exr(path, rows=rows)
    image = image[..., :1].copy()
    image[33, 4, 0] = np.nan
    _write_with_oiio(tmp_path / "nan.exr", image, ["Y"])
    with pytest.raises(ImageError, match=r"x=4, y=33.*'Y'"):
        read_exr(tmp_path / "nan.exr", rows=(30, 40))
    np.testing.assert_array_equal(read_exr(tmp_path / "nan.exr", rows=(34, 40))[0], image[34:40])
