"""Nothing a user made is ever lost (ilt/io/staged.py staged_directory): a stage replaces
only its own earlier output or an empty directory, never a workspace, a raw capture,
the current directory or a directory holding someone else's file, even with --force;
what it writes follows the umask; temporaries of killed runs are removed by the next."""

import os
import stat
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from ilt.cli import cli
from ilt.io.manifest import fingerprint_file


def invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def hashes(root):
    """relative path -> sha256 of every file below ``root``, hidden ones too."""
    return {str(p.relative_to(root)): fingerprint_file(p) for p in sorted(root.rglob("*")) if p.is_file()}


def refused(result, *words):
    """Exit 1 with one line ``ilt: error: ...`` holding ``words``, no raw OS error."""
    assert result.exit_code == 1, result.output
    lines = result.stderr.strip().splitlines()
    assert lines[-1].startswith("ilt: error: ") and "Errno" not in lines[-1], result.stderr
    for w in words:
        assert w in lines[-1], lines[-1]


def simulate(out, *more):
    result = invoke("simulate", "m", "--beams", 8, "-o", out, *more)
    assert result.exit_code == 0, result.output
    return out


def dead_pid():
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_report_into_the_workspace_is_refused(workspace):  # noqa: F811
    before = hashes(workspace)
    refused(invoke("report", "-w", workspace, "-o", workspace), str(workspace), "is a workspace")
    assert hashes(workspace) == before


def test_report_into_a_directory_with_a_users_file_is_refused(workspace, tmp_path):  # noqa: F811
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("my notes")
    before = hashes(tmp_path)
    refused(invoke("report", "-w", workspace, "-o", out), str(out), "ilt did not write: notes.txt")
    assert hashes(tmp_path) == before


def test_report_into_the_current_directory_is_refused(workspace, tmp_path, monkeypatch):  # noqa: F811
    (tmp_path / "notes.txt").write_text("my notes")
    monkeypatch.chdir(tmp_path)
    before = hashes(tmp_path)
    refused(invoke("report", "-w", workspace, "-o", "."), "current directory")
    assert hashes(tmp_path) == before


def test_report_replaces_its_own_report_but_not_another_stages_output(workspace, tmp_path):  # noqa: F811
    out = tmp_path / "report"
    assert invoke("report", "-w", workspace, "-o", out).exit_code == 0
    assert invoke("report", "-w", workspace, "-o", out).exit_code == 0  # its own: replaced
    isf = simulate(tmp_path / "isf")
    before = hashes(isf)
    refused(invoke("report", "-w", workspace, "-o", isf), str(isf), "output of 'simulate', not 'report'")
    assert hashes(isf) == before


def test_merge_onto_its_capture_is_refused_even_with_force(workspace):  # noqa: F811
    capture = workspace / "capture"
    before = hashes(capture)
    refused(invoke("merge", capture, "-o", capture, "--force"), str(capture), "raw capture (capture.jsonl)")
    assert hashes(capture) == before


def test_a_stage_output_holding_a_users_file_is_kept_even_with_force(tmp_path):
    isf = simulate(tmp_path / "isf")
    (isf / "truth" / "notes.txt").write_text("my notes")
    before = hashes(isf)
    refused(invoke("simulate", "m", "--beams", 16, "-o", isf, "--force"), "ilt did not write: truth/notes.txt")
    assert hashes(isf) == before


def test_force_replaces_a_stages_own_output(tmp_path):
    isf = simulate(tmp_path / "isf")
    refused(invoke("simulate", "m", "--beams", 16, "-o", isf), "--force")
    simulate(isf, "--beams", 16, "--force")
    assert np.load(isf / "T.npy").shape == (16, 16)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["isf"]  # no temporary left beside it


def test_demo_into_a_foreign_directory_is_refused(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("my notes")
    before = hashes(out)
    refused(invoke("demo", "-o", out, "--quick"), str(out), "not an earlier 'ilt demo' output")
    assert hashes(out) == before


def test_demo_claims_an_empty_directory_and_its_own_again(tmp_path):
    from ilt.io.manifest import read_manifest
    from ilt.workspace.demo import claim_output

    out = tmp_path / "demo"
    out.mkdir()
    claim_output(out, quick=True)
    (out / "m").mkdir()  # what a run leaves there
    claim_output(out, quick=False)
    assert read_manifest(out)["stage"] == "demo" and read_manifest(out)["parameters"] == {"quick": False}


@pytest.mark.parametrize("umask", [0o022, 0o027], ids=["umask-022", "umask-027"])
def test_stage_directories_and_files_follow_the_umask(tmp_path, umask):
    old = os.umask(umask)
    try:
        isf = simulate(tmp_path / "isf")
    finally:
        os.umask(old)
    modes = {str(p.relative_to(isf)): stat.S_IMODE(p.stat().st_mode) for p in [isf, *isf.rglob("*")]}
    want = {name: (0o777 if (isf / name).is_dir() else 0o666) & ~umask for name in modes}
    assert modes == want
    assert {"T.npy", "manifest.json", "photos/room.exr", "photos"} <= set(modes)


def test_a_killed_runs_temporaries_are_removed_by_the_next_merge_a_live_ones_kept(workspace):  # noqa: F811
    dead, live = dead_pid(), os.getpid()
    stale = [workspace / f".hdr.tmp-{dead}-x", workspace / f".hdr.old-{dead}-y"]
    for d in stale:
        (d / "hdr").mkdir(parents=True)
        (d / "hdr" / "beam-00000.exr").write_bytes(b"half written")
    stale_file = workspace / f".rig.tmp-{dead}-z.toml"
    stale_file.write_text("half written")
    filling = workspace / f".hdr.tmp-{live}-x"
    filling.mkdir()
    elsewhere = workspace / f".hdr.tmp-{dead}@00000000-x"   # another host's run filling it, on shared storage
    elsewhere.mkdir()
    (filling / "beam-00000.exr").write_bytes(b"being written")
    try:
        assert invoke("merge", "-w", workspace, "--force").exit_code == 0
        assert not any(p.exists() for p in [*stale, stale_file])
        assert (filling / "beam-00000.exr").read_bytes() == b"being written"
        assert elsewhere.is_dir()
    finally:
        (filling / "beam-00000.exr").unlink()
        filling.rmdir()
        elsewhere.rmdir()


def test_an_operator_cache_entry_is_rebuilt_when_unreadable_also_one_without_manifest(tmp_path, monkeypatch):
    """Entries of ilt's own cache are replaced when decompose rebuilds them, also those
    an older ilt wrote without a manifest.json."""
    from ilt.decompose.stage import load_operator

    monkeypatch.setenv("ILT_CACHE_DIR", str(tmp_path))
    T = np.eye(6) + 0.1
    T /= np.linalg.norm(T, axis=0)
    load_operator(T, tmp_path)
    [entry] = (tmp_path / "operators").iterdir()
    (entry / "factors.npy").write_bytes(b"truncated")
    (entry / "manifest.json").unlink()
    op, diagnostics = load_operator(T, tmp_path)
    assert diagnostics["cached"] is False and np.load(entry / "factors.npy").shape == (6, 6)
