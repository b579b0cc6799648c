"""The reciprocity test of a Lambertian T: identities, known asymmetries, noise, a bad beam."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ilt.sim.scene import make_scene
from ilt.transport.reciprocity import TOLERANCE, near_pairs, reciprocity_check


def _symmetrisable(m: int, seed: int) -> np.ndarray:
    """D1 S D2 with S symmetric positive, D1, D2 positive diagonals: reciprocal by construction."""
    rng = np.random.default_rng(seed)
    S = rng.uniform(0.1, 1.0, (m, m))
    S = S + S.T
    return rng.uniform(0.2, 5.0, m)[:, None] * S * rng.uniform(0.2, 5.0, m)[None, :]


@settings(max_examples=20, deadline=None)
@given(m=st.integers(7, 40), seed=st.integers(0, 2**31 - 1))
def test_any_diagonal_scaling_of_a_symmetric_matrix_is_reciprocal(m, seed):
    r = reciprocity_check(_symmetrisable(m, seed))
    assert r.residual < 1e-8 and r.verdict == "lambertian" and r.pairs == m * (m - 1) // 2


def test_exact_lambertian_scenes_fit_to_rounding():
    for name, beams in (("m", 32), ("occluded", 32), ("box", 48)):
        T, _ = make_scene(name, beams).isf()
        r = reciprocity_check(T)
        assert r.residual < 1e-9, (name, r.residual)
        assert r.verdict == "lambertian"


def test_a_known_asymmetry_is_measured():
    """log T_ij - log T_ji off a gradient by e_ij ~ N(0, s^2): the robust rms reads s (one draw, 3%)."""
    m, s = 60, 0.3
    rng = np.random.default_rng(1)
    noise = np.triu(rng.normal(0, s, (m, m)), 1)
    T = _symmetrisable(m, 2) * np.exp(noise)
    r = reciprocity_check(T)
    # half the asymmetry is in T_ij, the other entry untouched: the fit sees e itself
    assert r.residual == pytest.approx(s, rel=0.06)
    assert r.verdict == "not lambertian" and r.excess == pytest.approx(r.residual)


def test_noise_alone_is_explained_by_the_floor_and_more_noise_leaves_it_undecided():
    """The exact box's T plus noise of sigma x max T: the residual is the floor's (within a fifth) and no
    excess, until no pair stands 10 sigmas above its noise."""
    T, _ = make_scene("box", 108).isf()
    rng = np.random.default_rng(3)
    for sigma, verdict in ((1e-4, "lambertian"), (1e-3, "lambertian"), (3e-3, "lambertian"), (1e-2, "undecided")):
        var = np.full(T.shape, sigma**2) * (T.max() ** 2)
        noisy = T + rng.normal(0, 1, T.shape) * np.sqrt(var)
        r = reciprocity_check(noisy, var)
        if r.pairs >= 100:
            assert r.noise_floor == pytest.approx(r.residual, rel=0.2), (sigma, r)
        assert r.excess < 0.5 * TOLERANCE
        assert r.verdict == verdict, (sigma, r.reason)


def test_one_bad_beam_does_not_condemn_the_scene_but_is_named():
    """A beam whose cell is not a fair sample (say one pixel at an occluding edge) spoils its own pairs only."""
    T, _ = make_scene("m", 32).isf()
    T = T.copy()
    T[7] *= np.exp(np.random.default_rng(4).normal(0, 1.0, 32))
    r = reciprocity_check(T)
    assert r.verdict == "lambertian" and r.residual < 0.02
    assert r.worst(1)[0]["beam"] == 7


def test_no_pair_above_the_noise_is_undecided():
    T = np.eye(5)
    r = reciprocity_check(T)
    assert r.verdict == "undecided" and r.pairs == 0 and "no pair" in r.reason


def test_near_pairs_are_those_within_the_spacings():
    samples = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [30.0, 0.0], [40.0, 0.0]])
    near = near_pairs(samples, spacings=1.5).tocsr()
    assert near[0, 1] and near[3, 4] and not near[0, 2] and not near[1, 4]
    T = _symmetrisable(5, 0)
    assert reciprocity_check(T, exclude=near).pairs == 10 - 4
