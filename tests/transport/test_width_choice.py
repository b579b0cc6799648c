"""The regularisation's width, chosen by its estimated risk (ilt.transport.regularise.choose_width),
and the noisy diagonal's raise (diagonal_raise)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree

from ilt.isf.fine import adjacent_cells
from ilt.transport import regularise as R


def _scene(m: int = 300, seed: int = 1):
    """A unit-column T over m spots on a grid of Voronoi cells (a 160 x 120 frame): indirect
    light falling with distance, 1.5x brighter on the right half (an edge); the cells' pairs."""
    side = int(np.ceil(np.sqrt(m * 4 / 3)))
    xs, ys = np.meshgrid(np.linspace(2, 158, side), np.linspace(2, 118, int(np.ceil(m / side))))
    spots = np.stack([xs.ravel(), ys.ravel()], axis=1)[:m]
    yy, xx = np.mgrid[0:120, 0:160]
    labels = cKDTree(spots).query(np.stack([xx.ravel(), yy.ravel()], axis=1))[1].reshape(120, 160)
    d = np.linalg.norm(spots[:, None] - spots[None], axis=2)
    T = 0.3 / m * np.exp(-d / 50.0) * (1.0 + 0.5 * (spots[:, 0][:, None] > 80))
    np.fill_diagonal(T, 1.0)
    return T / np.linalg.norm(T, axis=0), np.asarray(adjacent_cells(labels), np.int64)


@pytest.fixture(scope="module")
def scene():
    return _scene()


def _noisy(T, sigma, seed=0):
    """T plus noise of a known variance per entry (0.5 to 1.5 sigma^2), its diagonal exact."""
    rng = np.random.default_rng(seed)
    V = sigma ** 2 * (0.5 + rng.random(T.shape))
    noisy = T + np.sqrt(V) * rng.standard_normal(T.shape)
    np.fill_diagonal(noisy, np.diagonal(T))
    return noisy, V


@pytest.mark.parametrize("exact", [True, False], ids=["identity", "probes"])
def test_the_estimated_risk_is_the_filters_true_error(scene, exact, monkeypatch):
    """SURE: bias^2 + variance, estimated from the noisy T alone, is its distance from the
    true T at every width (relative to the noise's total variance), whether the filter's
    diagonals are measured exactly or from random sign probes."""
    T, pairs = scene
    sigma = 2e-3
    noisy, V = _noisy(T, sigma)
    monkeypatch.setattr(R, "PROBE_EXACT_M", 10 ** 9 if exact else 0)
    _, _, table = R.choose_width(noisy, None, sigma, V, pairs, widths=(0.5, 0.82, 1.41))
    total = V.sum() - np.trace(V)
    for row in table:
        true = np.sum((R.smooth_isf(noisy, None, row["width"], sigma, pairs) - T) ** 2) / total
        assert row["bias2"] + row["variance"] == pytest.approx(true, abs=0.02), row
    # and the filter removes noise: every width is far closer than T as measured (1.0)
    assert max(row["bias2"] + row["variance"] for row in table) < 0.2


def test_more_noise_gets_a_wider_filter_and_a_closer_t(scene):
    T, pairs = scene
    chosen = []
    for sigma in (1e-4, 1e-3, 1e-2):
        noisy, V = _noisy(T, sigma)
        filtered, width, _ = R.choose_width(noisy, None, sigma, V, pairs)
        chosen.append(width)
        assert np.linalg.norm(filtered - T) < np.linalg.norm(noisy - T)
    assert chosen == sorted(chosen) and chosen[-1] > chosen[0], chosen


def test_regularise_without_a_width_reports_the_choice(scene):
    T, pairs = scene
    noisy, V = _noisy(T, 1e-2)
    filtered, reg = R.regularise_isf(noisy, None, 1e-2, width=None, pairs=pairs, variance=V)
    assert reg.width in R.CHOICES and [w for w, _ in reg.tried] == [0.0, *R.CHOICES]
    assert f"width {reg.width:g}" in reg.describe() and "estimated risk" in reg.describe()
    assert np.linalg.norm(filtered - T) < 0.5 * np.linalg.norm(noisy - T)
    # no noise to remove: T as measured, and why
    clean, none = R.regularise_isf(T, None, 1e-12, width=None, pairs=pairs)
    assert none.width == 0 and np.allclose(clean, T, rtol=1e-12, atol=0) and "left as measured" in none.describe()


def test_the_plans_grid_and_its_own_pairs_choose_alike():
    """Without cells the filter runs on the plan's grid: the same choice, the same risks and
    the same filtered T as along the grid's own neighbour pairs (two code paths, one filter)."""
    rows, cols = 12, 10
    m = rows * cols
    index = np.arange(m).reshape(rows, cols)
    pairs = np.concatenate([np.stack([index[:-1].ravel(), index[1:].ravel()], 1),
                            np.stack([index[:, :-1].ravel(), index[:, 1:].ravel()], 1)])
    yy, xx = np.divmod(np.arange(m), cols)
    d = np.hypot(yy[:, None] - yy[None], xx[:, None] - xx[None])
    T = 0.3 / m * np.exp(-d / 4.0) * (1.0 + 0.5 * (xx[:, None] >= cols // 2))
    np.fill_diagonal(T, 1.0)
    noisy, V = _noisy(T / np.linalg.norm(T, axis=0), 3e-3)
    grid = R.choose_width(noisy, (rows, cols), 3e-3, V)
    graph = R.choose_width(noisy, None, 3e-3, V, pairs)
    assert grid[1] == graph[1] > 0
    assert np.allclose(grid[0], graph[0], rtol=1e-10, atol=1e-13)
    for a, b in zip(grid[2], graph[2]):
        assert a["risk"] == pytest.approx(b["risk"], rel=1e-8, abs=1e-12)


def _chain(m: int = 60, sigma: float = 1e-2, seed: int = 3):
    """A strip of m cells of 7 and 9 px in turn (a row of T is its cell's sum: the light per
    pixel times the area), smooth light per pixel; the chain's pairs, the areas, the true
    unit-column T and a noisy one with its variances."""
    i = np.arange(m)
    areas = np.where(i % 2 == 0, 7.0, 9.0)
    T = areas[:, None] * np.exp(-0.5 * ((i[:, None] - i[None]) / 12.0) ** 2) / m
    np.fill_diagonal(T, 1.0)
    T /= np.linalg.norm(T, axis=0)
    noisy, V = _noisy(T, sigma, seed)
    return T, noisy, V, areas, np.stack([i[:-1], i[1:]], axis=1)


def test_per_pixel_filtering_of_cells_of_two_sizes():
    """A row of T is a cell's sum: smoothing the sums of a 7 px and a 9 px cell gives each
    part of the other's area. Per pixel of each cell (``areas``) a smooth T passes the filter
    nearly unchanged, and a noisy one comes out closer to the truth than by its sums."""
    T, noisy, V, areas, pairs = _chain()
    clean_sums = R.smooth_isf(T, None, 1.41, 1e-2, pairs)
    clean_pixels, _ = R.regularise_isf(T, None, 1e-2, width=1.41, pairs=pairs, areas=areas)
    assert np.linalg.norm(clean_pixels - T) < 0.3 * np.linalg.norm(clean_sums - T)   # 0.087 against 0.434
    sums, by_sums = R.regularise_isf(noisy, None, 1e-2, width=None, pairs=pairs, variance=V)
    pixels, by_pixels = R.regularise_isf(noisy, None, 1e-2, width=None, pairs=pairs, variance=V, areas=areas)
    assert by_pixels.per_pixel and "per pixel of each cell" in by_pixels.describe()
    assert np.linalg.norm(pixels - T) < np.linalg.norm(sums - T) < np.linalg.norm(noisy / np.linalg.norm(
        noisy, axis=0) - T)
    # cells all of one size: the same filter either way
    same, _ = R.regularise_isf(noisy, None, 1e-2, width=1.0, pairs=pairs, areas=np.full(len(areas), 8.0))
    plain, _ = R.regularise_isf(noisy, None, 1e-2, width=1.0, pairs=pairs)
    assert np.allclose(same, plain, rtol=1e-9, atol=1e-12)


def test_areas_need_their_pairs():
    T, noisy, V, areas, pairs = _chain(m=12)
    with pytest.raises(ValueError, match="areas"):
        R.regularise_isf(noisy, (3, 4), 2e-3, areas=areas)
    with pytest.raises(ValueError, match="areas"):
        R.regularise_isf(noisy, None, 2e-3, pairs=pairs, areas=np.r_[areas[:-1], 0.0])


@settings(max_examples=40, deadline=None)
@given(st.integers(min_value=2, max_value=12), st.integers(min_value=0, max_value=2**31 - 1))
def test_the_diagonals_raise_is_its_variance_over_itself_and_nothing_else(m, seed):
    """For any T and variance: raise_diagonal changes the diagonal only, each entry by its
    variance over itself where it is positive (0 where it is not), and leaves T as it was;
    nothing is raised when every relative variance is under the floor."""
    from ilt.transport.regularise import DIAGONAL_FLOOR, diagonal_raise, raise_diagonal

    rng = np.random.default_rng(seed)
    T = rng.normal(0.0, 0.1, (m, m))
    T[np.diag_indices(m)] = rng.uniform(-0.2, 1.0, m)
    variance = rng.uniform(0.0, 0.05, (m, m))
    before = T.copy()
    raise_by, record = diagonal_raise(T, variance)
    d, v = np.diagonal(T), np.diagonal(variance)
    if raise_by is None:
        assert np.all((d <= 0) | (v / np.where(d > 0, d, 1.0) ** 2 <= DIAGONAL_FLOOR))
        return
    np.testing.assert_allclose(raise_by, np.where(d > 0, v / np.where(d > 0, d, 1.0), 0.0))
    out = raise_diagonal(T, raise_by)
    np.testing.assert_array_equal(T, before)
    off = ~np.eye(m, dtype=bool)
    np.testing.assert_array_equal(out[off], T[off])
    np.testing.assert_allclose(np.diagonal(out), d + raise_by)
    assert record["max_relative_raise"] >= record["mean_relative_raise"] >= 0
