"""What centroids says about flagged spots: a fault (no spot, a second one, clipped) warns
with the beams and what to look at; shape flags, which folds and grazing surfaces make,
are INFO until more than a tenth of the scan has them."""

import logging

from ilt.spots.stage import report_flags
from ilt.spots.table import Spot


def spots_with(flags: dict[int, dict], m: int = 20) -> list[Spot]:
    return [Spot(float(b), 0.0, 1.0, 1.0, 9, dict(flags.get(b, {}))) for b in range(m)]


def warned(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


def test_fault_flags_name_their_beams_and_the_overlay(caplog, tmp_path):
    spots = spots_with({3: {"multiple": 0.4}, 7: {"multiple": 0.2}, 9: {"none": 1.0}, 11: {"elongated": 2.1}})
    names = {b: f"beam-{b:05d}.exr" for b in range(20)}
    with caplog.at_level(logging.INFO, logger="ilt.spots"):
        report_flags(list(range(20)), spots, names, tmp_path / "spots")
    overlay = tmp_path / "spots" / "overlay.png"
    assert warned(caplog) == [
        (f"beam 9: spot flagged none (no spot above the noise: laser off, blocked or aimed outside the view): "
         f"build-isf drops it; look at {overlay}"),
        (f"beams 3, 7: spot flagged multiple (a second spot: a reflection, flare or another light): build-isf drops "
         f"them; look at {overlay}"),
    ]
    infos = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
    assert "beam 11 (beam-00011.exr): elongated=2.1" in infos      # one spot on a fold: INFO


def test_shape_flags_warn_past_a_tenth_of_the_scan(caplog, tmp_path):
    names = {b: "" for b in range(20)}
    with caplog.at_level(logging.INFO, logger="ilt.spots"):
        report_flags(list(range(20)), spots_with({1: {"elongated": 2.0}, 2: {"large": 3.0}}), names, tmp_path)
    assert warned(caplog) == []                                     # 2 of 20: not past a tenth
    with caplog.at_level(logging.INFO, logger="ilt.spots"):
        report_flags(list(range(20)), spots_with({1: {"elongated": 2.0}, 2: {"large": 3.0}, 5: {"outside": 1.0}}),
                     names, tmp_path)
    (line,) = warned(caplog)
    assert line.startswith("3 of 20 beams have flagged spots (elongated, large, outside)")
