"""Numerical stress cases (issue 6): each result is right within a stated bound, or the
run warns with the figure that explains why."""

import numpy as np
import pytest

from ilt.evaluate.bench import scene_batch
from ilt.evaluate.errors import noise_amplification, relative_errors
from ilt.sim import make_scene
from ilt.transport.diagnostics import operator_diagnostics
from ilt.transport.operators import bounce_images, cancellation_operator


def closed_enclosure(m, albedo, seed=0):
    """A transport with every row of K summing to 1 (no light escapes): rho(A) = albedo."""
    rng = np.random.default_rng(seed)
    K = rng.uniform(0, 1, (m, m))
    np.fill_diagonal(K, 0)
    K /= K.sum(axis=1, keepdims=True)
    A = albedo * K
    D = rng.uniform(0.5, 1.0, m)
    return A, np.linalg.solve(np.eye(m) - A, np.diag(D))


@pytest.mark.parametrize("albedo", [0.9, 0.99, 0.999])
def test_albedo_near_one(albedo):
    """Spectral radius of A -> 1: the bounces decay slowly, yet each is exact to
    ~eps * cond(T), and the diagnostics report rho."""
    A, T = closed_enclosure(150, albedo)
    op = cancellation_operator(T)
    d = operator_diagnostics(T, op)
    # within ilt.transport.diagnostics.RHO_TOL (1e-3) of rho; within 1e-2 of 1 it is refined to 1e-8
    assert d["spectral_radius_A"] == pytest.approx(albedo, rel=1e-6 if albedo > 0.99 else 1e-3)
    L1 = np.random.default_rng(1).uniform(size=150)
    L = np.linalg.solve(np.eye(150) - A, L1)
    truth = [L1]
    for _ in range(19):
        truth.append(A @ truth[-1])
    errors = relative_errors(bounce_images(op, L, 20).bounces, np.stack(truth))
    assert errors.max() <= 1e-13 * d["condition_estimate"] * 20


def test_dark_patches():
    """Albedo 1e-3 on some points: their T columns are tiny before normalisation."""
    scene = make_scene("textured", beams=128)
    # every 7th point gets albedo 1e-3: its row of A = P K and its direct light scale with it
    factor = np.ones(128)
    factor[::7] = 1e-3 / scene.albedo[::7]
    A = scene.A * factor[:, None]
    direct = scene.direct * factor
    T = np.linalg.solve(np.eye(128) - A, np.diag(direct))
    op = cancellation_operator(T)
    np.testing.assert_allclose(op.apply(np.eye(128)), np.eye(128) - A, atol=1e-12)
    np.testing.assert_allclose(op.t1, direct, rtol=1e-12)


def test_two_beams_almost_on_one_point_warn_with_condition():
    """Two beams 0.1 px apart see nearly the same column: T is near-singular and the
    diagnostics say so with the condition estimate."""
    scene = make_scene("m", beams=64)
    T, _ = scene.isf()
    T = T.copy()
    T[:, 11] = T[:, 10] + 1e-11 * T[:, 11]
    op = cancellation_operator(T)
    d = operator_diagnostics(T, op)
    assert d["condition_estimate"] > 1e10
    assert any("condition estimate" in w for w in d["warnings"])


def test_missing_beam_folds_into_direct_light():
    """A point with no beam acts like an occluded one (paper Sec. 3.1.2): C1 of the
    reduced T equals the collapsed transport exactly."""
    scene = make_scene("box", beams=192)
    keep = np.setdiff1d(np.arange(scene.m), [5, 77, 150])
    gone = np.setdiff1d(np.arange(scene.m), keep)
    A = scene.A
    Avv, Avh, Ahv, Ahh = A[np.ix_(keep, keep)], A[np.ix_(keep, gone)], A[np.ix_(gone, keep)], A[np.ix_(gone, gone)]
    collapsed = Avv + Avh @ np.linalg.solve(np.eye(len(gone)) - Ahh, Ahv)
    self_loops = np.diag(collapsed)
    A_eff = (collapsed - np.diag(self_loops)) / (1 - self_loops)[:, None]
    T_full = np.linalg.solve(np.eye(scene.m) - A, np.diag(scene.direct))
    op = cancellation_operator(T_full[np.ix_(keep, keep)])
    np.testing.assert_allclose(op.apply(np.eye(len(keep))), np.eye(len(keep)) - A_eff, atol=1e-13)


@pytest.mark.parametrize("bits, bound", [(8, 0.1), (12, 0.01), (16, 5e-4)])
def test_quantised_t(bits, bound):
    """T stored with b bits: bounce errors stay within ~6 times the quantisation noise
    (measured amplification 1-6 per bounce), stated as `bound`."""
    scene = make_scene("m", beams=128)
    T, _ = scene.isf()
    photos, truth = scene_batch(scene, 4, 4)
    levels = 2**bits - 1
    Tq = np.round(T / T.max() * levels) / levels * T.max()
    computed = bounce_images(cancellation_operator(Tq), photos, 4).bounces
    assert relative_errors(computed, truth).max() <= bound
    amplification = noise_amplification(T, Tq, computed, truth)
    assert np.all(amplification < 10)


def test_noise_sweep_amplification_is_bounded():
    """Gaussian noise sigma in T: the error of each bounce grows linearly with sigma
    (amplification independent of sigma within 20%)."""
    scene = make_scene("box", beams=192)
    T, _ = scene.isf()
    photos, truth = scene_batch(scene, 4, 4)
    rng = np.random.default_rng(0)
    noise = rng.normal(size=T.shape)
    amps = []
    for sigma in (1e-6, 1e-5, 1e-4):
        Tn = T + sigma * noise * np.abs(T).max()
        computed = bounce_images(cancellation_operator(Tn), photos, 4).bounces
        amps.append(noise_amplification(T, Tn, computed, truth))
    amps = np.array(amps)
    np.testing.assert_allclose(amps[1:], amps[:1].repeat(2, axis=0), rtol=0.2)
    assert amps.max() < 50


@pytest.mark.parametrize("name, beams", [("m", 128), ("box", 192)])
def test_regularised_t_beats_plain_under_noise(name, beams):
    """The edge-aware filter lowers the worst bounce error for sigma >= 1e-3 without
    raising the direct image's (T1), and leaves a nearly clean T (sigma = 1e-5)
    practically as measured."""
    from ilt.transport.regularise import regularise_isf
    from ilt.transport.scan import scan_isf

    scene = make_scene(name, beams=beams)
    T, scale = scene.isf()
    t1_true = scene.direct / scale
    photos, truth = scene_batch(scene, 4, 4)
    noise = np.random.default_rng(0).normal(size=T.shape)
    for sigma in (1e-5, 1e-3, 1e-2):
        measured = scan_isf(T + sigma * noise)
        Tn = measured.T
        plain_op = cancellation_operator(Tn / measured.norms)   # unit columns, as regularise_isf returns
        plain = relative_errors(bounce_images(plain_op, photos, 4).bounces, truth).max()
        Tr, info = regularise_isf(Tn, scene.layout, sigma)
        assert info.change <= info.noise_norm
        op = cancellation_operator(Tr)
        reg = relative_errors(bounce_images(op, photos, 4).bounces, truth).max()
        t1_plain, t1_reg = (np.max(np.abs(o.t1 - t1_true) / t1_true) for o in (plain_op, op))
        if sigma >= 1e-3:
            assert info.width > 0 and reg < plain, (sigma, reg, plain)
            assert t1_reg <= 1.05 * t1_plain, (sigma, t1_reg, t1_plain)
        else:
            assert reg <= 1.05 * plain


def test_edge_aware_filter_keeps_a_facet_edge():
    """Two facets that exchange light only with each other (no light within a facet: a
    block of zeros either side of the diagonal, like coplanar points): the filter
    removes noise inside each block and leaves the zero blocks at zero, where a
    filter blind to the edge spreads the other facet's light into them."""
    from ilt.transport.regularise import smooth_isf

    rows, cols = 16, 8   # facet A: layout rows 0-7, facet B: rows 8-15
    m = rows * cols
    facet = np.arange(m) // (m // 2)
    yy, xx = np.divmod(np.arange(m), cols)
    smooth = 0.02 * (1 + 0.5 * np.cos(yy[:, None] / 5.0) * np.cos(xx[None, :] / 4.0))
    T = np.where(facet[:, None] != facet[None, :], smooth, 0.0)
    T[np.arange(m), np.arange(m)] = 1.0
    sigma = 2e-3
    noisy = T + sigma * np.random.default_rng(5).normal(size=T.shape)
    out = smooth_isf(noisy, (rows, cols), 1.0, sigma)
    same = (facet[:, None] == facet[None, :]) & ~np.eye(m, dtype=bool)
    assert np.array_equal(np.diag(out), np.diag(noisy))                   # the direct entries untouched
    assert abs(out[same].mean()) < 0.05 * T[~same & ~np.eye(m, dtype=bool)].mean()  # no light leaked in
    assert np.sqrt(np.mean((out - T)[~np.eye(m, dtype=bool)] ** 2)) < 0.6 * sigma  # noise removed
    blind = smooth_isf(noisy, (rows, cols), 1.0, 1.0)  # noise "1": every neighbour counts as alike
    assert blind[same].mean() > 10 * abs(out[same].mean())


def test_edge_aware_filter_on_pairs_is_the_grid_filter_on_the_grid_pairs():
    """The filter along neighbour pairs (an ISF's cells that share an edge) is the layout
    filter when the pairs are the layout's own: the same entries to rounding, on a
    T with a facet edge (the weights) and noise; and a pair list in any order and either
    orientation gives the same."""
    from ilt.transport.regularise import smooth_isf

    rows, cols = 6, 5
    m = rows * cols
    index = np.arange(m).reshape(rows, cols)
    pairs = np.concatenate([np.stack([index[:-1].ravel(), index[1:].ravel()], 1),
                            np.stack([index[:, :-1].ravel(), index[:, 1:].ravel()], 1)])
    rng = np.random.default_rng(2)
    facet = np.arange(m) // (m // 2)
    T = np.where(facet[:, None] != facet[None, :], 0.03, 0.0) + 2e-3 * rng.normal(size=(m, m))
    T[np.arange(m), np.arange(m)] = 1.0
    grid = smooth_isf(T, (rows, cols), 1.0, 2e-3)
    assert np.allclose(smooth_isf(T, None, 1.0, 2e-3, pairs=pairs), grid, rtol=1e-12, atol=1e-13)
    shuffled = pairs[rng.permutation(len(pairs))]
    shuffled[::2] = shuffled[::2, ::-1]
    assert np.allclose(smooth_isf(T, None, 1.0, 2e-3, pairs=shuffled), grid, rtol=1e-12, atol=1e-13)
    assert not np.allclose(grid, T)


def test_bias_against_variance_of_regularisation():
    """Over noise draws, plain inversion is (nearly) unbiased with the noise's spread;
    wider filters trade spread for bias: spread falls and bias rises with the width,
    and error^2 = bias^2 + spread^2 per bounce (the decomposition of the mean squared
    error, with unbiased estimates of both). The width the discrepancy principle picks (the same rule as
    regularise_isf, checked on the same draws) has less error than plain inversion."""
    from ilt.transport.regularise import bias_variance, regularise_isf

    scene = make_scene("box", beams=192)
    T, _ = scene.isf()
    photos, truth = scene_batch(scene, 4, 4)
    sigma = 3e-3
    rows = bias_variance(T, scene.layout, photos, truth, sigma, draws=6, seed=1)
    widths = [r.width for r in rows]
    assert widths[0] == 0.0 and widths == sorted(widths) and sum(r.chosen for r in rows) == 6
    for r in rows:
        error, bias, spread = (np.square(v) for v in (r.error, r.bias, r.spread))
        positive = bias > 0     # a bias estimate below 0 (pure noise) is clipped: error^2 < spread^2 there
        np.testing.assert_allclose(error[positive], (bias + spread)[positive], rtol=1e-9)
        assert (error[~positive] <= spread[~positive] * (1 + 1e-9)).all()
    plain, widest = rows[0], rows[-1]
    assert plain.pooled_bias < 0.2 * plain.pooled_spread          # noise, not bias, limits plain inversion
    assert widest.pooled_spread < 0.6 * plain.pooled_spread       # filtering removes much of the spread (edges stop it)
    assert widest.pooled_bias > 2 * plain.pooled_bias             # at the price of bias
    spreads = [r.pooled_spread for r in rows]
    assert all(b <= a * 1.02 for a, b in zip(spreads, spreads[1:]))
    picked = max(rows, key=lambda r: r.chosen)
    assert picked.width > 0 and picked.pooled_error < plain.pooled_error
    # the same draws through regularise_isf choose the same widths
    rng = np.random.default_rng(1)
    unit = T / np.linalg.norm(T, axis=0)
    chosen = [regularise_isf(unit + sigma * rng.normal(size=T.shape), scene.layout, sigma)[1].width
              for _ in range(6)]
    assert {w: chosen.count(w) for w in set(chosen)} == {r.width: r.chosen for r in rows if r.chosen}
