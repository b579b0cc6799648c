"""ilt.io.raw on real DNGs (tests/data, ../shared/realdata) and on DNGs written here
with the level tags LibRaw handles in its own ways (LinearizationTable, BlackLevel per
CFA position, MaskedAreas, BlackLevelDeltaH/V, an odd ActiveArea). Known answers only:
the files' own tags, read with tifffile, and pixel values computed here."""

from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import tifffile
from click.testing import CliRunner

from ilt.cli import cli
from ilt.io.exposure import ExposureError
from ilt.io.exr import read_exr
from ilt.io.raw import read_dng_levels, read_green

DATA = Path(__file__).resolve().parents[1] / "data"
TINYDNG = DATA / "tinydng_colorchart.dng"
REALDATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "realdata"
BLACKMAGIC = REALDATA / "raw" / "imageio_Blackmagic.dng"

IDENTITY = (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1)


def _tags(path):
    with tifffile.TiffFile(path) as tf:
        return {code: tag.value for code, tag in tf.pages[0].tags.items()}


def _unpack_14bit(path, tags):
    """The uncompressed 14-bit strip as tifffile's spec says (MSB first), without LibRaw."""
    offset, count = tags[273][0], tags[279][0]
    bits = np.unpackbits(np.frombuffer(path.read_bytes()[offset:offset + count], np.uint8)).reshape(-1, 14)
    padded = np.zeros((bits.shape[0], 16), np.uint8)
    padded[:, 2:] = bits
    return np.packbits(padded, axis=1).view(">u2").reshape(tags[257], tags[256]).astype(np.float64)


def _green_of(mosaic, black):
    """Green of an RGGB mosaic: mean of the (0, 1) and (1, 0) sites less their black."""
    black = np.broadcast_to(np.asarray(black, np.float64), mosaic.shape)
    m = mosaic - black
    return (m[0::2, 1::2] + m[1::2, 0::2]) / 2


# ------------------------------------------------------------------ real files


def test_tinydng_decodes_as_its_tags_say():
    """Canon 550D via Magic Lantern: 14-bit uncompressed, black 2056, white 15000,
    ActiveArea (26, 152, 1182, 1886): 1734 x 1156 RGGB."""
    tags = _tags(TINYDNG)
    assert (tags[50714], tags[50717], tuple(tags[50829]), bytes(tags[33422])) == \
        (2056, 15000, (26, 152, 1182, 1886), b"\x00\x01\x01\x02")
    green, info = read_green(TINYDNG, hand_time=Fraction(1, 50))
    assert info.full_shape == (1156, 1734) and green.shape == (578, 867)
    assert info.cfa == "RGGB" and info.camera == "Canon Canon EOS Kiss X4"
    assert info.black_levels == (2056.0,) * 4
    assert info.white_level == info.file_white_level == 15000.0
    assert not info.saturated.any()  # the chart's brightest photosite is 12128
    top, left, bottom, right = tags[50829]
    active = _unpack_14bit(TINYDNG, tags)[top:bottom, left:right]
    assert np.array_equal(green, _green_of(active, 2056.0))


def test_tinydng_exposure_is_refused_without_times():
    with pytest.raises(ExposureError) as err:
        read_green(TINYDNG)
    assert str(err.value) == f"{TINYDNG}: EXIF exposure time is 0 (the camera or recorder wrote none); give --times"


def test_tinydng_merged_with_times_is_a_fiftieth_of_a_second(tmp_path):
    out = tmp_path / "x.exr"
    result = CliRunner().invoke(cli, ["merge", "--bracket", str(TINYDNG), "--times", "1/50", "-o", str(out)])
    assert result.exit_code == 0, result.output
    image, attributes = read_exr(out)
    assert attributes["ilt:exposure_times"] == [0.02] and attributes["ilt:f_numbers"] == [1.0]
    assert attributes["ilt:full_shape"] == [1156, 1734] and image.shape == (578, 867, 1)
    assert "WARNING" not in result.stderr
    _, info = read_green(TINYDNG, hand_time=Fraction(1, 50))
    assert (info.exposure.time_text, info.exposure.source) == ("1/50", "times")


def test_tinydng_merge_without_times_is_refused_and_writes_nothing(tmp_path):
    out = tmp_path / "x.exr"
    result = CliRunner().invoke(cli, ["merge", "--bracket", str(TINYDNG), "-o", str(out)])
    assert result.exit_code != 0
    lines = result.stderr.strip().splitlines()
    assert lines == [(f"ilt: error: {TINYDNG}: EXIF exposure time is 0 (the camera or recorder wrote none); "
                      "give --times")]
    assert list(tmp_path.iterdir()) == []


def test_blackmagic_lossless_jpeg_tiles_with_a_linearisation_table():
    """Blackmagic Pocket 4K: 12-bit lossless-JPEG tiles through a 4096-entry
    LinearizationTable (top 65472), WhiteLevel 65535, black 512, no exposure tags."""
    if not BLACKMAGIC.is_file():
        pytest.skip("../shared/realdata absent: the Blackmagic DNG (no licence) is not in the repository")
    tags = _tags(BLACKMAGIC)
    table = np.asarray(tags[50712])
    assert (tags[259], tags[258], tags[50714], tags[50717], table.size, int(table.max())) == \
        (7, 12, 512, 65535, 4096, 65472)
    levels = read_dng_levels(BLACKMAGIC)
    assert np.array_equal(levels.table, table) and levels.white == 65535.0 and levels.black.tolist() == [[512.0]]
    green, info = read_green(BLACKMAGIC, hand_time=Fraction(1, 24))
    assert info.full_shape == (2176, 4128) and green.shape == (1088, 2064) and info.cfa == "RGGB"
    assert info.black_levels == (512.0,) * 4
    # the table's top, not the 65535 of WhiteLevel, is where the sensor clips
    assert info.file_white_level == 65535.0 and info.white_level == 65472.0
    assert green.max() <= 65472 - 512 and info.saturated.any()
    with pytest.raises(ExposureError, match=r"imageio_Blackmagic\.dng: no exposure time in the manifest or EXIF; "
                                            r"give --times$"):
        read_green(BLACKMAGIC)


# ------------------------------------------------------------------ DNGs written here


def _write(path, mosaic, raw_tags=(), black=(100,), repeat=(1, 1), white=4000, subifd=False):
    """A Bayer DNG (RGGB, EXIF 1/50 s at f/2.8) with the given level tags; the CFA image
    in IFD0, or in a SubIFD under a thumbnail as Adobe's converter writes it."""
    head = [(271, "s", 0, "Test", True), (272, "s", 0, "Cam", True), (50706, "B", 4, (1, 4, 0, 0), True),
            (50707, "B", 4, (1, 1, 0, 0), True), (50708, "s", 0, "Test Cam", True),
            (50721, "2i", 9, IDENTITY, True), (50778, "H", 1, 21, True),
            (33434, "2I", 1, (1, 50), True), (33437, "2I", 1, (28, 10), True)]
    cfa = [(33421, "H", 2, (2, 2), True), (33422, "B", 4, (0, 1, 1, 2), True),
           (50713, "H", 2, repeat, True), (50714, "I", len(black), tuple(black), True)]
    if white is not None:
        cfa.append((50717, "I", 1, white, True))
    cfa += list(raw_tags)
    mosaic = np.ascontiguousarray(mosaic, np.uint16)
    with tifffile.TiffWriter(path) as tw:
        if subifd:
            tw.write(np.zeros((8, 12, 3), np.uint8), photometric="rgb", subfiletype=1, subifds=1,
                     extratags=head, metadata=None, software=False)
            tw.write(mosaic, photometric=32803, subfiletype=0, extratags=cfa, metadata=None, software=False)
        else:
            tw.write(mosaic, photometric=32803, extratags=head + cfa, metadata=None, software=False)
    return path


def _mosaic(shape, low=400, high=3000, seed=0):
    return np.random.default_rng(seed).integers(low, high, shape)


def test_a_linearization_table_gives_linear_values_and_caps_white(tmp_path):
    """LibRaw applies the table while unpacking (raw_image is table[code]); without a
    WhiteLevel the DNG default is 65535, but nothing can exceed the table's top."""
    codes = _mosaic((64, 96), 0, 1024)
    table = (np.arange(1024, dtype=np.float64) ** 2 / 1023**2 * 60000).astype(np.uint16)
    lut = [(50712, "H", 1024, tuple(int(x) for x in table), True)]
    for white, expected in ((None, 60000.0), (50000, 50000.0)):
        dng = _write(tmp_path / f"lin-{white}.dng", codes, lut, black=(64,), white=white)
        green, info = read_green(dng)
        assert np.array_equal(green, _green_of(table[codes].astype(np.float64), 64.0))
        assert info.white_level == expected
        assert info.file_white_level == (65535.0 if white is None else 50000.0)
        assert info.exposure.time_text == "1/50" and info.exposure.f_number == 2.8


def test_black_levels_per_cfa_position(tmp_path):
    mosaic = _mosaic((64, 96))
    dng = _write(tmp_path / "bl.dng", mosaic, black=(100, 200, 300, 400), repeat=(2, 2))
    green, info = read_green(dng)
    assert info.black_levels == (100.0, 200.0, 300.0, 400.0)
    assert np.array_equal(green, _green_of(mosaic, np.tile([[100, 200], [300, 400]], (32, 48))))


def test_masked_areas_give_libraws_measured_black(tmp_path):
    """With a MaskedAreas tag LibRaw measures the black of each CFA colour there, in
    place of the BlackLevel tag (the DNG spec allows either); ilt takes LibRaw's."""
    mosaic = _mosaic((64, 104))
    mosaic[:, :8] = np.tile([[300, 310], [320, 330]], (32, 4))
    dng = _write(tmp_path / "masked.dng", mosaic, [(50829, "I", 4, (0, 8, 64, 104), True),
                                                   (50830, "I", 4, (0, 0, 64, 8), True)])
    assert read_dng_levels(dng).masked
    green, info = read_green(dng)
    assert info.full_shape == (64, 96) and info.black_levels == (300.0, 310.0, 320.0, 330.0)
    assert np.array_equal(green, _green_of(mosaic[:, 8:], np.tile([[300, 310], [320, 330]], (32, 48))))


def test_black_level_deltas_apply_per_row_and_column(tmp_path):
    """BlackLevelDeltaH/V (LibRaw adds only their means to the black): the green is the
    photosites less BlackLevel + DeltaV[row] + DeltaH[column], exactly. CFA image in a SubIFD."""
    mosaic = _mosaic((64, 96))
    dh = 40 * ((np.arange(96) // 2) % 2)
    dv = 10 * ((np.arange(64) // 2) % 3)
    rationals = [(50715, "2i", 96, tuple(x for v in dh for x in (int(v), 1)), True),
                 (50716, "2i", 64, tuple(x for v in dv for x in (int(v), 1)), True)]
    dng = _write(tmp_path / "deltas.dng", mosaic, rationals, subifd=True)
    levels = read_dng_levels(dng)
    assert np.array_equal(levels.delta_h, dh) and np.array_equal(levels.delta_v, dv)
    green, info = read_green(dng)
    assert np.array_equal(green, _green_of(mosaic, 100 + dv[:, None] + dh[None, :]))
    assert info.black_levels == pytest.approx((100 + dv.mean() + dh.mean(),) * 4)


def test_an_odd_active_area_keeps_the_black_patterns_phase(tmp_path):
    """The BlackLevel pattern starts at the ActiveArea's top-left (DNG spec). LibRaw
    moves an odd ActiveArea origin (1, 1) to (2, 2), keeping the CFA's phase but not
    the black's; ilt places it from the tags."""
    mosaic = _mosaic((65, 97))
    dng = _write(tmp_path / "odd.dng", mosaic, [(50829, "I", 4, (1, 1, 65, 97), True)],
                 black=(100, 200, 300, 400), repeat=(2, 2))
    green, info = read_green(dng)
    # visible (0, 0) is raw (2, 2), the ActiveArea's (1, 1): blue, black pattern[1][1]
    assert info.full_shape == (63, 95) and info.cfa == "BGGR"
    assert info.black_levels == (400.0, 300.0, 200.0, 100.0)
    visible = mosaic[2:64, 2:96] - np.tile([[400, 300], [200, 100]], (31, 47))
    assert np.array_equal(green, (visible[0::2, 1::2] + visible[1::2, 0::2]) / 2)
