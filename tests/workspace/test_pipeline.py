"""`ilt run` / `ilt status` on a small simulated rig: skipping, staleness, workspace."""

import json

import pytest
from click.testing import CliRunner

from ilt.cli import cli
from ilt.io.workspace_dirs import Workspace
from ilt.workspace.pipeline import load_run_config, workspace_status
from tests.capture_helpers import SMALL_RIG, run_rig_toml


def run(*args):
    result = CliRunner().invoke(cli, list(args))
    assert result.exit_code == 0, result.output
    return result


def stages_run(result) -> list[str]:
    return [s["stage"] for s in json.loads(result.stdout) if s["ran"]]


def test_first_run_writes_every_stage(workspace):
    for sub in ("capture", "hdr", "spots", "isf", "photos", "decompose"):
        assert (workspace / sub / "manifest.json").exists()
    assert (workspace / "decompose" / "flashlight" / "bounce-1.exr").exists()
    assert (workspace / "rig.toml").read_text() == SMALL_RIG
    # the emulated rig's noisy scan of a matte scene passes the reciprocity check, above its noise floor
    verdict = json.loads((workspace / "isf" / "lambertian.json").read_text())
    assert verdict["verdict"] == "lambertian" and 0 < verdict["noise_floor"] and verdict["excess"] < verdict["tolerance"]
    summary = json.loads((workspace / "decompose" / "flashlight" / "summary.json").read_text())
    assert summary["lambertian"]["verdict"] == "lambertian" and summary["lambertian"]["accepted"] is False


def test_build_isf_reads_the_frames_centroids_kept_and_leaves_none(workspace, tmp_path):
    """`ilt run` decodes every EXR once (centroids keeps the frames for build-isf): its T
    is the one build-isf makes from the EXR files, and the scratch copies are gone."""
    import numpy as np

    from ilt.isf.build import build_isf
    from ilt.workspace.pipeline import SCRATCH_DIR

    assert not (workspace / SCRATCH_DIR).exists()
    build_isf(workspace / "hdr", workspace / "spots", tmp_path / "isf", workers=1)
    for name in ("T.npy", "scales.npy"):
        assert np.array_equal(np.load(workspace / "isf" / name), np.load(tmp_path / "isf" / name)), name


def test_a_wrong_spot_warns_at_build_isf_and_decompose_refuses_its_t(workspace, tmp_path):
    """Two beams' spots swapped (as when a reflection is taken for a spot): build-isf
    says which beams light another's cell more than their own, and decompose refuses
    the T (its series diverges), one line, nothing written."""
    import shutil

    shutil.copytree(workspace / "spots", tmp_path / "spots")
    lines = (tmp_path / "spots" / "spots.csv").read_text().splitlines()
    a, b = lines[3].split(","), lines[4].split(",")
    a[1:3], b[1:3] = b[1:3], a[1:3]
    lines[3], lines[4] = ",".join(a), ",".join(b)
    (tmp_path / "spots" / "spots.csv").write_text("\n".join(lines) + "\n")
    built = CliRunner().invoke(cli, ["build-isf", str(workspace / "hdr"), str(tmp_path / "spots"), "-o",
                                     str(tmp_path / "isf"), "-j", "1"])
    assert built.exit_code == 0, built.output
    warned = [line for line in built.stderr.splitlines() if "WARNING" in line]
    assert len(warned) == 1 and "2 beams light another beam's cell more than their own" in warned[0]
    assert f"{a[0]} -> {b[0]}, {b[0]} -> {a[0]}" in warned[0] and "overlay.png" in warned[0]
    photo = workspace / "photos" / "flashlight.exr"
    refused = CliRunner().invoke(cli, ["decompose", "--isf", str(tmp_path / "isf"), str(photo), "-o",
                                       str(tmp_path / "out"), "--no-cache"])
    assert refused.exit_code != 0 and "diverges" in refused.stderr and not (tmp_path / "out").exists()


def test_saturated_pixels_an_unwritable_cache_and_no_frame_sum_warn_with_what_to_do(workspace, tmp_path):
    """Three things a user should fix, each one line: a photo's pixels clipped in every
    exposure (its .saturated.png), an operator cache that cannot be written, a spots
    directory without the frames' sum (so cells are not cut by the lit mask)."""
    import shutil

    import cv2
    import numpy as np

    photo = tmp_path / "flashlight.exr"
    shutil.copy(workspace / "photos" / "flashlight.exr", photo)
    frame = cv2.imread(str(workspace / "photos" / "flashlight.saturated.png"), cv2.IMREAD_GRAYSCALE)
    mask = np.zeros_like(frame)
    mask[2:4, 5:8] = 255                                            # 6 pixels clipped
    cv2.imwrite(str(tmp_path / "flashlight.saturated.png"), mask)
    (tmp_path / "cache").write_text("a file, not a directory")
    result = CliRunner().invoke(cli, ["decompose", "--isf", str(workspace / "isf"), str(photo), "-o",
                                      str(tmp_path / "out"), "--solver", "dense"],
                                env={"ILT_CACHE_DIR": str(tmp_path / "cache")})
    assert result.exit_code == 0, result.output
    warned = [line for line in result.stderr.splitlines() if "WARNING" in line]
    assert len(warned) == 2, warned
    assert "could not cache the operators in" in warned[0]
    assert f"{photo}: 6 saturated pixels (values are lower bounds) left out" in warned[1]
    assert "shorter exposures" in warned[1]
    shutil.copytree(workspace / "spots", tmp_path / "spots")
    (tmp_path / "spots" / "sum.exr").unlink()
    built = CliRunner().invoke(cli, ["build-isf", str(workspace / "hdr"), str(tmp_path / "spots"), "-o",
                                     str(tmp_path / "isf"), "-j", "1"])
    assert built.exit_code == 0, built.output
    (line,) = [line for line in built.stderr.splitlines() if "WARNING" in line]
    assert f"{tmp_path / 'spots' / 'sum.exr'}: missing, so no lit mask" in line


def test_second_run_skips_every_stage(workspace):
    result = run("run", "-w", str(workspace), "--json")
    assert stages_run(result) == []
    assert "every stage was up to date" in result.stderr
    status = run("status", "-w", str(workspace)).stdout
    assert status.count("done") == 6, status


def test_a_run_judges_each_stage_once(workspace, monkeypatch):
    """`ilt run` finds each stage's state, and fingerprints its inputs, once: the
    assessment made before the run (for a changed file) holds until a stage runs
    (before: the capture three times, every other stage twice)."""
    import ilt.io.stage as stage_module
    import ilt.workspace.pipeline as pipeline

    judged, fingerprinted = [], []
    real_state, real_inputs = stage_module.stage_state, pipeline.input_fingerprints

    def counting(directory, stage, *args, **kwargs):
        judged.append(stage)
        return real_state(directory, stage, *args, **kwargs)

    monkeypatch.setattr(stage_module, "stage_state", counting)
    monkeypatch.setattr(pipeline, "stage_state", counting)
    monkeypatch.setattr(pipeline, "input_fingerprints", lambda s: fingerprinted.append(s.name) or real_inputs(s))
    assert stages_run(run("run", "-w", str(workspace), "--json")) == []
    every = ["capture", "merge", "centroids", "build-isf", "photos", "decompose"]
    assert judged == every and fingerprinted == every


def test_decompose_run_by_hand_is_done_when_it_holds_what_the_run_would(workspace, tmp_path):
    """A decompose/ that `ilt decompose` filled by hand (no stage manifest of its own) is
    done when every photo's manifest records this T, the photo and the config's options,
    and stale, naming what differs, otherwise. `ilt run` then takes it as it is, or
    replaces it: its files are ilt's own."""
    import shutil

    ws = tmp_path / "ws"
    shutil.copytree(workspace, ws)
    shutil.rmtree(ws / "decompose")
    photo = str(ws / "photos" / "flashlight.exr")

    def decompose_state():
        return json.loads(run("status", "-w", str(ws), "--json").stdout)[-1]

    run("decompose", photo, "-w", str(ws))   # 8 bounces; the config asks for 4
    state = decompose_state()
    assert state["state"] == "stale" and "flashlight.exr decomposed with bounces 8 (wanted 4)" in state["reason"]
    assert stages_run(run("run", "-w", str(ws), "--json")) == ["decompose"]   # replaced
    assert json.loads((ws / "decompose" / "flashlight" / "manifest.json").read_text())["parameters"]["bounces"] == 4

    shutil.rmtree(ws / "decompose")
    run("decompose", photo, "-w", str(ws), "--bounces", "4")
    assert decompose_state()["state"] == "done"
    made = (ws / "decompose" / "flashlight" / "bounces.npy").stat().st_mtime_ns
    assert stages_run(run("run", "-w", str(ws), "--json")) == []
    assert (ws / "decompose" / "manifest.json").exists()
    assert (ws / "decompose" / "flashlight" / "bounces.npy").stat().st_mtime_ns == made
    assert run("status", "-w", str(ws), "--verify").stdout.count("done") == 6


def test_changed_merge_parameter_reruns_merge_and_after(workspace, tmp_path):
    changed = tmp_path / "changed.toml"
    changed.write_text(SMALL_RIG + "\n[merge]\nmargin = 0.05\n")
    status = json.loads(run("status", str(changed), "-w", str(workspace), "--json").stdout)
    states = {s["stage"]: s for s in status}
    assert states["capture"]["state"] == "done" and states["photos"]["state"] == "stale"
    assert states["merge"]["state"] == "stale" and "margin" in states["merge"]["reason"]
    assert states["centroids"]["reason"] == "after merge"
    capture_log = (workspace / "capture" / "capture.jsonl").read_text()
    result = run("run", str(changed), "-w", str(workspace), "--json")
    assert stages_run(result) == ["merge", "centroids", "build-isf", "photos", "decompose"]
    assert (workspace / "capture" / "capture.jsonl").read_text() == capture_log
    assert stages_run(run("run", "-w", str(workspace), "--json")) == []
    (workspace / "rig.toml").write_text(SMALL_RIG)  # back, for the tests after this one
    assert stages_run(run("run", "-w", str(workspace), "--json"))[0] == "merge"


def test_status_reports_missing_and_incomplete(tmp_path):
    (tmp_path / "rig.toml").write_text(SMALL_RIG)
    (tmp_path / "capture" / "beam-00000").mkdir(parents=True)
    states = workspace_status(Workspace(tmp_path), load_run_config(tmp_path / "rig.toml"))
    assert [s.state for s in states] == ["missing"] * 6
    assert "incomplete" in states[0].reason


def test_changed_scan_is_not_overwritten_without_force(workspace, tmp_path):
    other = tmp_path / "other.toml"
    other.write_text(SMALL_RIG.replace("1/125", "1/250"))
    result = CliRunner().invoke(cli, ["run", str(other), "-w", str(workspace)])
    assert result.exit_code == 1 and "--force" in result.output
    assert (workspace / "rig.toml").read_text() == SMALL_RIG     # a refused run changes nothing


def test_unknown_stage_option_names_the_key(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(SMALL_RIG + "\n[merge]\nmargins = 0.05\n")
    result = CliRunner().invoke(cli, ["status", str(bad), "-w", str(tmp_path)])
    assert result.exit_code == 1 and "margins" in result.output


def test_no_config_is_a_one_line_error(tmp_path):
    result = CliRunner().invoke(cli, ["status", "-w", str(tmp_path)])
    assert result.exit_code == 1 and "rig.toml" in result.output


def test_quiet_and_no_progress_bars_off_a_terminal(workspace, tmp_path):
    quiet = CliRunner().invoke(cli, ["-q", "run", "-w", str(workspace)])
    assert quiet.exit_code == 0 and quiet.stderr == "", quiet.stderr
    spots = ["centroids", str(workspace / "hdr"), "-o", str(tmp_path / "spots"), "--workers", "1"]
    logged = CliRunner().invoke(cli, spots)          # stderr is not a terminal here
    assert logged.exit_code == 0 and "\r" not in logged.stderr and "[" not in logged.stderr, logged.stderr
    assert CliRunner().invoke(cli, ["-q", *spots, "--force"]).stderr == ""


@pytest.mark.parametrize("section, value, message", [
    ("merge", "margin = 0.9", r"\[merge\]: margin = 0.9: 0.9 is not in the range 0<=x<=0.5"),
    ("merge", "color = 1", r"\[merge\]: color = 1: must be true or false"),
    ("merge", 'compression = "b44"', r"\[merge\]: compression = 'b44': 'b44' is not one of"),
    ("build-isf", "fine-degree = 1.5", r"\[build-isf\]: fine_degree = 1.5: must be a whole number"),
    ("centroids", "workers = 0", r"\[centroids\]: workers = 0: 0 is not in the range x>=1"),
    ("decompose", "bounces = true", r"\[decompose\]: bounces = True: must be a number"),
])
def test_stage_values_are_checked_as_the_command_line_checks_them(tmp_path, section, value, message):
    """A value the stage's command would refuse is refused in the config, naming the
    file, section and key, before anything runs; one it accepts is kept as written."""
    from ilt.capture.config import ConfigError
    from ilt.workspace.pipeline import load_run_config

    (tmp_path / "rig.toml").write_text(run_rig_toml(16, 8, "", f"[{section}]\n{value}\n"))
    with pytest.raises(ConfigError, match=message):
        load_run_config(tmp_path / "rig.toml")
    (tmp_path / "ok.toml").write_text(run_rig_toml(16, 8, "", "[merge]\nmargin = 0\n"))
    margin = load_run_config(tmp_path / "ok.toml").merge["margin"]
    assert margin == 0 and isinstance(margin, int)


def test_cells_ended_at_folds_are_part_of_build_isfs_fingerprint():
    """build-isf's fold_cells is fingerprinted, on (its default) or off: a workspace built
    before cells ended at folds by default is built again; the workers are not."""
    from ilt.workspace.pipeline import fingerprinted

    before = {"sampling": "cell", "fine_degree": 1}
    assert fingerprinted({**before, "fold_cells": True, "workers": 2}) == {**before, "fold_cells": True}
    assert fingerprinted({**before, "fold_cells": False, "workers": 2}) == {**before, "fold_cells": False}