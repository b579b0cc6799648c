"""Nothing a user made is ever lost, nothing changed is built on (issue 14): an edited
rig.toml, corrupted or swapped files, a damaged operator cache, paths that leave the
workspace, a multi-photo decompose cut short, stages run by hand."""

import json
import os
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from ilt.cli import cli
from ilt.io.manifest import fingerprint_file
from tests.capture_helpers import SMALL_RIG


def invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def run(*args):
    result = invoke(*args)
    assert result.exit_code == 0, result.output
    return result


def error_line(result) -> str:
    """The one line an ilt error prints (exit 1)."""
    assert result.exit_code == 1, result.output
    lines = [line for line in result.stderr.splitlines() if line.startswith("ilt: error:")]
    assert len(lines) == 1, result.stderr
    return lines[0]


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    root = tmp_path_factory.mktemp("integrity")
    (root / "small.toml").write_text(SMALL_RIG)
    run("run", root / "small.toml", "-w", root / "ws")
    return root


@pytest.fixture
def ws(built, tmp_path):
    """A copy of the built workspace (times kept, as a backup would keep them)."""
    shutil.copytree(built / "ws", tmp_path / "ws")
    return tmp_path / "ws"


def states(ws, *extra) -> dict:
    return {s["stage"]: s for s in json.loads(run("status", "-w", ws, "--json", *extra).stdout)}


def test_edited_rig_toml_is_moved_aside_never_overwritten(ws, built):
    edited = SMALL_RIG + "\n[merge]\nmargin = 0.05\n"
    (ws / "rig.toml").write_text(edited)
    result = run("run", built / "small.toml", "-w", ws)
    assert (ws / "rig.toml.previous-1").read_text() == edited
    assert (ws / "rig.toml").read_text() == SMALL_RIG
    assert "[merge] margin" in result.stderr and "rig.toml.previous-1" in result.stderr
    assert "edited since 'ilt run' copied it" in result.stderr
    # the copy `ilt run` made is its own: replaced without a copy aside
    other = ws.parent / "other.toml"
    other.write_text(SMALL_RIG.replace("bounces = 4", "bounces = 3"))
    run("run", other, "-w", ws)
    assert not (ws / "rig.toml.previous-2").exists()


def test_corrupted_hdr_frame_is_found_and_not_built_on(ws):
    frame = ws / "hdr" / "beam-00005.exr"
    stat = frame.stat()
    data = bytearray(frame.read_bytes())
    data[-100] ^= 0xFF
    frame.write_bytes(bytes(data))
    os.utime(frame, ns=(stat.st_atime_ns, stat.st_mtime_ns))  # size and time as before: only hashing sees it
    merge = states(ws, "--verify")["merge"]
    assert merge["state"] == "changed" and "beam-00005.exr" in merge["reason"], merge
    assert states(ws, "--verify")["centroids"]["state"] == "done"
    frame.touch()  # as any write leaves it: `ilt run` and `ilt status` re-hash it
    assert states(ws)["merge"]["state"] == "changed"
    line = error_line(invoke("run", "-w", ws))
    assert "hdr" in line and "beam-00005.exr" in line and "ilt run" in line, line


def test_swapped_dng_is_refused_by_merge(ws, tmp_path):
    frame = ws / "capture" / "beam-00005" / "frame-01.dng"
    original = frame.read_bytes()
    shutil.copyfile(ws / "capture" / "beam-00004" / "frame-01.dng", frame)  # another beam's frame
    line = error_line(invoke("merge", ws / "capture", "-o", tmp_path / "hdr"))
    assert "beam-00005/frame-01.dng" in line and "capture.jsonl" in line, line
    assert not (tmp_path / "hdr").exists()
    # another exposure of the same beam, in a capture without a log: its EXIF gives it away
    frame.write_bytes(original)
    (ws / "capture" / "capture.jsonl").unlink()
    shutil.copyfile(ws / "capture" / "beam-00005" / "frame-00.dng", frame)
    line = error_line(invoke("merge", ws / "capture", "-o", tmp_path / "hdr"))
    assert "beam-00005/frame-01.dng" in line and "1/125 s" in line and "1/15 s" in line, line


@pytest.mark.parametrize("damage", ["altered", "wrong-shape"])
def test_damaged_operator_cache_is_rebuilt_with_a_warning(ws, tmp_path, damage):
    cache = tmp_path / "cache"
    photo = ws / "photos" / "flashlight.exr"

    def decompose(out):
        result = run("decompose", photo, "-w", ws, "-o", tmp_path / out, "--cache-dir", cache, "--samples-only")
        summary = json.loads((tmp_path / out / "flashlight" / "summary.json").read_text())
        return result, np.load(tmp_path / out / "flashlight" / "bounces.npy"), summary["operators"]["cached"]

    _, reference, cached = decompose("first")
    assert not cached
    factors = next(cache.glob("operators/*/factors.npy"))
    good = np.load(factors)
    np.save(factors, good * 1.02 if damage == "altered" else good[:-1])
    result, bounces, cached = decompose("second")
    assert "ignoring the operator cache" in result.stderr and not cached, result.stderr
    np.testing.assert_array_equal(bounces, reference)
    _, bounces, cached = decompose("third")  # the rebuilt entry is good again
    assert cached
    np.testing.assert_array_equal(bounces, reference)


def test_paths_from_a_config_or_manifest_stay_inside(tmp_path, ws):
    config = tmp_path / "out.toml"
    config.write_text(SMALL_RIG.replace("[ptu]", '[output]\ndirectory = "../x"\n\n[ptu]'))
    line = error_line(invoke("capture", config, "-w", tmp_path / "w"))
    assert "[output] directory '../x'" in line and "-o" in line, line
    assert not (tmp_path / "x").exists()
    manifest = ws / "capture" / "manifest.json"
    data = json.loads(manifest.read_text())
    data["beams"][1] = "../outside"
    manifest.write_text(json.dumps(data))
    line = error_line(invoke("merge", ws / "capture", "-o", tmp_path / "hdr"))
    assert "'../outside'" in line and "manifest.json" in line, line


def test_multi_photo_decompose_completes_what_a_failure_left(ws, tmp_path, monkeypatch):
    import ilt.decompose.stage

    photos = [ws / "photos" / "flashlight.exr", tmp_path / "second.exr"]
    shutil.copyfile(photos[0], photos[1])
    out = tmp_path / "out"
    args = ["decompose", *photos, "-w", ws, "-o", out, "--no-cache", "--samples-only"]
    write = ilt.decompose.stage.write_decomposition

    def disk_full_on_the_second(directory, photo, *rest):
        if photo.name == "second":
            raise OSError(28, "No space left on device")
        return write(directory, photo, *rest)

    monkeypatch.setattr(ilt.decompose.stage, "write_decomposition", disk_full_on_the_second)
    assert invoke(*args).exit_code == 1
    assert (out / "flashlight" / "manifest.json").exists() and not (out / "second").exists()
    first = {p.name: fingerprint_file(p) for p in (out / "flashlight").iterdir() if p.is_file()}
    monkeypatch.setattr(ilt.decompose.stage, "write_decomposition", write)
    result = run(*args)  # no --force: the complete one is kept, the missing one made
    assert "already decomposed" in result.stderr
    assert (out / "second" / "manifest.json").exists()
    assert {p.name: fingerprint_file(p) for p in (out / "flashlight").iterdir() if p.is_file()} == first
    line = error_line(invoke(*args, "--bounces", "3"))  # other options: an existing result needs --force
    assert "--force" in line and "flashlight" in line, line


def test_stages_run_by_hand_are_done(ws):
    run("merge", "-w", ws, "--force")
    run("centroids", "-w", ws, "--force", "--workers", "1")
    s = states(ws)
    assert s["merge"]["state"] == "done" and s["centroids"]["state"] == "done", s
    ran = [x["stage"] for x in json.loads(run("run", "-w", ws, "--json").stdout) if x["ran"]]
    assert "merge" not in ran and "centroids" not in ran, ran
    assert all(x["state"] == "done" for x in states(ws).values())
