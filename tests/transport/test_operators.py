"""ilt.transport against known answers: C1 = I - A for a known A, identities that must hold."""

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ilt.transport.diagnostics import (
    RHO_TOL,
    decomposition_diagnostics,
    operator_diagnostics,
    spectral_radius,
)
from ilt.transport.operators import bounce_images, cancellation_operator
from ilt.transport.scan import TransportError


def physical_transport(m, albedo=0.7, seed=0, fill=1.0):
    """A random Lambertian-like transport A = P K (zero diagonal, row sums < 1) and
    direct responses D: T = (I - A)^-1 diag(D) (paper Eq. 5 with impulse illumination)."""
    rng = np.random.default_rng(seed)
    K = rng.uniform(0, 1, (m, m)) * (rng.uniform(0, 1, (m, m)) < fill)
    np.fill_diagonal(K, 0)
    K /= np.maximum(K.sum(axis=1, keepdims=True), 1e-300) * 1.1
    A = albedo * K
    D = rng.uniform(0.2, 1.0, m)
    T = np.linalg.solve(np.eye(m) - A, np.diag(D))
    return A, D, T


@pytest.mark.parametrize("m", [1, 2, 7, 64, 300, 700])
def test_c1_is_identity_minus_a(m):
    A, D, T = physical_transport(m, seed=m)
    op = cancellation_operator(T)
    C1 = op.apply(np.eye(m))
    np.testing.assert_allclose(C1, np.eye(m) - A, atol=1e-13 * max(1, m / 100))
    # Eq. (13): T1 = 1 / diag(T^-1), and C1 T = T1 is diagonal.
    np.testing.assert_allclose(op.t1, 1 / np.diag(np.linalg.inv(T)), rtol=1e-12)
    np.testing.assert_allclose(op.t1, D, rtol=1e-12)
    np.testing.assert_allclose(op.apply(T), np.diag(D), atol=1e-13)


def test_two_by_two_analytic():
    # Two facing patches exchanging a fraction a, b of their light: A = [[0, a], [b, 0]].
    a, b = 0.3, 0.6
    A = np.array([[0, a], [b, 0]])
    T = np.linalg.inv(np.eye(2) - A) * np.array([2.0, 5.0])
    op = cancellation_operator(T)
    L = np.array([1.0, 0.5])
    dec = bounce_images(op, L, n_bounces=4)
    # Ln = C1 (I - C1)^(n-1) L = (I - A) A^(n-1) L exactly.
    expected = [np.linalg.matrix_power(A, n - 1) @ (np.eye(2) - A) @ L for n in range(1, 5)]
    np.testing.assert_allclose(dec.bounces, expected, atol=1e-15)
    assert spectral_radius(op) == pytest.approx(np.sqrt(a * b), rel=1e-9)


def test_bounces_of_photo_match_truth_and_close():
    A, D, T = physical_transport(200, albedo=0.8, seed=3)
    rng = np.random.default_rng(1)
    L1 = rng.uniform(0, 1, (200, 5))
    L = np.linalg.solve(np.eye(200) - A, L1)
    dec = bounce_images(cancellation_operator(T), L, n_bounces=10)
    truth = L1
    for n in range(10):
        err = np.linalg.norm(dec.bounces[n] - truth) / np.linalg.norm(truth)
        assert err < 1e-11, (n, err)
        truth = A @ truth
    np.testing.assert_allclose(dec.residual, L - dec.bounces.sum(axis=0), atol=1e-15)
    diag = decomposition_diagnostics(L, dec)
    assert diag["closure_error"] < 1e-15
    assert diag["negative_share"] == [0.0] * 10
    # The residual is the light of > 10 bounces: (I - A)^-1 A^10 L1.
    tail = np.linalg.solve(np.eye(200) - A, np.linalg.matrix_power(A, 10) @ L1)
    np.testing.assert_allclose(dec.residual, tail, atol=1e-13 * np.abs(L).max())


@settings(max_examples=30, deadline=None)
@given(
    m=st.integers(2, 40),
    seed=st.integers(0, 2**31 - 1),
    log_scales=st.lists(st.floats(-6, 6), min_size=40, max_size=40),
)
def test_c1_independent_of_column_scaling(m, seed, log_scales):
    A, D, T = physical_transport(m, seed=seed)
    scales = 10.0 ** np.array(log_scales[:m])
    C1 = cancellation_operator(T).apply(np.eye(m))
    C1s = cancellation_operator(T * scales).apply(np.eye(m))
    np.testing.assert_allclose(C1s, C1, atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(m=st.integers(1, 30), k=st.integers(1, 4), n=st.integers(1, 12), seed=st.integers(0, 2**31 - 1))
def test_closure_holds_for_any_photo(m, k, n, seed):
    _, _, T = physical_transport(m, seed=seed)
    L = np.random.default_rng(seed).normal(size=(m, k))
    dec = bounce_images(cancellation_operator(T), L, n_bounces=n)
    rebuilt = dec.bounces.sum(axis=0) + dec.residual
    assert np.linalg.norm(L - rebuilt) <= 1e-14 * np.linalg.norm(L) * n


def test_vector_and_batch_agree():
    _, _, T = physical_transport(50, seed=2)
    op = cancellation_operator(T)
    L = np.random.default_rng(0).uniform(size=(50, 3))
    batch = bounce_images(op, L, 5).bounces
    for j in range(3):
        np.testing.assert_array_equal(bounce_images(op, L[:, j], 5).bounces, batch[:, :, j])


def test_tolerance_stops_and_says_where():
    A, D, T = physical_transport(100, albedo=0.5, seed=4)
    L = np.linalg.solve(np.eye(100) - A, np.ones(100))
    dec = bounce_images(cancellation_operator(T), L, n_bounces=50, tol=1e-3)
    assert dec.stopped_early
    assert dec.relative_norms[-1] < 1e-3 <= dec.relative_norms[-2]
    assert dec.count < 50
    diag = decomposition_diagnostics(L, dec)
    assert f"after bounce {dec.count}" in diag["stop_reason"]


def test_spectral_radius_matches_eigenvalues():
    A, _, T = physical_transport(120, albedo=0.9, seed=5)
    rho = np.max(np.abs(np.linalg.eigvals(A)))
    op = cancellation_operator(T)
    assert spectral_radius(op) == pytest.approx(rho, rel=RHO_TOL)
    assert spectral_radius(op, tol=1e-8) == pytest.approx(rho, rel=1e-6)
    d = operator_diagnostics(T, op)
    assert d["spectral_radius_A"] == pytest.approx(rho, rel=RHO_TOL)
    assert d["warnings"] == []
    assert d["condition_estimate"] >= 1


def test_non_physical_t_warns_with_figure():
    # A with spectral radius > 1 (albedo "1.5"): I - A is still invertible but T is not a physical ISF.
    m = 30
    A = 1.5 * np.full((m, m), 1 / (m - 1))
    np.fill_diagonal(A, 0)
    T = np.linalg.inv(np.eye(m) - A)
    op = cancellation_operator(T)
    d = operator_diagnostics(T, op)
    assert d["spectral_radius_A"] == pytest.approx(1.5, rel=1e-6)
    assert any("1.5" in w and ">= 1: the bounce series diverges" in w for w in d["warnings"])


@pytest.mark.parametrize(
    "T, message",
    [
        (np.ones((3, 4)), "square"),
        (np.array([[1.0, np.nan], [0.0, 1.0]]), "non-finite value nan at pixel row 0, beam column 1"),
        (np.array([[1.0, 0.0], [0.0, 0.0]]), "column 1 (beam 1) is all zero"),
        (np.array([[1.0, 1.0, 0.2], [0.5, 0.5, 1.0], [0.1, 0.1, 0.3]]), "columns 0 and 1 are identical"),
        (np.array([[1.0, 2.0], [2.0, 4.0000000000000001]]), "singular"),
        (np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]]), "singular"),
    ],
)
def test_bad_isf_is_refused_with_reason(T, message):
    with pytest.raises(TransportError, match=message.replace("(", r"\(").replace(")", r"\)")):
        cancellation_operator(T)


def test_wrong_length_photo_is_refused():
    _, _, T = physical_transport(10)
    op = cancellation_operator(T)
    with pytest.raises(TransportError, match=r"shape \(11,\).*m = 10"):
        bounce_images(op, np.ones(11))
    with pytest.raises(TransportError, match="non-finite"):
        bounce_images(op, np.full(10, np.inf))


def test_negatives_warn_past_a_tenth_of_a_bounce_and_only_beyond_its_noise():
    """A negative sample is wrong by at least its size: negatives holding > 10% of a
    bounce's 2-norm warn (one line for all bounces); with each sample's sigma known,
    only when they are also past 5 sigma of it."""
    A, D, T = physical_transport(40, albedo=0.7, seed=6)
    L = np.linalg.solve(np.eye(40) - A, np.ones(40))
    dec = bounce_images(cancellation_operator(T), L, n_bounces=3)
    clean = decomposition_diagnostics(L, dec)
    assert clean["negative_energy"] == [0.0] * 3 and clean["warnings"] == []
    assert clean["notes"] == ["bounces as expected: no negatives"]
    bounces = dec.bounces.copy()
    size = 0.2 * np.linalg.norm(bounces[1])
    bounces[1, 7] = -size                                 # about 20% of bounce 2, one sample
    bounces[2, 9] = -0.05 * np.linalg.norm(bounces[2])    # 5% of bounce 3: below the bar
    faulty = replace(dec, bounces=bounces, residual=L - bounces.sum(axis=0))   # still closes
    d = decomposition_diagnostics(L, faulty, where=lambda i: f"pixel {i}")
    assert d["negative_energy"][1] == pytest.approx(size / np.linalg.norm(bounces[1]), rel=1e-12)
    (w,) = d["warnings"]
    assert w.startswith("bounce 2 holds negatives") and "at least 20% of bounce 2 is wrong (worst: " in w
    assert "pixel 7" in w
    assert "noise of T is not known" in w
    # within the noise: the same negatives with a sigma as large are not a fault
    loud = decomposition_diagnostics(L, faulty, sigma=np.abs(bounces) + 0.3 * np.abs(bounces).max())
    assert loud["warnings"][:1] != [w] and not any("negatives" in x for x in loud["warnings"])
    assert loud["worst_sigma"][1] > -5
    # beyond it
    quiet = decomposition_diagnostics(L, faulty, sigma=np.full(bounces.shape, 1e-3 * np.abs(bounces).max()))
    (w,) = quiet["warnings"]
    assert "beyond the noise" in w and "bounce 2, " in w and "sigma at sample 7" in w


def test_lost_light_and_a_beam_dark_in_its_own_cell_warn():
    A, D, T = physical_transport(20, albedo=0.6, seed=5)
    L = np.linalg.solve(np.eye(20) - A, np.ones(20))
    dec = bounce_images(cancellation_operator(T), L, n_bounces=3)
    lossy = replace(dec, residual=dec.residual * 0.5)
    d = decomposition_diagnostics(L, lossy)
    assert d["closure_error"] == pytest.approx(np.linalg.norm(dec.residual) * 0.5 / np.linalg.norm(L), rel=1e-9)
    assert d["warnings"] == [f"closure error {d['closure_error']:.3g} > 1e-10: the decomposition lost light"]
    dark = T.copy()
    dark[4, 4] = -0.1 * T[4, 4]                    # beam 4 reads below black in its own cell
    diagnostics = operator_diagnostics(dark, cancellation_operator(dark))
    assert diagnostics["min_diagonal_beam"] == 4 and diagnostics["min_diagonal"] < 0
    assert any("beam 4 does not light its own sample pixel" in w for w in diagnostics["warnings"])


def test_noise_of_the_first_bounces_warns_past_a_fifth():
    A, D, T = physical_transport(30, albedo=0.7, seed=2)
    L = np.linalg.solve(np.eye(30) - A, np.ones(30))
    dec = bounce_images(cancellation_operator(T), L, n_bounces=4)
    sigma = 0.1 * np.abs(dec.bounces)
    assert decomposition_diagnostics(L, dec, sigma)["warnings"] == []
    sigma[1] *= 3.0                                            # bounce 2: 30% noise
    sigma[3] *= 9.0                                            # bounce 4 is not watched
    d = decomposition_diagnostics(L, dec, sigma)
    assert d["noise_share"][1] == pytest.approx(0.3)
    assert d["warnings"] == ["bounce 2 is noisy: its noise is 30% of its signal; longer exposures, more frames "
                             "per beam or --regularise lower it"]


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_factors_of_the_transpose_give_t_inverse_with_pivoting(dtype):
    """The factors are T^T's (issue 15: no Fortran-order copy of T): solves, diag(T^-1)
    and the 1-norm condition estimate are T's, also where partial pivoting reorders rows
    (a T that is not diagonally dominant, columns of very different scales)."""
    rng = np.random.default_rng(3)
    m = 97
    T = rng.uniform(0.0, 1.0, (m, m)) + np.diag(rng.uniform(0.0, 0.5, m))
    T *= rng.uniform(0.1, 10.0, m)[None, :]
    op = cancellation_operator(T, dtype=dtype)
    Tn = T / np.linalg.norm(T, axis=0)
    inverse = np.linalg.inv(Tn)
    tol = 1e-9 if dtype == np.float64 else 2e-2
    b = rng.standard_normal((m, 3))
    np.testing.assert_allclose(op.solve(b), inverse @ b, rtol=tol, atol=tol * np.abs(inverse @ b).max())
    np.testing.assert_allclose(op.solve(b[:, 0]), inverse @ b[:, 0], rtol=tol, atol=tol * np.abs(inverse @ b).max())
    np.testing.assert_allclose(op.t1_unit, 1.0 / np.diag(inverse), rtol=tol)
    exact = 1.0 / (np.abs(Tn).sum(axis=0).max() * np.abs(inverse).sum(axis=0).max())
    assert exact / 3 <= op.rcond <= exact * 3


class _Counting:
    """An operator that counts its applies."""

    def __init__(self, op):
        self.op, self.m, self.applies = op, op.m, 0

    def apply(self, x):
        self.applies += 1
        return self.op.apply(x)


@pytest.mark.parametrize("name", ["m", "box", "occluded", "textured"])
def test_spectral_radius_within_its_tolerance_of_dense_eigenvalues_in_few_applies(name):
    from ilt.sim import make_scene

    T, _ = make_scene(name).isf()
    op = cancellation_operator(T)
    m = op.m
    exact = np.max(np.abs(np.linalg.eigvals(np.eye(m) - op.apply(np.eye(m)))))
    counted = _Counting(op)
    assert spectral_radius(counted) == pytest.approx(exact, rel=RHO_TOL)
    assert counted.applies <= 30  # ARPACK at its default 1e-8 and basis of 20 took 21 and more


def test_spectral_radius_near_one_is_refined_so_the_warning_is_decided_sharply():
    # rho(A) = 1 - 5e-4 exactly (Perron root of a chain whose rows sum to it): within the
    # loose tolerance's reach of 1, so the value is recomputed to 1e-8 and stays below 1
    m = 200
    rng = np.random.default_rng(3)
    A = np.zeros((m, m))
    i = np.arange(m - 1)
    A[i, i + 1] = rng.uniform(0.5, 1.0, m - 1)
    A[i + 1, i] = rng.uniform(0.5, 1.0, m - 1)
    A *= (1 - 5e-4) / A.sum(axis=1, keepdims=True)
    T = np.linalg.solve(np.eye(m) - A, np.diag(rng.uniform(0.5, 2.0, m)))
    op = cancellation_operator(T)
    rho = spectral_radius(op)
    assert rho == pytest.approx(1 - 5e-4, rel=1e-7)
    assert operator_diagnostics(T, op)["warnings"] == []
