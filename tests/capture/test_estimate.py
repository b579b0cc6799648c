"""`ilt capture --estimate`: the scan's time before the scan, from the config and from
earlier capture logs (ilt/capture/estimate.py)."""

from __future__ import annotations

import json
from datetime import datetime
from fractions import Fraction

import pytest
from click.testing import CliRunner

from ilt.capture.estimate import FRAME_OVERHEAD, LASER_SWITCH, MOVE_OVERHEAD, PTU_RESOLUTION, estimate
from ilt.capture.log import read_log
from ilt.capture.plan import make_plan, to_steps
from ilt.cli import cli
from tests.capture_helpers import small_config, toml_text


def test_a_tethered_dslr_scan_is_the_sum_of_its_parts():
    """A gphoto2 camera on a real unit (no speed given): every part by hand from the
    config: 8 beams, 3 exposures + a dark frame, 1 s a frame, 0.5 s settle, travel at
    1000 positions/s from home."""
    cfg = small_config(ptu={"port": "/dev/ttyUSB0", "settle": 0.5}, camera={"backend": "gphoto2"})
    result = estimate(cfg)
    m, shutter = 8, float(Fraction(1, 15) + Fraction(1, 250) + Fraction(1, 4000))
    steps = to_steps(make_plan(cfg.plan), PTU_RESOLUTION)
    travel = (abs(steps[0, 0]) + sum(abs(int(b) - int(a)) for a, b in zip(steps[:-1, 0], steps[1:, 0]))) / 1000.0
    assert result.parts["settle"] == pytest.approx(0.5 * m)
    assert result.parts["exposures"] == pytest.approx(shutter * m)
    assert result.parts["downloads"] == pytest.approx(FRAME_OVERHEAD["gphoto2"] * 3 * m)
    assert result.parts["dark"] == pytest.approx((1 / 15 + FRAME_OVERHEAD["gphoto2"]) * m)
    assert result.parts["laser"] == pytest.approx(2 * LASER_SWITCH * m)
    assert result.parts["moves"] == pytest.approx(travel + MOVE_OVERHEAD * m)
    assert result.seconds == pytest.approx(sum(result.parts.values()))
    assert any("[ptu] speed" in n for n in result.notes)


def test_the_estimate_from_an_earlier_log_is_within_a_quarter_of_the_scan_it_predicts(tmp_path):
    """Shoot 8 beams on the emulated rig, then estimate the same scan from its log: the
    estimate is within 25 % of the logged span (the defaults alone are not held to it). The
    settle is 0.1 s a beam, so that the scan is mostly what the estimate models: at 0.02 s its
    whole span was 0.37 s, and a loaded machine's tenth of a second outside every part failed it."""
    config = tmp_path / "rig.toml"
    config.write_text(toml_text(ptu={"settle": 0.1}))
    runner = CliRunner()
    shot = runner.invoke(cli, ["-q", "capture", str(config), "-o", str(tmp_path / "cap")])
    assert shot.exit_code == 0, shot.output
    times = [datetime.fromisoformat(r["time"]) for r in read_log(tmp_path / "cap" / "capture.jsonl")]
    span = (times[-1] - times[0]).total_seconds()
    out = runner.invoke(cli, ["capture", "--estimate", str(config), "-o", str(tmp_path / "cap"), "--json"])
    assert out.exit_code == 0, out.output
    data = json.loads(out.output)
    assert "capture log" in data["sources"]["downloads"]
    assert abs(data["seconds"] - span) <= 0.25 * span, (data["seconds"], span, data["parts"])


def test_estimate_touches_nothing_and_log_needs_it(tmp_path):
    config = tmp_path / "rig.toml"
    config.write_text(toml_text())
    runner = CliRunner()
    out = runner.invoke(cli, ["capture", "--estimate", str(config), "-w", str(tmp_path)])
    assert out.exit_code == 0 and "total" in out.output and "8 beams" in out.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.toml"]
    log = tmp_path / "capture.jsonl"
    log.write_text("")
    refused = runner.invoke(cli, ["capture", str(config), "--log", str(log), "-w", str(tmp_path)])
    assert refused.exit_code == 2 and "--log is for --estimate" in refused.output
