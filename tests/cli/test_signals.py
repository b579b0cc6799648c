"""Signals and dead processes (issue 14): `ilt` run as a real subprocess, with a pool of
two workers, is sent SIGTERM or SIGKILL mid-stage, run from a directory holding a folder
named `ilt`, or loses a worker. Every process of a run is found through its session
(the run is started in a new one; the fork server, resource tracker and workers inherit
it), by a scan of /proc."""

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from ilt.cli import cli

ILT = Path(sys.executable).parent / "ilt"  # the console script, as a user runs it


def session(sid: int) -> dict[int, str]:
    """pid -> command line of every live (not zombie) process of session ``sid``."""
    out = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            fields = (d / "stat").read_text().rsplit(")", 1)[1].split()
            if int(fields[3]) == sid and fields[0] != "Z":
                out[int(d.name)] = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except (OSError, IndexError):
            pass  # ended meanwhile
    return out


def start(*args, cwd=None, env=None) -> subprocess.Popen:
    return subprocess.Popen([str(ILT), "-q", *map(str, args)], cwd=cwd, env=env, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for_workers(proc: subprocess.Popen, n: int = 2) -> dict[int, str]:
    """Wait until ``n`` pool workers run (children of the fork server); the session then."""
    deadline = time.monotonic() + 15
    while proc.poll() is None:
        procs = session(proc.pid)
        servers = [p for p, cmd in procs.items() if "forkserver" in cmd]
        workers = [p for p in procs if p != proc.pid and _ppid(p) in servers]
        if len(workers) >= n:
            return procs
        assert time.monotonic() < deadline, f"no {n} workers came: {procs}"
        time.sleep(0.005)
    raise AssertionError(f"ilt ended first: {proc.returncode} {proc.stderr.read()}")


def _ppid(pid: int) -> int:
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError):
        return -1


def stop_session(sid: int) -> None:
    """Whatever a failed test leaves of the run it started."""
    for pid in session(sid):
        os.kill(pid, signal.SIGKILL)


@pytest.fixture(scope="module")
def hdr(tmp_path_factory):
    """200 simulated beam frames and their spots found in this process (the reference)."""
    root = tmp_path_factory.mktemp("signals")
    simulate = ["simulate", "m", "--frames", "--beams", "200", "--px-per-beam", "16", "--fine", "2", "-o", root / "sim"]
    for args in (simulate,
                 ["centroids", root / "sim" / "hdr", "-o", root / "spots", "--workers", "1"]):
        result = CliRunner().invoke(cli, [str(a) for a in args])
        assert result.exit_code == 0, result.output
    return root / "sim" / "hdr", (root / "spots" / "spots.csv").read_text()


@pytest.mark.parametrize("signum, code", [(signal.SIGTERM, 143), (signal.SIGHUP, 129)])
def test_a_signal_mid_stage_ends_ilt_with_one_line_and_leaves_nothing(hdr, tmp_path, signum, code):
    proc = start("centroids", hdr[0], "-o", tmp_path / "spots", "--workers", 2)
    try:
        running = wait_for_workers(proc)
        assert len(running) >= 5, running  # ilt, resource tracker, fork server, 2 workers
        proc.send_signal(signum)  # the main process only, as `kill PID` does
        out, err = proc.communicate(timeout=15)
        assert proc.returncode == code, err
        assert err.splitlines() == [f"ilt: terminated ({signal.Signals(signum).name}); nothing partial is left behind"]
        assert session(proc.pid) == {}, "processes of ilt outlived it"
        assert sorted(p.name for p in tmp_path.iterdir()) == [], "a partial output is left"
    finally:
        stop_session(proc.pid)


def test_sigterm_in_run_removes_the_frames_scratch(hdr, tmp_path):
    """`ilt run` keeps decoded frames in WORKSPACE/.frames-scratch while centroids runs:
    SIGTERM then removes it, the stage's temporary directory, and every process."""
    from tests.capture_helpers import SMALL_RIG

    config = tmp_path / "small.toml"
    config.write_text(SMALL_RIG.replace("[centroids]\nworkers = 1", "[centroids]\nworkers = 2"))
    ws = tmp_path / "ws"
    proc = start("run", config, "-w", ws)
    try:
        deadline = time.monotonic() + 20
        while not (ws / ".frames-scratch").exists():
            assert proc.poll() is None, proc.stderr.read()
            assert time.monotonic() < deadline, "centroids never started"
            time.sleep(0.002)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=15)
        assert proc.returncode == 143, err
        assert err.splitlines() == ["ilt: terminated (SIGTERM); nothing partial is left behind"]
        assert session(proc.pid) == {}
        left = sorted(p.name for p in ws.iterdir())
        assert ".frames-scratch" not in left and not [n for n in left if ".tmp-" in n], left
        assert not (ws / "spots").exists()
    finally:
        stop_session(proc.pid)


def test_sigkill_of_the_main_process_takes_its_workers_along(hdr, tmp_path):
    proc = start("centroids", hdr[0], "-o", tmp_path / "spots", "--workers", 2)
    try:
        running = wait_for_workers(proc)
        os.kill(proc.pid, signal.SIGKILL)  # the main process only: the OOM killer's way
        proc.wait()
        killed = time.monotonic()
        while session(proc.pid) and time.monotonic() - killed < 3:
            time.sleep(0.01)
        assert session(proc.pid) == {}, f"left after 3 s, of {sorted(running)}"
    finally:
        stop_session(proc.pid)


def test_a_folder_named_ilt_in_the_current_directory_is_not_imported(hdr, tmp_path):
    """Workers import the installed package, not ./ilt (here a package without __version__)."""
    (tmp_path / "ilt").mkdir()
    (tmp_path / "ilt" / "__init__.py").write_text("# not ilt\n")
    proc = start("centroids", hdr[0], "-o", tmp_path / "spots", "--workers", 2, cwd=tmp_path)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert (tmp_path / "spots" / "spots.csv").read_text() == hdr[1]


def test_a_worker_that_dies_is_one_line_naming_its_beams(hdr, tmp_path):
    """A worker that exits in the middle of a chunk (beam 40's): exit 1, one line naming
    the chunk's beams and how the worker ended. The crash is installed by a
    sitecustomize module, which every Python process of the run (the fork server too) imports."""
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(
        "import os\n"
        "import ilt.spots.stage\n"
        "real = ilt.spots.stage._centroid_chunk\n"
        "def _centroid_chunk(beams, *args, **kwargs):\n"
        "    if 40 in beams:\n"
        "        os._exit(3)\n"
        "    return real(beams, *args, **kwargs)\n"
        "ilt.spots.stage._centroid_chunk = _centroid_chunk\n")
    env = {**os.environ, "PYTHONPATH": str(hook)}
    proc = start("centroids", hdr[0], "-o", tmp_path / "spots", "--workers", 2, env=env)
    try:
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 1, err
        lines = err.splitlines()
        assert len(lines) == 1, err
        found = re.fullmatch(r"ilt: error: beams (\d+)-(\d+): the worker process running them exited with "
                             r"status 3 \(its error, if it printed one, is above\)", lines[0])
        assert found and int(found[1]) <= 40 <= int(found[2]), lines[0]
        assert session(proc.pid) == {}
        assert not (tmp_path / "spots").exists()
    finally:
        stop_session(proc.pid)
