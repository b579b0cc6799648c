"""Stage skipping (ilt/io/stage.py): done / stale (why) / missing, cheap fingerprints."""

import json

import pytest

from ilt.io.manifest import write_manifest
from ilt.io.stage import (
    DONE,
    MISSING,
    STALE,
    fingerprint_input,
    fingerprint_stage,
    run_stage,
    stage_state,
    write_record,
)
from ilt.io.staged import staged_directory


def make_stage(path, stage="merge", parameters=None, content=b"frame"):
    with staged_directory(path, force=True) as tmp:
        (tmp / "beam-00000.exr").write_bytes(content)
        write_manifest(tmp, stage, parameters or {"margin": 0.03})
    return path


def test_missing_then_done_after_run(tmp_path):
    out = tmp_path / "hdr"
    assert stage_state(out, "merge", {"margin": 0.03}).state == MISSING
    calls = []
    ran, before = run_stage(out, "merge", {"margin": 0.03}, {"capture": "sha256:a"},
                            lambda: calls.append(make_stage(out)))
    assert ran and before.state == MISSING
    assert stage_state(out, "merge", {"margin": 0.03}, {"capture": "sha256:a"}).done
    ran, before = run_stage(out, "merge", {"margin": 0.03}, {"capture": "sha256:a"},
                            lambda: calls.append(make_stage(out)))
    assert not ran and before.done and len(calls) == 1


def test_stale_says_what_changed(tmp_path):
    out = make_stage(tmp_path / "hdr")
    write_record(out, "merge", {"margin": 0.03}, {"capture": "sha256:a"})
    s = stage_state(out, "merge", {"margin": 0.05}, {"capture": "sha256:a"})
    assert s.state == STALE and "margin" in s.reason and "0.05" in s.reason
    s = stage_state(out, "merge", {"margin": 0.03}, {"capture": "sha256:b"})
    assert s.state == STALE and "input capture changed" in s.reason
    s = stage_state(out, "merge", {"margin": 0.03}, {"capture": "sha256:a", "response": "sha256:c"})
    assert s.state == STALE and "response new" in s.reason


def test_force_reruns(tmp_path):
    out = tmp_path / "hdr"
    run_stage(out, "merge", {}, {}, lambda: make_stage(out, parameters={}))
    ran, before = run_stage(out, "merge", {}, {}, lambda: make_stage(out, parameters={}), force=True)
    assert ran and before.done


def test_incomplete_directory_is_never_done(tmp_path):
    out = tmp_path / "capture"
    (out / "beam-00000").mkdir(parents=True)
    s = stage_state(out, "capture", {})
    assert s.state == MISSING and "incomplete" in s.reason


def test_changed_outputs_make_it_stale(tmp_path):
    out = make_stage(tmp_path / "hdr")
    write_record(out, "merge", {"margin": 0.03}, {})
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["outputs"]["beam-00000.exr"] = "sha256:other"
    (out / "manifest.json").write_text(json.dumps(manifest))
    s = stage_state(out, "merge", {"margin": 0.03})
    assert s.state == STALE and "outputs changed" in s.reason


def test_without_record_parameters_decide(tmp_path):
    out = make_stage(tmp_path / "capture", stage="capture", parameters={"plan": [1, 2], "ptu": "x"})
    assert stage_state(out, "capture", {"plan": [1, 2]}).state == DONE
    assert stage_state(out, "capture", {"plan": [1, 3]}).state == STALE
    assert "no run record" in stage_state(out, "capture", {"plan": [1, 2]}, {"x": "sha256:1"}).reason


def test_wrong_stage_is_stale(tmp_path):
    out = make_stage(tmp_path / "hdr", stage="centroids")
    assert stage_state(out, "merge", {"margin": 0.03}).state == STALE


def test_stage_fingerprint_reads_the_manifest_only(tmp_path):
    out = make_stage(tmp_path / "hdr")
    fp = fingerprint_stage(out)
    (out / "beam-00000.exr").write_bytes(b"changed behind ilt's back")  # not re-hashed
    assert fingerprint_stage(out) == fp == fingerprint_input(out)
    make_stage(out, content=b"new frame")
    assert fingerprint_stage(out) != fp
    make_stage(out, parameters={"margin": 0.05})  # same outputs, other parameters: downstream re-runs
    assert fingerprint_stage(out) != fp


def test_file_inputs_and_missing_inputs(tmp_path):
    f = tmp_path / "photo.exr"
    f.write_bytes(b"1")
    assert fingerprint_input(f).startswith("sha256:")
    with pytest.raises(ValueError):
        fingerprint_input(tmp_path / "nothing.exr")
