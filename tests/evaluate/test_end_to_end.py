"""The simulated rig loses little to capture, RAW and merge (issue 7): its bounce errors against
the renderer's truth are at most 1.2x those of the same decomposition from noise-free frames."""

import numpy as np
import pytest

from ilt.evaluate.end_to_end import compare, green_grid, ideal_workspace
from ilt.io.workspace_dirs import Workspace
from ilt.sim.sensor import SensorModel
from ilt.workspace.pipeline import load_run_config, run_pipeline
from tests.capture_helpers import run_rig_toml

RIG = run_rig_toml(16, 16, "spot = 0.1", """\
[photos]
sim = ["flashlight", "room"]

[decompose]
bounces = 4
""")


@pytest.fixture(scope="module")
def figures(tmp_path_factory):
    root = tmp_path_factory.mktemp("e2e")
    (root / "rig.toml").write_text(RIG)
    cfg = load_run_config(root / "rig.toml")
    run_pipeline(Workspace(root / "rig"), cfg)
    ideal_workspace(cfg.rig, cfg.photo_kinds, root / "ideal", n_bounces=4)
    return compare(root / "rig", root / "ideal", cfg.rig, cfg.photo_kinds, n_bounces=3)


def test_the_rig_adds_at_most_20_percent_to_the_bounce_errors(figures):
    for kind, f in figures.items():
        assert max(f["ideal"]) < 0.1, (kind, f)             # the cells' discretisation error, small
        assert max(f["ratio"]) <= 1.2, (kind, f)


def test_green_grid_averages_the_two_green_sites():
    sensor = SensorModel(width=24, height=22)               # RGGB: greens at (0, 1) and (1, 0)
    frame = np.arange(22 * 24, dtype=float).reshape(22, 24)[:21, :23]
    green = green_grid(frame, sensor)
    assert green.shape == (11, 12)
    assert green[0, 0] == 0.5 * (frame[0, 1] + frame[1, 0])
    assert green[10, 11] == 0.0                              # both sites off the rendered frame
