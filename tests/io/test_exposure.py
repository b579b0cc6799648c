"""ilt.io.exposure: which exposure facts are believed, in which order, and what is said."""

import logging
from fractions import Fraction
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner

from ilt.cli import cli
from ilt.io.exposure import (
    EXIF_TOLERANCE_STOPS,
    ExposureError,
    check_range,
    exif_facts,
    read_exif,
    resolve_facts,
)
from ilt.io.exr import read_exr
from ilt.sim.sensor import SensorModel, write_dng

REALDATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "realdata"
FILE = Path("frame.dng")


class Tag:
    """What exifread gives for a tag: ``values``, a list of ratios."""

    def __init__(self, value):
        self.values = [value]


def tags(time=None, f_number=None, **more):
    out = {}
    if time is not None:
        out["EXIF ExposureTime"] = Tag(Fraction(time))
    if f_number is not None:
        out["EXIF FNumber"] = Tag(Fraction(f_number))
    out.update({f"EXIF {k}": Tag(Fraction(v)) for k, v in more.items()})
    return out


@pytest.mark.parametrize("time, why", [
    ("0", "is 0 (the camera or recorder wrote none)"),
    ("-1/50", "is -1/50 s (negative)"),
    ("7200", "is 7200 s (outside 1e-06 s ... 1 hour)"),
    ("1/2000000", "is 1/2000000 s (outside 1e-06 s ... 1 hour)"),
])
def test_an_unusable_exif_time_is_not_used_and_the_refusal_says_why(time, why):
    assert check_range(Fraction(time), "time") == why
    assert exif_facts(tags(time, "2.8")) == (None, Fraction("2.8"))
    with pytest.raises(ExposureError) as err:
        resolve_facts(FILE, None, None, tags(time, "2.8"))
    assert str(err.value) == f"frame.dng: EXIF exposure time {why}; give --times"


@pytest.mark.parametrize("f_number", ["0", "-2", "0.4", "300"])
def test_an_unusable_exif_f_number_is_not_used(f_number):
    assert exif_facts(tags("1/50", f_number)) == (Fraction(1, 50), None)
    facts = resolve_facts(FILE, None, None, tags("1/50", f_number))
    assert (facts.exposure_time, facts.f_number, facts.source) == (0.02, 1.0, "exif")


def test_believable_extremes_are_used():
    assert exif_facts(tags("3600", "0.5")) == (Fraction(3600), Fraction(1, 2))
    assert exif_facts(tags("1/1000000", "256")) == (Fraction(1, 1000000), Fraction(256))


def test_libraw_one_second_from_apex_zero_is_not_used():
    """Magic Lantern's DNG: ExposureTime 0, ShutterSpeedValue 0, from which LibRaw makes
    1 s (2^-0) and f/1: neither may become the frame's exposure."""
    other = SimpleNamespace(shutter_speed=1.0, aperture=1.0)
    for t in (tags("0", "0", ShutterSpeedValue=0, ApertureValue=0), tags(ShutterSpeedValue=0)):
        with pytest.raises(ExposureError, match=r"^frame\.dng: .*; give --times$"):
            resolve_facts(FILE, None, None, t, other)
    facts = resolve_facts(FILE, None, None, tags("0", "0", ApertureValue=0), other, Fraction(1, 50))
    assert (facts.exposure_time, facts.f_number, facts.source) == (0.02, 1.0, "times")


def test_libraw_values_serve_only_when_believable_and_exif_has_none():
    facts = resolve_facts(FILE, None, None, {}, SimpleNamespace(shutter_speed=0.004, aperture=5.6))
    assert (facts.time_text, facts.f_number, facts.source) == ("1/250", 5.6, "rawpy")
    for garbage in (0.0, -0.01, 1e9, 1e-9, float("nan"), None):
        with pytest.raises(ExposureError, match="no exposure time in the manifest or EXIF; give --times"):
            resolve_facts(FILE, None, None, {}, SimpleNamespace(shutter_speed=garbage, aperture=garbage))


def test_a_hand_time_overrides_exif_and_warns_beyond_the_tolerance(caplog):
    with caplog.at_level(logging.WARNING):
        facts = resolve_facts(FILE, None, None, tags("1/100", "4"), hand_time=Fraction(1, 50))
    assert (facts.exposure_time, facts.f_number, facts.source) == (0.02, 4.0, "times")
    warned = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1
    assert warned[0].getMessage() == "frame.dng: --times gives 1/50 s, its EXIF 1/100 s (1.00 stops apart): using --times"
    caplog.clear()
    # 1/125 against a camera's 1/128: 0.03 stop, within 1/6 stop: no warning, --times still wins
    with caplog.at_level(logging.WARNING):
        facts = resolve_facts(FILE, None, None, tags("1/128"), hand_time=Fraction(1, 125))
    assert EXIF_TOLERANCE_STOPS == pytest.approx(1 / 6)
    assert (facts.time_text, facts.source, caplog.records) == ("1/125", "times", [])


def test_the_manifest_still_comes_first():
    facts = resolve_facts(FILE, "1/60", "2", tags("1/60", "2"), hand_time=Fraction(1, 50))
    assert (facts.time_text, facts.source) == ("1/60", "manifest")
    with pytest.raises(ExposureError, match="the manifest says 1/60 s"):
        resolve_facts(FILE, "1/60", None, tags("1/30"), hand_time=Fraction(1, 60))


def test_hand_time_wins_over_exif_through_the_cli(tmp_path):
    sensor = SensorModel(width=32, height=24)
    dng = write_dng(tmp_path / "shot.dng", np.full((12, 16), 2e5), 1 / 100, 4.0, sensor,
                    np.random.default_rng(0))
    out = tmp_path / "out.exr"
    result = CliRunner().invoke(cli, ["merge", "--bracket", str(dng), "--times", "1/50", "-o", str(out)])
    assert result.exit_code == 0, result.output
    _, attributes = read_exr(out)
    assert attributes["ilt:exposure_times"] == [0.02] and attributes["ilt:f_numbers"] == [4.0]
    warnings = [line for line in result.stderr.splitlines() if "WARNING" in line]
    assert warnings == [(f"ilt: WARNING: {dng}: --times gives 1/50 s, its EXIF 1/100 s (1.00 stops apart): "
                         "using --times")]


def _png(path):
    import cv2

    cv2.imwrite(str(path), np.full((8, 8), 100, np.uint8))
    return path


def test_reading_a_png_logs_nothing_from_exifread(tmp_path, caplog, capsys):
    png = _png(tmp_path / "a.png")
    before = logging.getLogger("exifread").level
    with caplog.at_level(logging.DEBUG):
        assert read_exif(png) == {}
        with open(png, "rb") as f:
            assert read_exif(f) == {} and f.tell() == 0
        assert read_exif(__file__) == {}  # not an image at all: "File format not recognized"
        facts = resolve_facts(png, None, None, hand_time=Fraction(1, 30))
    assert facts.source == "times"
    assert [r for r in caplog.records if r.name.startswith("exifread")] == []
    assert capsys.readouterr().err == ""
    assert logging.getLogger("exifread").level == before


def test_reading_a_png_bracket_for_calibration_logs_nothing_from_exifread(tmp_path, caplog):
    from ilt.hdr.stages import collect_calibration_input

    pngs = [_png(tmp_path / f"{k}.png") for k in range(2)]
    with caplog.at_level(logging.DEBUG):
        data = collect_calibration_input(pngs, [Fraction(1, 30), Fraction(1, 15)])
    assert [f.source for f in data.facts] == ["times", "times"]
    assert [r for r in caplog.records if r.name.startswith("exifread")] == []


def test_a_real_png_without_exif_is_silent(caplog):
    png = REALDATA / "memorial" / "memorial0061.png"
    if not png.is_file():
        pytest.skip("../shared/realdata absent: the Memorial PNGs (no licence) are not in the repository")
    with caplog.at_level(logging.DEBUG):
        facts = resolve_facts(png, None, None, hand_time=Fraction(32))
    assert (facts.exposure_time, facts.source) == (32.0, "times")
    assert [r for r in caplog.records if r.name.startswith("exifread")] == []
