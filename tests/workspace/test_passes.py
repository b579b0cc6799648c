"""`ilt run` with [refine] passes: scan, refine, capture the new beams into the same capture/."""

import csv
import json

import numpy as np
import pytest
from click.testing import CliRunner

from ilt.capture.log import read_log
from ilt.capture.loop import verify_log
from ilt.cli import cli
from ilt.io.exr import read_exr
from ilt.io.manifest import read_manifest
from tests.capture_helpers import SMALL_RIG

PASSES = "\n[refine]\npasses = {passes}\nbeams = 2\n"
EVERY = ["capture", "merge", "centroids", "build-isf"]


def invoke(*args):
    return CliRunner().invoke(cli, list(args))


@pytest.fixture(scope="module")
def refined(tmp_path_factory):
    root = tmp_path_factory.mktemp("passes")
    config = root / "rig.toml"
    config.write_text(SMALL_RIG + PASSES.format(passes=1))
    result = invoke("run", str(config), "-w", str(root / "ws"), "--json")
    assert result.exit_code == 0, result.output
    return root, config, json.loads(result.stdout)


def test_a_pass_refines_then_captures_into_the_same_scan(refined):
    root, _, summary = refined
    ws = root / "ws"
    assert [s["stage"] for s in summary] == EVERY + ["refine"] + EVERY + ["photos", "decompose"]
    assert all(s["ran"] for s in summary)
    manifest = read_manifest(ws / "capture")
    assert manifest["plan"]["passes"] == [8, 10] and len(manifest["beams"]) == 10
    events = [r["event"] for r in read_log(ws / "capture" / "capture.jsonl")]
    assert events.count("start") == 1 and events.count("extend") == 1
    assert verify_log(ws / "capture") == []
    isf = read_manifest(ws / "isf")
    assert isf["plan_m"] == 10 and isf["m"] == 10 - len(isf["dropped_beams"])
    # the build with the new beams keeps what the one refine read covered (its copy of the cells)
    kept = ws / "passes" / "pass-1" / "cells.exr"
    assert isf["parameters"]["keep_covered"] == str(kept) and str(kept) in isf["inputs"]
    assert isf["coverage"]["lit"]["kept_from"]["cells"] == str(kept)
    before, after = (read_exr(p)[0][..., 0] >= 0 for p in (kept, ws / "isf" / "cells.exr"))
    assert before.any() and after[before].all()


def test_new_beams_land_where_the_simulator_puts_them(refined):
    """Each new beam's spot is where its angles put it in the simulated scene (the
    plan's affine map, RenderedScene.beam_between), and within 1.5 px of refine's
    target (the pointing map's error at a fold: the spot cut by the crease)."""
    from ilt.sim.render import render_scene

    ws = refined[0] / "ws"
    with open(ws / "passes" / "landing.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    with open(ws / "passes" / "pass-1" / "refine.csv", newline="") as f:
        pans = [float(r["pan"]) for r in csv.DictReader(f)]
    assert [int(r["beam"]) for r in rows] == [8, 9]
    dropped = read_manifest(ws / "isf")["dropped_beams"]
    assert [int(r["beam"]) for r in rows if r["flags"] == "dropped"] == dropped
    scene = render_scene("m", beams=8, px_per_beam=8, rows=8, spot=0.1)
    for row, pan in zip(rows, pans):
        if row["flags"]:
            continue
        spot = np.array([float(row["spot_x"]), float(row["spot_y"])])
        truth = scene.beam_between(((pan + 20) / 40 * 7,)).centres[0]
        assert np.hypot(*(spot - truth)) < 0.15, (spot, truth)
        assert float(row["error_px"]) < 1.5
    status = invoke("status", "-w", str(ws)).stdout
    assert "refine     done: pass 1 of 1 (8 + 2 beams); landing" in status, status


def test_a_second_run_does_nothing(refined):
    root, config, _ = refined
    result = invoke("run", str(config), "-w", str(root / "ws"), "--json")
    assert result.exit_code == 0, result.output
    assert [s["stage"] for s in json.loads(result.stdout) if s["ran"]] == []


def test_fewer_passes_than_the_scan_holds_is_refused(refined, tmp_path):
    root, _, _ = refined
    fewer = tmp_path / "fewer.toml"
    fewer.write_text(SMALL_RIG)
    before = (root / "ws" / "rig.toml").read_text()
    result = invoke("run", str(fewer), "-w", str(root / "ws"))
    assert result.exit_code == 1
    assert "holds 1 refine pass(es), the config asks for 0" in result.output
    assert len(result.output.strip().splitlines()) == 1
    assert (root / "ws" / "rig.toml").read_text() == before


def test_an_edited_pass_makes_the_capture_stale_not_re_aimed(refined, tmp_path):
    root, config, _ = refined
    csv_path = root / "ws" / "passes" / "pass-1" / "refine.csv"
    data = csv_path.read_bytes()
    try:
        csv_path.write_bytes(data.replace(b",0.0,", b",0.5,", 1))
        result = invoke("run", str(config), "-w", str(root / "ws"))
        assert result.exit_code == 1
        assert "parameter passes changed; the scan differs from the config" in result.output
    finally:
        csv_path.write_bytes(data)


def test_another_pass_adds_only_its_beams_and_resumes_after_a_fault(refined):
    """passes = 2 on a scan of one: refine pass 2 and its 2 beams only; a fault
    in its capture (the pan-tilt unit unplugged) stops the run, and the next run shoots the beam left."""
    root, config, _ = refined
    ws = root / "ws"
    log = ws / "capture" / "capture.jsonl"
    shot = sum(r["event"] == "beam_done" for r in read_log(log))
    faulty = config.with_name("faulty.toml")
    text = SMALL_RIG + PASSES.format(passes=2)
    faulty.write_text(text.replace("emulator_speed = 20000", 'emulator_speed = 20000\nemulator_faults = ["unplug:PP@4"]'))
    result = invoke("run", str(faulty), "-w", str(ws))
    assert result.exit_code == 1 and "disconnected" in result.output, result.output
    status = invoke("status", str(faulty), "-w", str(ws)).stdout
    assert "capture    missing: refine pass 2: its beams to shoot" in status, status
    assert sum(r["event"] == "beam_done" for r in read_log(log)) == shot + 1
    config.write_text(text)
    result = invoke("run", str(config), "-w", str(ws), "--json")
    assert result.exit_code == 0, result.output
    ran = [s["stage"] for s in json.loads(result.stdout) if s["ran"]]
    assert ran == EVERY + ["decompose"]   # the photos do not depend on the beams
    assert sum(r["event"] == "beam_done" for r in read_log(log)) == shot + 2
    assert read_manifest(ws / "capture")["plan"]["passes"] == [8, 10, 12]
    assert verify_log(ws / "capture") == []


@pytest.mark.parametrize("section, message", [
    ("passes = 2", "passes = 2 needs beams = K"),
    ("passes = 1\nbeams = 4\nhours = 1.0", "beams and hours both given"),
    ("passes = -1\nbeams = 4", "passes = -1: must be a whole number >= 0"),
    ("passes = 1\nbeams = 1", "beams = 1: must be a whole number >= 2"),
    ("passes = 1\nhours = 0", "hours = 0: must be a number >= 0 and > 0"),
    ("passes = 1\nbeam = 4", "unknown key 'beam'"),
])
def test_bad_refine_sections_are_one_line(tmp_path, section, message):
    config = tmp_path / "bad.toml"
    config.write_text(SMALL_RIG + "\n[refine]\n" + section + "\n")
    result = invoke("run", str(config), "-w", str(tmp_path / "ws"))
    assert result.exit_code == 1 and message in result.output, result.output
    assert not (tmp_path / "ws").exists()


def test_the_report_shows_each_new_beams_landing(refined, tmp_path):
    ws = refined[0] / "ws"
    result = invoke("report", "-w", str(ws), "-o", str(tmp_path / "report"))
    assert result.exit_code == 0, result.output
    page = (tmp_path / "report" / "index.html").read_text()
    assert "Refine passes: where the new beams landed" in page
    with open(ws / "passes" / "landing.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) >= 2 and page.count("<tr><td>") == len(rows)   # one row a new beam (2 a pass)


def test_hours_share_the_rig_time_over_the_passes_left(tmp_path):
    """hours = H: each pass gets what is left of H at the capture estimate's time a beam,
    shared over the passes left; none left writes an empty pass, and the run stops there."""
    from ilt.capture.estimate import estimate
    from ilt.io.workspace_dirs import Workspace
    from ilt.workspace.passes import (
        RefineConfig,
        beams_for_pass,
        completed_passes,
        finished,
        run_refine_pass,
    )
    from tests.capture_helpers import small_config

    rig = small_config()
    est = estimate(rig)
    per_beam = est.seconds / est.beams
    cfg = RefineConfig(passes=2, hours=20 * per_beam / 3600)
    assert beams_for_pass(cfg, rig, [], tmp_path / "capture") == 10
    ws = Workspace(tmp_path / "ws")
    none = RefineConfig(passes=2, hours=3.9 * per_beam / 3600)       # 1.95 beams a pass: not a pair
    done = run_refine_pass(ws, none, rig, [])
    assert done.beams == 0 and completed_passes(ws)[0].angles.shape == (0, 2)
    assert finished(none, [done])
