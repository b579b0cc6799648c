"""Solver back-ends against the dense reference and the simulator's truth."""

import numpy as np
import pytest
import scipy.linalg

from ilt.evaluate.bench import scene_batch
from ilt.evaluate.errors import relative_errors
from ilt.sim import make_scene
from ilt.transport.operators import bounce_images, cancellation_operator
from ilt.transport.scan import TransportError
from ilt.transport.solvers import (
    build_operator,
    choose_solver,
    estimate_noise,
    independent_groups,
)


def independent_objects(k, beams=64):
    """k separate M scenes (different albedo): T is block diagonal, then shuffled."""
    scenes = [make_scene("m", beams=beams, albedo=0.5 + 0.1 * i) for i in range(k)]
    T = scipy.linalg.block_diag(*[s.isf()[0] for s in scenes])
    A = scipy.linalg.block_diag(*[s.A for s in scenes])
    order = np.random.default_rng(k).permutation(T.shape[0])
    return T[np.ix_(order, order)], A[np.ix_(order, order)]


def test_blocks_find_groups_and_match_dense():
    T, A = independent_objects(3)
    groups = independent_groups(T)
    assert sorted(len(g) for g in groups) == [64, 64, 64]
    L = np.linalg.solve(np.eye(T.shape[0]) - A, np.random.default_rng(0).uniform(size=(T.shape[0], 3)))
    dense = bounce_images(cancellation_operator(T), L, 6).bounces
    op, reason = build_operator(T, "auto")
    assert op.solver == "blocks" and "3 independent groups" in reason
    blocks = bounce_images(op, L, 6).bounces
    np.testing.assert_allclose(blocks, dense, atol=1e-12 * np.abs(dense).max())
    np.testing.assert_allclose(op.apply(np.eye(T.shape[0])), np.eye(T.shape[0]) - A, atol=1e-12)


def test_mixed_precision_error_and_refinement():
    scene = make_scene("box", beams=768)
    T, scale = scene.isf()
    photos, truth = scene_batch(scene, 4, 8)
    op, _ = build_operator(T, "mixed")
    assert op.solver == "mixed"
    # solves are refined to float64: T_n^-1 b to rounding
    b = photos[:, 0]
    np.testing.assert_allclose(T @ (op.solve(b) / op.column_norms), b, atol=1e-14 * np.abs(b).max())
    # T1 comes from float32 factors: ~1e-7 relative, so are the bounces
    assert np.max(np.abs(op.t1 - scene.direct / scale) / op.t1) < 1e-6
    assert relative_errors(bounce_images(op, photos, 8).bounces, truth).max() < 1e-6


def test_mixed_falls_back_to_dense_on_ill_conditioned_t():
    rng = np.random.default_rng(1)
    U, _ = np.linalg.qr(rng.normal(size=(300, 300)))
    V, _ = np.linalg.qr(rng.normal(size=(300, 300)))
    T = U @ np.diag(np.logspace(0, -9, 300)) @ V.T  # condition 1e9: float32 factors cannot converge
    op, reason = build_operator(T, "mixed")
    assert op.solver == "dense" and "fell back to dense" in reason


def test_auto_reasons():
    scene = make_scene("box", beams=192)
    T, _ = scene.isf()
    assert choose_solver(T, None)[0] == "dense"
    assert "one connected group" in choose_solver(T, None)[1]
    with pytest.raises(TransportError, match="unknown solver 'fast'"):
        build_operator(T, "fast")


@pytest.mark.parametrize("sigma", [1e-4, 1e-3, 1e-2])
def test_noise_floor_from_negative_entries(sigma):
    T, _ = independent_objects(2)  # half of T is exactly zero: unlit samples
    noisy = T + np.random.default_rng(2).normal(scale=sigma, size=T.shape)
    assert estimate_noise(noisy) == pytest.approx(sigma, rel=0.1)
    assert estimate_noise(T) is None


def test_the_group_search_stops_at_a_group_of_more_than_half_and_decides_the_same():
    """choose_solver only asks whether every group holds at most m / 2 points: the search
    stops at the first larger one (a dense T after one step) and decides as a full one."""
    big, _ = independent_objects(1, beams=96)
    small, _ = independent_objects(2, beams=32)
    T = scipy.linalg.block_diag(big, small)                          # groups 96, 32, 32 of 160
    order = np.random.default_rng(5).permutation(T.shape[0])
    T = T[np.ix_(order, order)]
    full = independent_groups(T)
    assert sorted(len(g) for g in full) == [32, 32, 96]
    early = independent_groups(T, stop_above=T.shape[0] // 2)
    assert len(early[0]) > T.shape[0] // 2 and set(early[0]) <= set(full[0])
    assert choose_solver(T, None)[0] != "blocks"
    dense = np.random.default_rng(0).uniform(0.1, 1.0, (300, 300)) + np.eye(300)
    assert [len(g) for g in independent_groups(dense, stop_above=150)] == [300]
    assert choose_solver(dense, None)[0] != "blocks"
    T3, _ = independent_objects(3)                                    # every group <= m / 2: searched in full
    name, reason = choose_solver(T3, None)
    assert name == "blocks" and "3 independent groups" in reason


def test_one_scan_checks_t_measures_the_noise_and_feeds_the_build(monkeypatch):
    """load_operator reads T once for its checks, column norms and noise (scan_isf),
    whichever solver it builds: the IsfMatrix it makes is what the solver choice, the
    build and the diagnostics take. estimate_noise from the scan equals the blockwise
    definition."""
    from ilt.decompose.stage import load_operator
    from ilt.transport import scan

    T, _ = independent_objects(2)
    noisy = T + np.random.default_rng(2).normal(scale=1e-3, size=T.shape)
    Tn = noisy / np.linalg.norm(noisy, axis=0)
    assert estimate_noise(noisy) == pytest.approx(np.sqrt(np.mean(Tn[Tn < 0] ** 2)), rel=1e-12)
    measured = scan.scan_isf(noisy)
    assert scan.scan_isf(measured) is measured
    np.testing.assert_allclose(measured.norms, np.linalg.norm(noisy, axis=0), rtol=1e-14)
    assert measured.negatives == int((noisy < 0).sum())
    passes = []
    real = scan._check_isf  # what every pass over T starts with
    monkeypatch.setattr(scan, "_check_isf", lambda T: passes.append(np.shape(T)) or real(T))
    ref = cancellation_operator(noisy)
    for solver in ("auto", "dense", "mixed", "blocks", "compressed"):
        passes.clear()
        op, diag = load_operator(noisy, None, solver=solver, points=np.random.default_rng(0).uniform(size=(128, 2)))
        assert passes.count(noisy.shape) == 1, solver   # blocks' groups are scanned as they are copied
        assert diag["noise"] == pytest.approx(estimate_noise(noisy))
        np.testing.assert_allclose(op.t1_unit, ref.t1_unit, rtol=1e-4 if solver == "compressed" else 1e-6)


def test_scan_refuses_what_the_row_by_row_checks_refused():
    from ilt.transport.scan import scan_isf

    T = np.eye(600) + 0.01
    for value, where in ((np.inf, (400, 7)), (np.nan, (3, 599))):
        bad = T.copy()
        bad[where] = value
        bad[where[0] + 100 if where[0] < 500 else 0, 1] = np.nan  # a later one is not named
        with pytest.raises(TransportError, match=f"pixel row {where[0]}, beam column {where[1]}"):
            scan_isf(bad)
    huge = T * 1e200  # squares overflow, entries finite: still an ISF as far as the checks go
    scan_isf(huge)
    dup = T.copy()
    dup[:, 9] = dup[:, 4]
    with pytest.raises(TransportError, match="columns 4 and 9 are identical"):
        scan_isf(dup)
    zero = T.copy()
    zero[:, 5] = 0
    with pytest.raises(TransportError, match="column 5 .* all zero"):
        scan_isf(zero)


def test_mixed_refinement_runs_on_one_blas():
    """MixedOperator's residual products go through scipy's BLAS, the library of its
    float32 solves (numpy's and scipy's OpenBLAS pools fought; docs/numerics.md), and
    give numpy's product."""
    from ilt.transport.solvers import _product

    rng = np.random.default_rng(0)
    T = rng.random((300, 300)) + 300 * np.eye(300)
    x, X = rng.random(300), rng.random((300, 3))
    np.testing.assert_allclose(_product(T, x), T @ x, rtol=1e-13)
    np.testing.assert_allclose(_product(T, X), T @ X, rtol=1e-13)
    np.testing.assert_allclose(_product(np.asfortranarray(T), X), T @ X, rtol=1e-13)  # not C order: numpy's
    op, _ = build_operator(T, "mixed")
    assert op.solver == "mixed"
    # T1 comes from the float32 factors (about 1e-7 relative); the solves are refined to float64
    np.testing.assert_allclose(op.apply(X), cancellation_operator(T).apply(X), rtol=1e-5)
    np.testing.assert_allclose(op.solve(X), np.linalg.solve(T / np.linalg.norm(T, axis=0), X), rtol=1e-12)
