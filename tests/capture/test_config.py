"""Rig config and beam plans: known answers and one-line errors."""

from fractions import Fraction

import numpy as np
import pytest

from ilt.capture.config import ConfigError, load_config, parse_config
from ilt.capture.plan import check_limits, make_plan, to_steps
from tests import ROOT
from tests.capture_helpers import small_config


def test_sim_config_is_the_paper_bracket():

    cfg = load_config(ROOT / "configs" / "sim.toml")
    shutters = [e.shutter for e in cfg.bracket.exposures]
    assert len(shutters) == 11 and shutters[0] == Fraction(1, 15) and shutters[-1] == Fraction(1, 8000)
    assert cfg.bracket.exposures[-1].aperture == 16.0  # the f/16 frame: the shortest relative exposure
    assert [e.relative for e in cfg.bracket.exposures] == sorted((e.relative for e in cfg.bracket.exposures), reverse=True)
    assert make_plan(cfg.plan).m == 32


def test_example_rig_config_parses():

    cfg = load_config(ROOT / "configs" / "rig-example.toml")
    assert cfg.camera.backend == "gphoto2" and make_plan(cfg.plan).layout == (8, 8)


@pytest.mark.parametrize("raw, words", [
    ({"bracket": {"shutter": ["1/0"]}}, "shutter '1/0'"),
    ({"ptu": {"baudrate": 9600}}, "unknown key 'baudrate'"),
    ({"laser": {"control": "serial"}}, "needs a port"),
    ({"camera": {"backend": "webcam"}}, "backend 'webcam'"),
    ({"plan": {"kind": "spiral"}}, "kind 'spiral'"),
    ({"plan": {"count": "many"}}, "count = 'many'"),
    ({"lens": {}}, "unknown section [lens]"),
    ({"dark": {"every": 0}}, "[dark] every 0 must be a whole number of beams >= 1"),
])
def test_bad_config_names_the_key(raw, words):
    with pytest.raises(ConfigError, match=None) as info:
        parse_config(raw, "rig.toml")
    assert "rig.toml" in str(info.value) and words in str(info.value)


def test_plans_line_grid_list_in_degrees_and_steps():
    line = make_plan(small_config(plan={"pan": [-1.0, 1.0], "count": 3}).plan)
    assert line.layout == (1, 3) and line.targets.tolist() == [[-1, 0], [0, 0], [1, 0]]
    grid = make_plan(small_config(plan={"kind": "grid", "pan": [0.0, 2.0], "tilt": [1.0, 0.0], "shape": [2, 3]}).plan)
    assert grid.layout == (2, 3)
    assert grid.targets.tolist() == [[0, 1], [1, 1], [2, 1], [0, 0], [1, 0], [2, 0]]  # scanline order
    lst = make_plan(small_config(plan={"kind": "list", "units": "steps", "points": [[10, -3], [0, 4]]}).plan)
    assert to_steps(lst, (92.5714, 46.2857)).tolist() == [[10, -3], [0, 4]]
    # 1 degree = 3600 arc-seconds = 3600 / 92.5714 steps = 38.89 -> 39
    assert to_steps(line, (92.5714, 46.2857))[:, 0].tolist() == [-39, 0, 39]


def test_out_of_limit_plan_names_the_beam():
    steps = np.array([[0, 0], [4000, 0], [5000, 0]])
    with pytest.raises(ConfigError, match=r"beam 1: pan 4000 steps is outside the unit's limits \[-3090, 3090\] \(2 beam"):
        check_limits(steps, {"pan_min": -3090, "pan_max": 3090, "tilt_min": -907, "tilt_max": 604})


def test_a_laser_switched_by_hand_says_so_before_the_scan(caplog):
    """control = "none": nothing switches the laser, so the user must, and frames are
    labelled on/off as if it obeyed: a warning with what to do."""
    import logging

    from ilt.capture.config import LaserConfig
    from ilt.capture.laser import open_laser

    with caplog.at_level(logging.WARNING, logger="ilt.capture"):
        laser = open_laser(LaserConfig(control="none"), None)
    assert laser.line is None
    assert "laser control 'none': switch the laser by hand" in caplog.text
