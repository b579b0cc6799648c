"""The capture loop end to end on the emulated rig: layout, log, faults, resume, errors."""

import os
import signal
import subprocess
import sys
import time
from dataclasses import replace

import pytest
from click.testing import CliRunner

from ilt.capture.emulator import LaserEmulator, PTUEmulator
from ilt.capture.errors import RigError
from ilt.capture.log import read_log
from ilt.capture.loop import capture, verify_log
from ilt.cli import cli
from ilt.io.manifest import LOG_NAME
from tests import ROOT
from tests.capture_helpers import frame_hashes, pointing_of, small_config, toml_text


def run_on(emu, cfg, out, resume=False, laser_emu=None, added=()):
    cfg = replace(cfg, ptu=replace(cfg.ptu, port=emu.port))
    if laser_emu is not None:
        cfg = replace(cfg, laser=replace(cfg.laser, control="serial", port=laser_emu.port, on="L1", off="L0"))
    return capture(cfg, out, resume=resume, pointing=pointing_of(emu, laser_emu), added=added)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted run over a pty: the answer every interrupted run must reach."""
    out = tmp_path_factory.mktemp("ref") / "capture"
    with PTUEmulator("pty", speed=20000) as emu:
        summary = run_on(emu, small_config(), out)
        assert emu.aux is False
    return out, summary


def test_capture_layout_is_what_merge_reads(reference):
    from ilt.hdr.bracket import list_beams, read_beam
    from ilt.io.raw import read_green

    out, summary = reference
    assert summary["beams"] == 8 and summary["frames"] == 8 * 4
    beams = list_beams(out)
    assert [b.name for b in beams] == [f"beam-{j:05d}" for j in range(8)]
    bracket = read_beam(beams[3])
    assert [f.exposure_time for f in bracket.frames] == ["1/15", "1/250", "1/4000"]
    assert bracket.dark.file == "dark.dng"
    green, info = read_green(bracket.path(bracket.frames[2]))  # a real DNG rawpy reads
    assert info.exposure.time_text == "1/4000" and green.max() > 1000  # the spot is lit
    dark, _ = read_green(bracket.path(bracket.dark))
    assert dark.max() < 50  # laser off: noise only
    assert verify_log(out) == []
    frames = [r for r in read_log(out / LOG_NAME) if r["event"] == "frame"]
    assert len(frames) == 32 and all(r["exif"]["exposure_time"] == r["requested"]["shutter"] for r in frames)
    assert all(r["laser"] is (r["kind"] == "bracket") for r in frames)
    assert all(r["readback"]["pan"] == r["requested"]["pan"] for r in frames)


def test_socket_loopback_gives_the_same_frames(reference, tmp_path):
    with PTUEmulator("socket", speed=20000) as emu:
        run_on(emu, small_config(), tmp_path / "c")
    assert frame_hashes(tmp_path / "c") == frame_hashes(reference[0])


FAULTS = {
    # kind: (PTU faults, camera faults, serial laser?) -- each breaks beam 2
    "timeout": (["timeout:OA0@4"], [], False),   # laser-off after beam 2's bracket never answers
    "device-error": (["error:OA1@3"], [], False),  # beam 2's laser-on refused
    "camera-unplug": ([], ["unplug@10"], False),   # USB camera gone mid-bracket of beam 2
    "ptu-unplug": (["unplug:A@3"], [], True),      # PTU cable pulled at beam 2's move
}


@pytest.mark.parametrize("fault", sorted(FAULTS))
def test_fault_then_resume_equals_uninterrupted(fault, reference, tmp_path):
    ptu_faults, cam_faults, serial_laser = FAULTS[fault]
    cfg = small_config(camera={"faults": cam_faults})
    out = tmp_path / "c"
    laser = LaserEmulator("pty").start() if serial_laser else None
    try:
        with PTUEmulator("pty", faults=ptu_faults, speed=20000) as emu:
            with pytest.raises(RigError):
                run_on(emu, cfg, out, laser_emu=laser)
            assert (laser or emu).aux is False, "the laser must end off"
        problems = verify_log(out)
        assert problems == []
        records = read_log(out / LOG_NAME)
        assert records[-1]["event"] == "abort" and records[-1]["laser_off"] is True
        done = [r["beam"] for r in records if r["event"] == "beam_done"]
        assert done == [0, 1]
        with PTUEmulator("pty", speed=20000) as emu:
            summary = run_on(emu, small_config(), out, resume=True, laser_emu=laser)
            assert emu.aux is False and (laser or emu).aux is False
    finally:
        if laser:
            laser.stop()
    records = read_log(out / LOG_NAME)
    resumed = records[[r["event"] for r in records].index("resume"):]
    shot = [r["beam"] for r in resumed if r["event"] == "beam_done"]
    assert shot == list(range(2, 8)) and summary["shot"] == 6
    aside = [r for r in resumed if r["event"] == "set_aside"]
    assert [r["beam"] for r in aside] == ([2] if (out / ".incomplete").exists() else [])
    assert frame_hashes(out) == frame_hashes(reference[0])
    assert verify_log(out) == []


def test_sigkill_mid_bracket_then_resume(reference, tmp_path):
    cfg_path = tmp_path / "rig.toml"
    # beam 2's shots are 9-12 (3 exposures and a dark): the camera hangs at its third, so the
    # kill lands mid-bracket however fast the rest runs (it would wait the camera's 30 s timeout)
    cfg_path.write_text(toml_text(camera={"faults": ["hang@11"]}))
    out = tmp_path / "c"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "ilt", "-q", "capture", str(cfg_path), "-o", str(out)],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            log = out / LOG_NAME
            if log.exists() and sum('"beam": 2, "file"' in line for line in log.read_text().splitlines()) >= 2:
                break
            time.sleep(0.01)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    assert verify_log(out) == []
    assert not (out / "beam-00002" / "manifest.json").exists()
    with PTUEmulator("pty", speed=20000) as emu:
        run_on(emu, small_config(), out, resume=True)
        assert [c for c in emu.received if c.startswith("OA")][0] == "OA0"  # laser off first thing
        assert emu.aux is False
    records = read_log(out / LOG_NAME)
    resumed = records[[r["event"] for r in records].index("resume"):]
    assert [r["beam"] for r in resumed if r["event"] == "beam_done"] == list(range(2, 8))
    assert [r["beam"] for r in resumed if r["event"] == "set_aside"] == [2]
    assert frame_hashes(out) == frame_hashes(reference[0])
    assert verify_log(out) == []


def _cli(args):
    return CliRunner().invoke(cli, args)


def test_cli_errors_are_one_line_and_lose_nothing(tmp_path, reference):
    cfg = tmp_path / "rig.toml"
    cases = {
        "out-of-limit": (toml_text(plan={"pan": [-5.0, 90.0]}), "beam 7: pan 3500 steps is outside the unit's limits"),
        "unknown-port": (toml_text(ptu={"port": "/dev/ilt-no-such-port"}), "port /dev/ilt-no-such-port does not exist"),
        "wrong-model": (toml_text(camera={"model": "Canon EOS 20D"}), "connected model is 'ilt SimSensor'"),
        "disk-full": (toml_text(camera={"faults": ["enospc@6"]}), "no space left on device"),
    }
    for name, (text, words) in cases.items():
        cfg.write_text(text)
        out = tmp_path / name
        result = _cli(["capture", str(cfg), "-o", str(out)])
        lines = result.output.strip().splitlines()
        assert result.exit_code == 1, (name, result.output)
        assert lines[-1].startswith("ilt: error:") and words in lines[-1], (name, lines[-1])
        if out.exists() and (out / LOG_NAME).exists():
            assert verify_log(out) == []
    # disk full after beam 0 (4 frames) and 1 frame of beam 1: beam 0 stays complete
    assert (tmp_path / "disk-full" / "beam-00000" / "manifest.json").exists()


def test_cli_port_held_and_unwritable_output(tmp_path):
    cfg = tmp_path / "rig.toml"
    with PTUEmulator("pty") as emu:
        import serial

        holder = serial.Serial(emu.port, exclusive=True)
        try:
            cfg.write_text(toml_text(ptu={"port": emu.port}))
            result = _cli(["capture", str(cfg), "-o", str(tmp_path / "held")])
        finally:
            holder.close()
    assert result.exit_code == 1 and "is held by another process" in result.output
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    cfg.write_text(toml_text())
    result = _cli(["capture", str(cfg), "-o", str(blocker / "c")])
    assert result.exit_code == 1, result.output
    assert "cannot write the capture directory (Not a directory)" in result.output


def test_cli_refuses_to_overwrite_and_resume_of_complete_capture_shoots_nothing(reference, tmp_path):
    out, _ = reference
    cfg = tmp_path / "rig.toml"
    cfg.write_text(toml_text())
    before = frame_hashes(out)
    result = _cli(["capture", str(cfg), "-o", str(out)])
    assert result.exit_code == 1 and "use --resume" in result.output
    result = _cli(["capture", str(cfg), "-o", str(out), "--resume", "--json"])
    assert result.exit_code == 0, result.output
    assert '"shot": 0' in result.output and frame_hashes(out) == before


def test_a_dark_frame_every_four_beams_is_linked_into_the_beams_between(reference, tmp_path):
    """[dark] every = 4 on 8 beams: beams 0 and 4 shoot a dark frame, the others hold a
    hard link to it, logged as frames with shared_from; the bracket frames are the
    reference's byte for byte, verify_log finds nothing wrong, and merge takes it."""
    from ilt.capture.log import read_log
    from ilt.hdr.stages import merge_capture

    ref, _ = reference
    out = tmp_path / "capture"
    with PTUEmulator("pty", speed=20000) as emu:
        summary = run_on(emu, small_config(dark={"every": 4}), out)
    assert summary["beams"] == 8
    darks = [out / f"beam-{j:05d}" / "dark.dng" for j in range(8)]
    inodes = [os.stat(d).st_ino for d in darks]
    assert inodes[0] == inodes[1] == inodes[2] == inodes[3] != inodes[4] == inodes[7]
    shared = [r for r in read_log(out / "capture.jsonl") if r["event"] == "frame" and "shared_from" in r]
    assert [r["beam"] for r in shared] == [1, 2, 3, 5, 6, 7]
    assert shared[0]["shared_from"] == "beam-00000/dark.dng"
    mine, theirs = frame_hashes(out), frame_hashes(ref)
    assert {k: v for k, v in mine.items() if "dark" not in k} == {k: v for k, v in theirs.items() if "dark" not in k}
    assert verify_log(out) == []
    merge_capture(out, tmp_path / "hdr")
    assert len(list((tmp_path / "hdr").glob("beam-*.exr"))) == 8


def test_a_plan_extended_by_a_refine_pass_appends_and_keeps_every_frame(reference, tmp_path):
    """capture(resume=True, added=...) shoots only the added beams, logged as 'extend';
    the frames taken stay byte for byte; the manifest names the passes; the first plan
    alone is refused on the extended scan (it no longer describes it)."""
    import shutil

    import numpy as np

    from ilt.capture.config import ConfigError
    from ilt.io.manifest import read_manifest

    out = tmp_path / "capture"
    shutil.copytree(reference[0], out)
    before = frame_hashes(out)
    added = [np.array([[-4.0, 0.0], [1.3, 0.0]])]
    with PTUEmulator("pty", speed=20000) as emu:
        summary = run_on(emu, small_config(), out, resume=True, added=added)
    assert summary["shot"] == 2 and summary["beams"] == 10
    after = frame_hashes(out)
    assert {k: after[k] for k in before} == before and len(after) == len(before) + 2 * 5  # 3 frames, dark, manifest
    assert [r["event"] for r in read_log(out / LOG_NAME)].count("extend") == 1
    manifest = read_manifest(out)
    assert manifest["plan"]["passes"] == [8, 10] and manifest["plan"]["targets"][8:] == added[0].tolist()
    assert verify_log(out) == []
    with PTUEmulator("pty", speed=20000) as emu, pytest.raises(ConfigError, match="differ from the capture's"):
        run_on(emu, small_config(), out, resume=True)
