"""SIGKILL `ilt run` at 10 moments of a simulated scan (issue 7): no stage that `ilt status`
calls done is incomplete, no completed beam is lost, and the final re-run gives results
identical, bit for bit, to an uninterrupted run.

Five kills fall in the capture, each a fixed delay after a file appears (the log, a frame,
a beam's manifest, the capture's manifest); one in each later stage, a seeded random
fraction of that stage's uninterrupted run time after `ilt run` logs that it started. A
stage's time varies from run to run (a shared machine, warm caches), so a kill that comes
after its stage is done is tried again, the stage's directory removed (as a user would, to
make it run again) and the delay halved: every stage is killed inside itself, whatever
the speed of the machine. The runs go on in one workspace, each resuming what the last
one left.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from ilt.capture.loop import verify_log
from ilt.cli import cli
from ilt.io.frames import read_frame
from ilt.io.manifest import fingerprint_file, read_manifest
from tests.capture_helpers import SMALL_RIG

#: the kills: (a path appearing in the workspace, glob; seconds after it) during the capture,
#: then (a stage starting, as logged; the fraction of its uninterrupted run time after it)
CAPTURE_KILLS = (
    ("capture/capture.jsonl", 0.15),
    ("capture/beam-00001/frame-02.dng", 0.1),
    ("capture/beam-00003/manifest.json", 0.0),
    ("capture/beam-00006/dark.dng", 0.2),
    ("capture/manifest.json", 0.0),
)
STAGE_KILLS = ("merge", "centroids", "build-isf", "photos", "decompose")
#: results compared with the uninterrupted run's, byte for byte
RESULTS = ("isf/T.npy", "isf/scales.npy", "isf/samples.csv", "spots/spots.csv",
           "decompose/flashlight/bounces.npy", "decompose/flashlight/residual.npy")


def _ilt(*args, env):
    return subprocess.Popen([sys.executable, "-m", "ilt", *map(str, args)], env=env, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _run_and_kill(ws: Path, config: Path, env, *, pattern: str = "", stage: str = "", delay: float) -> bool:
    """Start `ilt run` and SIGKILL its process group ``delay`` s after a new path matching
    ``pattern`` appears in ``ws``, or after it logs that ``stage`` is running. Returns True
    when it was killed, False when it finished first."""
    before = set(ws.glob(pattern)) if pattern else set()
    log: list[str] = []
    proc = _ilt("run", config, "-w", ws, env=env)
    reader = threading.Thread(target=lambda: log.extend(proc.stderr), daemon=True)
    reader.start()

    def triggered():
        if pattern:
            return any(p not in before for p in ws.glob(pattern))
        return any(f"INFO: {stage}: running" in line for line in list(log))

    deadline = time.monotonic() + 60
    while proc.poll() is None and not triggered():
        assert time.monotonic() < deadline, f"{pattern or stage} never came"
        time.sleep(0.002)
    time.sleep(delay)
    killed = proc.poll() is None
    if killed:
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    reader.join()
    assert killed or proc.returncode == 0, "".join(log)
    return killed


def _states(ws: Path) -> dict[str, dict]:
    result = CliRunner().invoke(cli, ["status", "-w", str(ws), "--json"])
    assert result.exit_code == 0, result.output
    return {s["stage"]: s for s in json.loads(result.stdout)}


def _kill_inside_stage(ws: Path, config: Path, env, stage: str, delay: float, tries: int = 8) -> int:
    """SIGKILL `ilt run` while ``stage`` runs; returns how many runs it took. A run whose kill
    came after ``stage`` was done (or that finished) is followed by removing the stage's
    directory, so that the next run makes it again, and a run with half the delay."""
    for attempt in range(1, tries + 1):
        killed = _run_and_kill(ws, config, env, stage=stage, delay=delay)
        _check_done_stages_are_complete(ws)
        state = _states(ws)[stage]
        if killed and state["state"] != "done":
            return attempt
        shutil.rmtree(state["directory"])
        delay /= 2
    raise AssertionError(f"no kill of {tries} came while {stage} ran")


def _complete_beams(capture: Path) -> dict[str, dict[str, str]]:
    """Every complete beam (its manifest exists) with the fingerprints of its files."""
    return {b.name: {f.name: fingerprint_file(f) for f in b.iterdir()}
            for b in capture.glob("beam-*") if (b / "manifest.json").exists()}


def _check_done_stages_are_complete(ws: Path):
    for state in _states(ws).values():
        if state["state"] != "done":
            continue
        directory = Path(state["directory"])
        for name, digest in read_manifest(directory)["outputs"].items():
            assert (directory / name).is_file(), f"{state['stage']} done but {name} missing"
            assert fingerprint_file(directory / name) == digest, f"{state['stage']} done but {name} changed"
        if state["stage"] == "capture":
            beams = read_manifest(directory)["beams"]
            assert all((directory / b / "manifest.json").exists() for b in beams)


@pytest.fixture
def env(tmp_path):
    return {**os.environ, "ILT_CACHE_DIR": str(tmp_path / "cache"), "OMP_NUM_THREADS": "1"}


def test_sigkill_at_ten_moments_loses_nothing_and_resumes_identically(tmp_path, env):
    config = tmp_path / "small.toml"
    # a settle of 0.05 s a beam (a real rig's is 0.5 s or more): the capture's kills, a fixed
    # delay after a file appears, land inside it however fast the emulated unit answers
    config.write_text(SMALL_RIG.replace("settle = 0.0", "settle = 0.05"))
    reference = tmp_path / "reference"
    proc = _ilt("run", config, "-w", reference, "--json", env=env)
    out, err = proc.communicate()
    assert proc.returncode == 0, err
    seconds = {s["stage"]: s["seconds"] for s in json.loads(out)}

    ws = tmp_path / "ws"
    fractions = np.random.default_rng(2005).uniform(0.05, 0.7, len(STAGE_KILLS))
    kills = [{"pattern": p, "delay": d} for p, d in CAPTURE_KILLS] + \
        [{"stage": s, "delay": f * seconds[s]} for s, f in zip(STAGE_KILLS, fractions)]
    kept: dict[str, dict[str, str]] = {}
    finished = []
    for kill in kills:
        if "pattern" in kill:
            if not _run_and_kill(ws, config, env, **kill):
                finished.append(kill)
            _check_done_stages_are_complete(ws)
        else:
            _kill_inside_stage(ws, config, env, **kill)
        beams = _complete_beams(ws / "capture")
        for name, files in kept.items():
            assert beams.get(name) == files, f"completed {name} lost or changed by the kill {kill}"
        kept = beams
        assert verify_log(ws / "capture") == []
    assert len(finished) <= 1, f"these runs finished before their kill: {finished}"

    assert _ilt("run", config, "-w", ws, env=env).wait() == 0
    assert [s["state"] for s in _states(ws).values()] == ["done"] * 6
    assert _complete_beams(ws / "capture").items() >= kept.items()
    for name in RESULTS:
        assert (ws / name).read_bytes() == (reference / name).read_bytes(), name
    for frame in sorted((reference / "hdr").glob("beam-*.exr")) + [reference / "photos" / "flashlight.exr"]:
        np.testing.assert_array_equal(read_frame(ws / frame.relative_to(reference)), read_frame(frame))
