"""The ``series`` back-end against scenes whose transport is known exactly.

Every scene here is built from its light transport: ``A`` (non-negative, zero
diagonal) and ``T1`` (positive diagonal), ``T = (I - A)^-1 T1``. Then ``C1 = I - A``,
``t1 = diag(T1)`` and the bounces of a photo L are ``Ln = (I - A) A^(n-1) L``.
"""

import json
import logging
import math

import numpy as np
import pytest
from click.testing import CliRunner

from ilt.cli import cli
from ilt.decompose.stage import load_operator
from ilt.evaluate.bench import bench_case
from ilt.evaluate.errors import relative_errors
from ilt.sim import make_scene
from ilt.transport import solvers
from ilt.transport.operators import bounce_images, cancellation_operator
from ilt.transport.scan import TransportError
from ilt.transport.series import iterations_needed, series_operator
from ilt.transport.solvers import build_operator, choose_solver


def local_scene(m, rho=0.5, seed=0):
    """Points on a line, each lighting its 2 neighbours on either side (weights 1 and
    0.5, jittered), rows scaled to sum to rho, so rho(A) = rho exactly (Perron).
    T is dense but its entries decay geometrically with |i - j|."""
    rng = np.random.default_rng(seed)
    A = np.zeros((m, m))
    for step, weight in ((1, 1.0), (2, 0.5)):
        i = np.arange(m - step)
        A[i, i + step] = weight * rng.uniform(0.5, 1.0, m - step)
        A[i + step, i] = weight * rng.uniform(0.5, 1.0, m - step)
    A *= rho / A.sum(axis=1, keepdims=True)
    t1 = rng.uniform(0.5, 2.0, m)
    return A, t1, np.linalg.solve(np.eye(m) - A, np.diag(t1))


def sparse_scene(kind, m=64, seed=0):
    """T exactly sparse: 'pairs' of points lighting only each other (T has 2 x 2
    blocks), or 'senders': odd points light their even neighbours and receive nothing,
    so A^2 = 0 and T = (I + A) T1 is banded and connected."""
    rng = np.random.default_rng(seed)
    A = np.zeros((m, m))
    if kind == "pairs":
        i = np.arange(0, m, 2)
        A[i, i + 1] = rng.uniform(0.2, 0.6, m // 2)
        A[i + 1, i] = rng.uniform(0.2, 0.6, m // 2)
    else:
        for i in range(0, m, 2):
            A[i, [j for j in (i - 1, i + 1) if 0 <= j < m]] = rng.uniform(0.2, 0.4)
        assert not (A @ A).any()
    t1 = rng.uniform(0.5, 2.0, m)
    return A, t1, np.linalg.solve(np.eye(m) - A, np.diag(t1))


def true_bounces(A, L, n):
    """``Ln = (I - A) A^(n-1) L`` for n = 1..N, stacked (N, m, k)."""
    out = [L - A @ L]
    for _ in range(n - 1):
        out.append(A @ out[-1])
    return np.stack(out)


def photos(m, k=3, seed=1):
    return np.random.default_rng(seed).uniform(size=(m, k))


def test_local_scene_matches_truth_and_dense():
    A, t1, T = local_scene(256)
    op, reason = build_operator(T, "series", noise=1e-14)
    assert op.solver == "series" and reason == "asked for series"
    # entries of T fall below 1e-14 about 32 points away: a band of ~65, as many colours
    assert 25 <= op.colours <= 40 and op.S.nnz < 70 * 256
    # rho(A) = 0.5 gives rho(I - D^-1 T) ~ 0.8 (module docstring), measured to 1e-3
    assert 0.75 < op.jacobi_radius < 0.85
    # solves stop at a relative residual of 1e-12 (cond(T) ~ 3), dropped entries are
    # <= 1e-14: T1, C1 and every bounce to 1e-11
    assert np.max(np.abs(op.t1 - t1) / t1) < 1e-11
    np.testing.assert_allclose(op.apply(np.eye(256)), np.eye(256) - A, rtol=0, atol=1e-11)
    L = photos(256)
    series = bounce_images(op, L, 6).bounces
    assert relative_errors(series, true_bounces(A, L, 6)).max() < 1e-11
    dense = bounce_images(cancellation_operator(T), L, 6).bounces
    assert relative_errors(series, dense).max() < 1e-11
    assert op.matvecs > 0 and 1 / op.rcond == pytest.approx(1 / cancellation_operator(T).rcond, rel=0.2)
    assert op.probe_error < 1e-11  # the pattern check: T^-1 stays inside S's pattern


@pytest.mark.parametrize("floor", [1e-10, 1e-8, 1e-6])
def test_error_follows_the_noise_floor(floor):
    """Dropping entries below the floor costs an error of the floor's order in T1 and C1
    (measured: 1.6-2 times the floor)."""
    A, t1, T = local_scene(256)
    op, _ = build_operator(T, "series", noise=floor)
    t1_error = np.max(np.abs(op.t1 - t1) / t1)
    assert floor / 10 < t1_error < 5 * floor
    assert t1_error / 3 < op.probe_error < 3 * t1_error  # the estimate follows the error
    assert np.abs(op.apply(np.eye(256)) - (np.eye(256) - A)).max() < 5 * floor


@pytest.mark.parametrize("kind", ["pairs", "senders"])
def test_exactly_sparse_t_is_exact(kind):
    A, t1, T = sparse_scene(kind)
    op = series_operator(T)
    # T keeps its non-zeros, so probing is exact with 2 colours; only the solves' 1e-12 remain
    assert op.colours == 2 and op.threshold == 0 and op.probe_error < 1e-11
    assert np.max(np.abs(op.t1 - t1) / t1) < 1e-11
    np.testing.assert_allclose(op.apply(np.eye(64)), np.eye(64) - A, rtol=0, atol=1e-11)
    L = photos(64)
    assert relative_errors(bounce_images(op, L, 4).bounces, true_bounces(A, L, 4)).max() < 1e-11


def test_divergent_series_is_refused_with_its_spectral_radius():
    # T = I + c (shift up + shift down): I - D^-1 T has eigenvalues -2c cos(k pi / (m + 1))
    m, c = 64, 0.52
    T = np.eye(m) + c * (np.eye(m, k=1) + np.eye(m, k=-1))
    assert 2 * c * math.cos(math.pi / (m + 1)) == pytest.approx(1.0388, abs=1e-4)
    with pytest.raises(TransportError, match=r"series diverges: spectral radius of I - D\^-1 T is 1\.04 >= 1"):
        build_operator(T, "series")


def test_slow_series_warns_with_the_iterations_it_needs(caplog):
    # one pair of points with albedo 0.995 facing each other: T's 2 x 2 block is
    # [[1, a], [a, 1]] t1 / (1 - a^2), so I - D^-1 T has eigenvalues +-a
    A, t1, _ = sparse_scene("pairs")
    A[0, 1] = A[1, 0] = 0.995
    T = np.linalg.solve(np.eye(64) - A, np.diag(t1))
    with caplog.at_level(logging.INFO, logger="ilt.transport.series"):
        op = series_operator(T)
    assert op.jacobi_radius == pytest.approx(0.995, abs=1e-3)  # ARPACK's tolerance
    predicted = iterations_needed(op.jacobi_radius)
    assert predicted == pytest.approx(math.log(1e-12) / math.log(0.995), rel=0.2)  # 5513
    assert "spectral radius of I - D^-1 T is 0.99" in caplog.text and f"about {predicted} iterations" in caplog.text
    # still right: cond(T) ~ 1 / (1 - a) = 200 amplifies the 1e-12 residual
    assert np.max(np.abs(op.t1 - t1) / t1) < 1e-9
    np.testing.assert_allclose(op.apply(np.eye(64)), np.eye(64) - A, rtol=0, atol=1e-9)


def test_dense_scene_is_refused_with_its_colour_count():
    T, _ = make_scene("m", beams=64).isf()  # every point exchanges light with every other
    with pytest.raises(TransportError, match="probing T1 needs at least 64 colours, more than m / 4 = 16"):
        build_operator(T, "series")


def test_auto_picks_series_for_a_large_sparse_t_only():
    A, t1, T = local_scene(2048, rho=0.1)
    name, reason = choose_solver(T, 1e-14)
    assert name == "series"
    assert "noise floor 1e-14" in reason and "18 colours" in reason and "spectral radius is 0.11" in reason
    op, why = build_operator(T, "auto", 1e-14)
    assert op.solver == "series" and why == reason
    probe = np.random.default_rng(3).uniform(size=(2048, 2))
    np.testing.assert_allclose(op.apply(probe), probe - A @ probe, rtol=0, atol=1e-11)
    assert np.max(np.abs(op.t1 - t1) / t1) < 1e-11
    # without a floor T is dense (its entries decay to underflow ~350 points away)
    assert choose_solver(T, None)[0] == "dense"
    # rho(A) = 0.2: 42 entries per column, 22 colours, ~20 iterations: 0.041 of dense's
    # flops, 0.82 of its time with sparse flops 20x slower: not a clear win
    assert choose_solver(local_scene(2048, rho=0.2)[2], 1e-14)[0] == "dense"


def test_auto_keeps_dense_for_the_m_scene(monkeypatch):
    T, _ = make_scene("m", beams=128).isf()
    monkeypatch.setattr(solvers, "SERIES_MIN_M", 64)  # consider series at this size
    assert choose_solver(T, None) == ("dense", "m = 128, one connected group, noise unknown")


def test_load_operator_keeps_the_reason_auto_gave():
    A, _, T = sparse_scene("pairs")
    op, diagnostics = load_operator(T, None, "auto")
    assert op.solver == "blocks" and "32 independent groups" in diagnostics["solver_reason"]
    op, diagnostics = load_operator(T, None, "series")
    assert diagnostics["solver"] == "series" and diagnostics["solver_reason"] == "asked for series"
    assert diagnostics["spectral_radius_A"] == pytest.approx(np.sqrt(np.max(A[::2, 1::2].diagonal()
                                                                         * A[1::2, ::2].diagonal())), rel=1e-3)
    assert np.isfinite(diagnostics["condition_estimate"])


def test_decompose_cli_with_series(tmp_path):
    A, _, T = sparse_scene("senders")
    isf = tmp_path / "isf"
    isf.mkdir()
    np.save(isf / "T.npy", T)
    L = photos(64, k=1)[:, 0]
    np.save(tmp_path / "photo.npy", L)
    result = CliRunner().invoke(cli, ["decompose", "--isf", str(isf), str(tmp_path / "photo.npy"), "-o",
                                      str(tmp_path / "out"), "--no-cache", "--solver", "series", "--bounces", "3",
                                      "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)[0]
    assert summary["operators"]["solver"] == "series" and summary["operators"]["series"]["colours"] == 2
    bounces = np.load(tmp_path / "out" / "photo" / "bounces.npy")
    # A^2 = 0: one interreflection, then nothing
    assert relative_errors(bounces[:2], true_bounces(A, L[:, None], 2)[..., 0]).max() < 1e-11
    assert np.abs(bounces[2]).max() < 1e-11 * np.abs(L).max()
    # a dense T: one line naming the colour count, nothing written
    np.save(isf / "T.npy", make_scene("m", beams=64).isf()[0])
    result = CliRunner().invoke(cli, ["decompose", "--isf", str(isf), str(tmp_path / "photo.npy"), "-o",
                                      str(tmp_path / "dense"), "--no-cache", "--solver", "series"])
    assert result.exit_code == 1 and "64 colours" in result.output
    assert not (tmp_path / "dense").exists()


def test_bench_records_a_refusal():
    rows = bench_case("m", 48, solvers=("dense", "series"), batch=2, n_bounces=2, repeats=1)
    assert [r.solver for r in rows] == ["scipy", "dense", "series"]
    assert rows[1].refused is None and rows[1].bounce_error < 1e-12
    assert "colours" in rows[2].refused and rows[2].seconds is None


def test_a_t_whose_inverse_leaves_its_pattern_warns_to_compare_with_dense(caplog):
    """T = I - 0.2 K (K: the two nearest neighbours each side) is no Lambertian ISF: its
    inverse sum (0.2 K)^n is positive off the diagonal and fills every band, so probing
    with T's own pattern reads T1 wrong; the warning says so and what to compare with."""
    m = 128
    K = sum(np.diag(np.ones(m - k), k) + np.diag(np.ones(m - k), -k) for k in (1, 2))
    with caplog.at_level(logging.WARNING, logger="ilt.transport.series"):
        op = series_operator(np.eye(m) - 0.2 * K)
    assert op.probe_error > 0.1
    exact = 1 / np.diag(np.linalg.inv(np.eye(m) - 0.2 * K))
    assert np.max(np.abs(op.t1 - exact) / exact) > 0.01       # and it is wrong
    assert "T1 from probing may be off" in caplog.text and "compare with --solver dense" in caplog.text
