"""The command line end to end: outputs against the simulator's truth, errors, exit codes."""

import json
import subprocess
import sys

import numpy as np
import pytest
from click.testing import CliRunner

from ilt.cli import cli
from ilt.evaluate.errors import relative_errors
from ilt.io.exr import read_exr, write_exr


def run(*args, ok=True):
    result = CliRunner().invoke(cli, [str(a) for a in args])
    if ok:
        assert result.exit_code == 0, result.output + repr(result.exception)
    return result


@pytest.fixture(scope="module")
def isf_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "isf"
    result = run("simulate", "m", "--beams", 64, "-o", out)
    assert result.stdout.strip() == str(out)
    return out


def test_simulate_writes_an_isf_directory(isf_dir):
    T = np.load(isf_dir / "T.npy")
    assert T.shape == (64, 64) and T.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(T, axis=0), 1, rtol=1e-14)
    manifest = json.loads((isf_dir / "manifest.json").read_text())
    assert manifest["stage"] == "simulate" and manifest["layout"] == [1, 64]
    assert "T.npy" in manifest["outputs"] and manifest["outputs"]["T.npy"].startswith("sha256:")
    header = (isf_dir / "samples.csv").read_text().splitlines()[0]
    assert header == "beam,x,y"
    for kind in ("flashlight", "room", "projector"):
        assert (isf_dir / "photos" / f"{kind}.exr").exists()
        assert (isf_dir / "truth" / "photos" / f"{kind}-bounces.npy").exists()


def test_decompose_npy_matches_truth_and_reuses_operators(isf_dir, tmp_path):
    cache = tmp_path / "cache"
    out = tmp_path / "out"
    photo = isf_dir / "photos" / "room.npy"
    result = run("decompose", "--isf", isf_dir, photo, "-o", out, "--cache-dir", cache, "--json")
    summary = json.loads(result.stdout)[0]
    assert summary["operators"]["cached"] is False
    bounces = np.load(out / "room" / "bounces.npy")
    truth = np.load(isf_dir / "truth" / "photos" / "room-bounces.npy")
    assert bounces.shape == (8, 64)
    assert relative_errors(bounces, truth).max() < 1e-10
    residual = np.load(out / "room" / "residual.npy")
    L = np.load(photo)
    assert np.linalg.norm(L - bounces.sum(0) - residual) <= 1e-12 * np.linalg.norm(L)
    for name in ["bounce-1", "bounce-8", "indirect", "residual", "photo"]:
        image, attrs = read_exr(out / "room" / "samples" / f"{name}.exr")
        assert image.shape == (1, 64, 1)
    np.testing.assert_allclose(read_exr(out / "room" / "samples" / "bounce-2.exr")[0][0, :, 0], bounces[1], rtol=1e-6)
    assert (out / "room" / "preview.png").stat().st_size > 0
    # the second photo reuses the factorised operators
    result = run("decompose", "--isf", isf_dir, isf_dir / "photos" / "flashlight.npy", "-o", out,
                 "--cache-dir", cache, "--json")
    assert json.loads(result.stdout)[0]["operators"]["cached"] is True


def test_decompose_reads_t_through_a_read_only_memory_map(isf_dir):
    """`ilt decompose` memory-maps T.npy: nothing holds it twice, pages are read as a
    solver needs them (and the kernel may drop them again), nothing can write to it."""
    from ilt.isf.directory import load_isf

    mapped, loaded = load_isf(isf_dir, mmap=True).T, load_isf(isf_dir).T
    assert isinstance(mapped, np.memmap) and not mapped.flags.writeable
    assert not isinstance(loaded, np.memmap) and np.array_equal(mapped, loaded)


def test_decompose_exr_frame(isf_dir, tmp_path):
    out = tmp_path / "out"
    run("decompose", "--isf", isf_dir, isf_dir / "photos" / "projector.exr", "-o", out, "--no-cache")
    bounces = np.load(out / "projector" / "bounces.npy")
    truth = np.load(isf_dir / "truth" / "photos" / "projector-bounces.npy")
    # EXR stores float32: the photo carries ~6e-8 relative rounding, amplified mildly by C1.
    assert relative_errors(bounces[:4], truth[:4]).max() < 1e-5
    frame, _ = read_exr(out / "projector" / "samples" / "bounce-1.frame.exr")
    photo, _ = read_exr(isf_dir / "photos" / "projector.exr")
    assert frame.shape == photo.shape


def test_tol_stops_early_and_reports(isf_dir, tmp_path):
    result = run("decompose", "--isf", isf_dir, isf_dir / "photos" / "room.npy", "-o", tmp_path / "o",
                 "--bounces", 40, "--tol", 1e-4, "--no-cache", "--json")
    dec = json.loads(result.stdout)[0]["decomposition"]
    assert dec["stopped_early"] and dec["bounces"] < 40
    assert dec["relative_norms"][-1] < 1e-4


def _bad_isf(tmp_path, T):
    d = tmp_path / "badisf"
    d.mkdir()
    np.save(d / "T.npy", T)
    return d


@pytest.mark.parametrize(
    "case, message",
    [
        ("nonsquare", "square"),
        ("nan", "non-finite"),
        ("zero column", "column 2 (beam 2) is all zero"),
        ("identical", "columns 1 and 3 are identical"),
        ("length", "does not match the ISF's m = 64"),
        ("frame", "frame is"),
        ("missing", "no such file"),
    ],
)
def test_bad_input_fails_cleanly(isf_dir, tmp_path, case, message):
    isf, photo = isf_dir, isf_dir / "photos" / "room.npy"
    good = np.load(isf_dir / "T.npy")
    if case == "nonsquare":
        isf = _bad_isf(tmp_path, good[:, :-1])
    elif case == "nan":
        T = good.copy()
        T[3, 5] = np.nan
        isf = _bad_isf(tmp_path, T)
    elif case == "zero column":
        T = good.copy()
        T[:, 2] = 0
        isf = _bad_isf(tmp_path, T)
    elif case == "identical":
        T = good.copy()
        T[:, 3] = T[:, 1]
        isf = _bad_isf(tmp_path, T)
    elif case == "length":
        photo = tmp_path / "short.npy"
        np.save(photo, np.ones(63))
    elif case == "frame":
        photo = tmp_path / "small.exr"
        write_exr(photo, np.ones((4, 5), np.float32))
    elif case == "missing":
        photo = tmp_path / "nothere.exr"
    if case not in ("length", "frame", "missing"):
        photo = tmp_path / "ok.npy"
        np.save(photo, np.ones(good.shape[0]))
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "ilt", "decompose", "--isf", str(isf), str(photo), "-o", str(out), "--no-cache"],
        capture_output=True, text=True,
    )
    assert proc.returncode == 1, proc.stderr
    lines = proc.stderr.strip().splitlines()
    errors = [line for line in lines if line.startswith("ilt: error:")]
    assert errors == lines[-1:], proc.stderr  # one line, the last, says why
    assert message in errors[0]
    named = str(photo) if case in ("length", "frame", "missing") else str(isf)
    assert named in errors[0]
    assert not out.exists()
    assert proc.stdout == ""


def test_usage_error_exit_code():
    proc = subprocess.run([sys.executable, "-m", "ilt", "decompose"], capture_output=True, text=True)
    assert proc.returncode == 2
    assert "Usage" in proc.stderr


def test_existing_output_is_kept_without_force(isf_dir, tmp_path):
    """The same photo, ISF and options again: skipped; other options: refused without --force."""
    out = tmp_path / "out"
    photo = isf_dir / "photos" / "room.npy"
    run("decompose", "--isf", isf_dir, photo, "-o", out, "--no-cache")
    before = (out / "room" / "bounces.npy").read_bytes()
    run("decompose", "--isf", isf_dir, photo, "-o", out, "--no-cache")
    assert (out / "room" / "bounces.npy").read_bytes() == before
    result = run("decompose", "--isf", isf_dir, photo, "-o", out, "--no-cache", "--bounces", 3, ok=False)
    assert result.exit_code == 1 and "--force" in result.output
    assert (out / "room" / "bounces.npy").read_bytes() == before
    run("decompose", "--isf", isf_dir, photo, "-o", out, "--no-cache", "--force", "--bounces", 3)
    assert np.load(out / "room" / "bounces.npy").shape == (3, 64)


def test_demo_quick(tmp_path):
    result = run("demo", "-o", tmp_path / "demo", "--quick", "--json")
    assert "WARNING" not in result.stderr, [line for line in result.stderr.splitlines() if "WARNING" in line]
    results = json.loads(result.stdout)
    assert [r["scene"] for r in results] == ["m", "box"]
    for r in results:
        for row in r["errors"]["exact"]:
            assert row["mean"] <= 1e-26 and row["max"] <= 1e-24
        assert (tmp_path / "demo" / r["scene"] / "exact" / "fig5.png").exists()
        assert len(r["previews"]) == 3
        assert (tmp_path / "demo" / r["scene"] / "report" / "index.html").exists()  # the simulated rig's
    assert (tmp_path / "demo" / "report" / "index.html").exists()


def test_bench_writes_figures_with_errors_against_truth(tmp_path):
    result = run("bench", "--sizes", "48,108", "--noise", "0,1e-4", "--repeats", 1, "--batch", 4,
                 "-o", tmp_path / "b", "--json")
    rows = json.loads(result.stdout)
    assert {(r["m"], r["noise"], r["solver"]) for r in rows} == {
        (m, n, s) for m in (48, 108) for n in (0.0, 1e-4) for s in ("scipy", "dense", "mixed", "blocks", "series",
                                                               "compressed")
    } | {(m, 1e-4, "regularised") for m in (48, 108)}
    for r in rows:
        if r["solver"] == "series":  # the box's points all exchange light: T is dense, series refuses
            assert "colours" in r["refused"] and r["seconds"] is None
            continue
        assert r["refused"] is None
        # pooled^2 is the energy-weighted mean of the per-bounce errors^2: never above the worst
        assert 0 <= r["pooled_error"] <= r["bounce_error"] * (1 + 1e-12)
        if r["noise"] == 0:
            bound = 1e-5 if r["solver"] == "mixed" else 1e-12
            assert r["bounce_error"] < bound and r["t1_error"] < bound and r["closure_error"] < 1e-14
        else:  # 1e-4 noise: errors follow it, amplified a little
            assert 1e-6 < r["bounce_error"] < 1e-2 and 0.1 < r["amplification"] < 100
        if r["solver"] == "scipy":
            assert r["ratio_to_scipy"] == 1.0
    written = json.loads((tmp_path / "b" / "bench.json").read_text())
    assert written["rows"] == rows
    assert (tmp_path / "b" / "bench.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # bias against variance of regularisation: at the smallest size, for the noisy case
    bv = written["bias_variance"]
    assert {(r["m"], r["noise"]) for r in bv} == {(48, 1e-4)} and bv[0]["width"] == 0.0
    assert sum(r["chosen"] for r in bv) == 8 == bv[0]["draws"]
    assert all(len(r["bias"]) == len(r["spread"]) == 8 for r in bv)
    assert "bias" in result.stderr and "spread" in result.stderr


def test_decompose_solver_noise_and_regularisation(isf_dir, tmp_path):
    photo = isf_dir / "photos" / "room.npy"
    truth = np.load(isf_dir / "truth" / "photos" / "room-bounces.npy")
    result = run("decompose", "--isf", isf_dir, photo, "-o", tmp_path / "a", "--no-cache", "--json")
    ops = json.loads(result.stdout)[0]["operators"]
    assert ops["solver"] == "dense" and "one connected group" in ops["solver_reason"]
    assert ops["noise"] is None and "give --noise" in ops["noise_source"]
    result = run("decompose", "--isf", isf_dir, photo, "-o", tmp_path / "b", "--no-cache", "--solver", "mixed",
                 "--json")
    assert json.loads(result.stdout)[0]["operators"]["solver"] == "mixed"
    assert relative_errors(np.load(tmp_path / "b" / "room" / "bounces.npy"), truth).max() < 1e-5
    # a clean T has no negative entries: regularising needs the noise level
    result = run("decompose", "--isf", isf_dir, photo, "-o", tmp_path / "c", "--no-cache", "--regularise", ok=False)
    assert result.exit_code == 1 and "give --noise" in result.output
    assert not (tmp_path / "c").exists()
    # a noisy T: the noise is measured, the filter width reported, and the bounces are closer to the truth
    noisy = tmp_path / "noisy"
    noisy.mkdir()
    for name in ("samples.csv", "manifest.json"):
        (noisy / name).write_bytes((isf_dir / name).read_bytes())
    T = np.load(isf_dir / "T.npy")
    np.save(noisy / "T.npy", T + 1e-2 * np.random.default_rng(0).normal(size=T.shape))
    # (by default only with the noise known, not estimated from T's negative entries)
    errors, ops = {}, {}
    for flags in (["--no-regularise"], ["--regularise"], [], ["--noise", "1e-2"]):
        out = tmp_path / ("_".join(flags) or "default")
        result = run("decompose", "--isf", noisy, photo, "-o", out, "--no-cache", "--bounces", 4, *flags, "--json")
        ops[tuple(flags)] = json.loads(result.stdout)[0]["operators"]
        errors[tuple(flags)] = relative_errors(np.load(out / "room" / "bounces.npy"), truth[:4]).max()
    assert ops[()]["noise"] == pytest.approx(1e-2, rel=0.3) and "negative entries" in ops[()]["noise_source"]
    assert ops[()]["regularisation_width"] == 0 and "only estimated" in ops[()]["regularisation"]
    assert ops[("--no-regularise",)]["regularisation_width"] == 0 and errors[()] == errors[("--no-regularise",)]
    assert ops[("--regularise",)]["regularisation_width"] > 0 and ops[("--noise", "1e-2")]["regularisation_width"] > 0
    assert max(errors[("--regularise",)], errors[("--noise", "1e-2")]) < errors[()]


def test_progress_in_a_log_is_a_line_every_tenth(caplog):
    """Under `ilt run` or in a pipe (stderr no terminal) the per-beam stages log their
    progress a tenth at a time, with the beams done and an ETA."""
    import logging

    from ilt.cli.options import progress_bar

    with caplog.at_level(logging.INFO), progress_bar(95, "merge") as update:
        for _ in range(95):
            update(1)
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("merge:")]
    assert [line.split(",")[0] for line in lines] == [f"merge: {n}/95 beams" for n in range(9, 91, 9)] + \
        ["merge: 95/95 beams"]
    assert all("ETA" in line for line in lines)
