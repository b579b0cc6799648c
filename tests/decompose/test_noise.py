"""Each bounce sample's noise from draws of T and of the photo, against known answers:
the error a noisy T really makes (its truth known), a photo's noise through C1 (linear: its
covariance is exact), and where the noise of T comes from."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ilt.decompose.noise import bounce_sigma, draws_for, entry_noise, photo_noise
from ilt.isf.directory import ISF
from ilt.isf.noise import T_VAR_FILE
from ilt.transport.operators import bounce_images, cancellation_operator
from tests.transport.test_operators import physical_transport


def split(op, values, n):
    return bounce_images(op, values, n)


def unit(T):
    return T / np.linalg.norm(T, axis=0)


def test_the_draws_predict_the_error_a_noisy_t_makes():
    """T + noise of sigma 0.005 (unit columns): the draws' noise share of each bounce is
    the error against the true bounces to within 15%, seed after seed."""
    A, _, T = physical_transport(60, albedo=0.7, seed=6)
    T = unit(T)
    L = np.linalg.solve(np.eye(60) - A, np.ones(60))
    truth = [np.ones(60)]
    for _ in range(2):
        truth.append(A @ truth[-1])
    for seed in range(3):
        noisy = T + np.random.default_rng(seed).normal(scale=0.005, size=T.shape)
        dec = bounce_images(cancellation_operator(noisy), L, 3)
        (sigma,) = bounce_sigma(noisy, 0.005, [dec], [L], split, seed=seed + 10)
        error = np.linalg.norm(dec.bounces - np.array(truth), axis=1)
        predicted = np.linalg.norm(sigma, axis=1)
        np.testing.assert_allclose(predicted / error, 1.0, atol=0.15)


def test_a_photos_noise_goes_through_c1_as_its_covariance_says():
    """Bounce 1 is C1 L, linear in the photo: sigma_i^2 = sum_j C1_ij^2 s_j^2 exactly;
    400 draws find it to a few percent (and an entry sigma of 0 adds nothing)."""
    A, _, T = physical_transport(12, albedo=0.6, seed=1)
    L = np.linalg.solve(np.eye(12) - A, np.ones(12))
    op = cancellation_operator(T)
    dec = bounce_images(op, L, 2)
    s = 0.01 * L
    (sigma,) = bounce_sigma(T, 0.0, [dec], [L], split, values_std=[s], draws=400)
    C1 = op.apply(np.eye(12))
    exact = np.sqrt((C1**2) @ s**2)
    np.testing.assert_allclose(sigma[0], exact, rtol=0.12)
    assert np.median(np.abs(sigma[0] / exact - 1)) < 0.05


def test_per_entry_sigma_is_drawn_as_one_number_is():
    A, _, T = physical_transport(20, seed=2)
    L = np.linalg.solve(np.eye(20) - A, np.ones(20))
    dec = bounce_images(cancellation_operator(T), L, 2)
    one = bounce_sigma(T, 1e-3, [dec], [L], split, draws=8)[0]
    each = bounce_sigma(T, np.full(T.shape, 1e-3), [dec], [L], split, draws=8)[0]
    np.testing.assert_array_equal(one, each)
    assert draws_for(32) == 24 and draws_for(4096) == 8 and draws_for(1024) == 12


def test_the_noise_of_t_comes_from_t_var_unless_given(tmp_path):
    T = unit(physical_transport(6, seed=3)[2])
    (tmp_path / "isf").mkdir()
    isf = ISF(T=T, samples=None, layout=(1, 6), frame_shape=None, path=tmp_path / "isf" / "T.npy")
    assert entry_noise(isf, None, "given")[0] is None
    assert "not known" in entry_noise(isf, None, "given")[1]
    assert entry_noise(isf, 2e-3, "measured from negative entries of T") == (2e-3, "measured from negative entries of T")
    np.save(tmp_path / "isf" / T_VAR_FILE, np.full((6, 6), 4e-6, np.float32))
    sigma, source = entry_noise(isf, 1e-3, "measured from the beam frames")
    np.testing.assert_allclose(sigma, 2e-3, rtol=1e-6)
    assert source.endswith(T_VAR_FILE)
    assert entry_noise(isf, 5e-3, "given") == (5e-3, "given")      # --noise wins
    np.save(tmp_path / "isf" / T_VAR_FILE, np.ones((5, 5), np.float32))   # another T's: not used
    assert entry_noise(isf, 1e-3, "measured") == (1e-3, "measured")


def test_a_photos_sigma_is_the_frames_model_over_its_cells(tmp_path):
    T = unit(physical_transport(4, seed=4)[2])
    (tmp_path / "isf").mkdir()
    isf = ISF(T=T, samples=None, layout=(1, 4), frame_shape=None, path=tmp_path / "isf" / "T.npy")
    values = np.array([0.0, 10.0, 20.0, 40.0])
    assert photo_noise(isf, values, frame=True) is None          # no noise.json
    (tmp_path / "isf" / "noise.json").write_text(json.dumps(
        {"levels": [0.0, 100.0], "variances": [1.0, 101.0], "slope": 1.0, "frames": 1, "pixels": 1, "bins": 2,
         "entry_sigma": 1e-3}))
    assert photo_noise(isf, values, frame=False) is None          # a sample vector's noise is not known
    # point sampling: each sample is one pixel, Var = 1 + level
    np.testing.assert_allclose(photo_noise(isf, values, frame=True), np.sqrt(1 + values))
    cells = np.array([[0, 0, 1, -1], [2, 3, 3, 3]], np.int32)        # areas 2, 1, 1, 3
    isf = replace(isf, cells=cells)
    area = np.array([2, 1, 1, 3])
    np.testing.assert_allclose(photo_noise(isf, values, frame=True), np.sqrt(area * (1 + values / area)))
    with pytest.raises(AssertionError):
        np.testing.assert_allclose(photo_noise(isf, values, frame=True), np.sqrt(1 + values))


def test_a_noisy_diagonal_biases_bounce_1_low_and_its_variance_takes_that_back():
    """T's diagonal (each spot's own cell) 10% noisy, as a path tracer's noise makes it:
    over 300 draws bounce 1 comes out low on average (E[1 / (d + e)] > 1 / d: each beam's
    solved light high, and the light its neighbours get from it), by more than its draws'
    own scatter; raising each diagonal entry by its variance over itself
    (ilt.transport.regularise.diagonal_raise, with T_var's diagonal) takes at least two
    thirds of that bias away. Without a variance, or one too small to matter, nothing is raised."""
    from ilt.transport.regularise import diagonal_raise, raise_diagonal

    A, _, T = physical_transport(40, albedo=0.7, seed=3)
    T = unit(T)
    L = np.linalg.solve(np.eye(40) - A, np.ones(40))
    truth = bounce_images(cancellation_operator(T), L, 1).bounces[0]
    variance = np.zeros_like(T)
    np.fill_diagonal(variance, (0.1 * np.diag(T)) ** 2)
    rng = np.random.default_rng(7)
    plain, debiased = [], []
    for _ in range(300):
        noisy = T.copy()
        noisy[np.diag_indices(40)] *= 1.0 + 0.1 * rng.standard_normal(40)
        plain.append(bounce_images(cancellation_operator(noisy), L, 1).bounces[0].sum())
        raise_by, record = diagonal_raise(noisy, variance)
        fixed = raise_diagonal(noisy, raise_by)
        debiased.append(bounce_images(cancellation_operator(fixed), L, 1).bounces[0].sum())
    bias, left = np.mean(plain) - truth.sum(), np.mean(debiased) - truth.sum()
    assert bias < -3 * np.std(plain) / np.sqrt(300)
    assert abs(left) < abs(bias) / 3
    assert record["median_relative_sigma"] == pytest.approx(0.1, rel=0.15)
    assert diagonal_raise(T, None) == (None, None)
    assert diagonal_raise(T, variance * 1e-6) == (None, None)


def test_a_memory_mapped_T_is_raised_into_a_memory_map_of_its_own(tmp_path):
    """decompose reads T memory-mapped (never held twice): its raised diagonal goes to a
    memory map in a scratch directory beside the operator cache, gone when the stack
    closes; T's own file is unchanged; a T the decompose made itself is raised in place."""
    import contextlib

    from ilt.decompose.stage import _debiased_diagonal

    rng = np.random.default_rng(0)
    T = np.eye(50) + 0.01 * rng.random((50, 50))
    np.save(tmp_path / "T.npy", T)
    variance = np.zeros_like(T)
    np.fill_diagonal(variance, 0.04)
    mapped = np.load(tmp_path / "T.npy", mmap_mode="r")
    cache = tmp_path / "cache"
    cache.mkdir()
    with contextlib.ExitStack() as stack:
        out, record = _debiased_diagonal(mapped, variance, False, cache, stack)
        assert isinstance(out, np.memmap) and Path(out.filename).parent.parent == cache
        expected = T + np.diag(0.04 / np.diag(T))
        np.testing.assert_array_equal(out, expected)
        assert record["max_relative_raise"] == pytest.approx(0.04 / np.diag(T).min() ** 2)
    assert list(cache.iterdir()) == []
    np.testing.assert_array_equal(np.load(tmp_path / "T.npy"), T)
    own = T.copy()
    with contextlib.ExitStack() as stack:
        assert _debiased_diagonal(own, variance, True, None, stack)[0] is own
    np.testing.assert_array_equal(own, expected)
