"""Flat cells' slopes from their neighbours' means (ilt.isf.slopes), against analytic fields."""

import numpy as np

from ilt.isf.fine import CellGeometry
from ilt.isf.slopes import NeighbourSlopes


def _grid(cells_y, cells_x, px):
    """Square cells of ``px`` pixels a side, in scanline order."""
    y, x = np.mgrid[:cells_y * px, :cells_x * px]
    return (y // px) * cells_x + x // px


def _voronoi(shape, spacing, rng):
    """Cells about jittered lattice spots (as a scan's are)."""
    ys, xs = np.mgrid[spacing // 2:shape[0]:spacing, spacing // 2:shape[1]:spacing]
    spots = np.stack([xs.ravel(), ys.ravel()], 1) + rng.uniform(-0.3, 0.3, (xs.size, 2)) * spacing
    y, x = np.mgrid[:shape[0], :shape[1]]
    d = (x[..., None] - spots[:, 0]) ** 2 + (y[..., None] - spots[:, 1]) ** 2
    return d.argmin(axis=2), spots.shape[0]


def _planes(geometry, slopes, means):
    """(n, c) the field at the pixels inside cells: each cell's mean plus its plane."""
    coefficients = slopes.coefficients(means)
    basis = geometry.basis(1)
    label = geometry.label
    return means[label] + basis[0][:, None] * coefficients[0][label] + basis[1][:, None] * coefficients[1][label]


def _means(geometry, field):
    """(m, 1) cell means of ``field`` (H, W)."""
    values = field.ravel()[geometry.inside]
    return (np.bincount(geometry.label, values, geometry.m) / geometry.area)[:, None]


def test_a_linear_field_is_rebuilt_exactly_inside_the_scan():
    """Analytic: cell means of f = 2 + 0.3 x - 0.1 y give back f at every pixel of every
    cell whose neighbours surround it (the limiter leaves a ramp alone), in the basis'
    units (slope x the cell's size)."""
    labels = _grid(6, 7, 6)
    geometry = CellGeometry.from_labels(labels, 42)
    y, x = np.mgrid[:36, :42].astype(np.float64)
    field = 2.0 + 0.3 * x - 0.1 * y
    means = _means(geometry, field)
    slopes = NeighbourSlopes(geometry, np.ones(42, bool))
    coefficients = slopes.coefficients(means)
    interior = np.array([r * 7 + c for r in range(1, 5) for c in range(1, 6)])
    np.testing.assert_allclose(coefficients[0, interior, 0], 0.3 * 6, rtol=1e-10)
    np.testing.assert_allclose(coefficients[1, interior, 0], -0.1 * 6, rtol=1e-10)
    rebuilt = _planes(geometry, slopes, means)[:, 0]
    inside = np.isin(geometry.label, interior)
    np.testing.assert_allclose(rebuilt[inside], field.ravel()[geometry.inside][inside], atol=1e-12)
    # the corner cells holding the ramp's extremes (top right, bottom left): no plane can stay in range there
    assert np.all(coefficients[:, [6, 35], 0] == 0)


def test_no_plane_leaves_the_range_of_its_neighbours_means():
    """The Barth-Jespersen bound, an identity of the limiter: on Voronoi cells of jittered
    spots, for a field with a jump, a peak and noise, every pixel of every cell's plane
    lies between the smallest and largest mean of the cell and its neighbours, and every
    plane sums to zero over its cell."""
    rng = np.random.default_rng(3)
    labels, m = _voronoi((60, 80), 10, rng)
    geometry = CellGeometry.from_labels(labels, m)
    y, x = np.mgrid[:60, :80].astype(np.float64)
    field = np.where(x > 37.5, 3.0, 1.0) + np.exp(-((x - 20) ** 2 + (y - 30) ** 2) / 50.0) + 0.02 * x
    field = np.stack([field, field * 0.5 + rng.normal(0, 0.2, field.shape)], axis=-1)
    means = np.stack([_means(geometry, field[..., k])[:, 0] for k in range(2)], axis=1)
    slopes = NeighbourSlopes(geometry, np.ones(m, bool))
    rebuilt = _planes(geometry, slopes, means)
    pairs = set()
    for a, b in ((labels[:, :-1], labels[:, 1:]), (labels[:-1], labels[1:])):
        edge = a != b
        pairs |= set(zip(a[edge].tolist(), b[edge].tolist())) | set(zip(b[edge].tolist(), a[edge].tolist()))
    high, low = means.copy(), means.copy()
    for i, j in pairs:
        high[i], low[i] = np.maximum(high[i], means[j]), np.minimum(low[i], means[j])
    label = geometry.label
    assert np.all(rebuilt <= high[label] + 1e-12) and np.all(rebuilt >= low[label] - 1e-12)
    sums = np.stack([np.bincount(label, rebuilt[:, k] - means[label, k], m) for k in range(2)], axis=1)
    assert np.abs(sums).max() < 1e-9
    assert np.abs(slopes.coefficients(means)).max() > 0.1        # and the planes are there
    # a 3D fold between two columns of square cells, light rising to it on the left, noisy, and
    # less across: a cell with a neighbour across it may reach as far again past its mean as
    # its own side's farthest neighbour lies on the other side of it, no further
    labels = _grid(8, 10, 6)
    geometry = CellGeometry.from_labels(labels, 80)
    label = geometry.label
    y, x = np.mgrid[:48, :60].astype(np.float64)
    means = _means(geometry, np.where(x < 30, 1.0 + 0.05 * x, 0.5) + rng.normal(0, 0.05, x.shape))
    fold = (np.array([29.5, -1.0]), np.array([29.5, 49.0]), True)
    folded = _planes(geometry, NeighbourSlopes(geometry, np.ones(80, bool), folds=[fold]), means)
    pairs = set()
    for a, b in ((labels[:, :-1], labels[:, 1:]), (labels[:-1], labels[1:])):
        edge = a != b
        pairs |= set(zip(a[edge].tolist(), b[edge].tolist())) | set(zip(b[edge].tolist(), a[edge].tolist()))
    side = lambda i, j: (i % 10 < 5) == (j % 10 < 5)
    high, low = means.copy(), means.copy()
    for i, j in pairs:
        high[i], low[i] = np.maximum(high[i], means[j]), np.minimum(low[i], means[j])
    wide_high, wide_low = high.copy(), low.copy()
    for i in {i for i, j in pairs if not side(i, j)}:
        same = [j for a, j in pairs if a == i and side(i, j)]
        wide_high[i] = np.maximum(high[i], 2 * means[i] - np.min([means[i], *means[same]], axis=0))
        wide_low[i] = np.minimum(low[i], 2 * means[i] - np.max([means[i], *means[same]], axis=0))
    assert np.all(folded <= wide_high[label] + 1e-12) and np.all(folded >= wide_low[label] - 1e-12)
    assert (folded > high[label] + 0.05).any()                     # and the cells beside the fold use it


def test_a_peak_stays_flat_and_sloped_cells_keep_their_own():
    """A cell whose mean is above all its neighbours' gets no slope; cells the build
    sloped get 0 here (their slopes are in the fine coefficients)."""
    labels = _grid(3, 3, 5)
    geometry = CellGeometry.from_labels(labels, 9)
    means = np.array([[1.0], [2.0], [3.0], [2.0], [5.0], [4.0], [3.0], [4.0], [5.0]])
    flat = np.ones(9, bool)
    flat[7] = False
    coefficients = NeighbourSlopes(geometry, flat).coefficients(means)
    assert np.all(coefficients[:, 4] == 0)                        # the peak
    assert np.all(coefficients[:, 7] == 0)                        # sloped by the build
    assert coefficients[0, 3, 0] > 0 and coefficients[1, 3, 0] > 0   # a cell on the ramp up to the peak


def test_a_row_of_strips_gets_no_slope_across_the_row():
    """A flatland scan's cells are strips the height of the frame, side by side: a field
    rising along x gets its slope in x inside the row, and none in y (nothing to read it from)."""
    x = np.arange(64)
    labels = np.broadcast_to(x // 8, (32, 64))
    geometry = CellGeometry.from_labels(labels, 8)
    field = np.broadcast_to(0.5 + 0.25 * x, (32, 64)).astype(np.float64)
    coefficients = NeighbourSlopes(geometry, np.ones(8, bool)).coefficients(_means(geometry, field))
    np.testing.assert_allclose(coefficients[0, 1:7, 0], 0.25 * geometry.size[1:7], rtol=1e-10)
    assert np.abs(coefficients[1]).max() < 1e-12


def test_a_neighbour_across_a_fold_bounds_the_plane_but_gives_it_no_gradient():
    """Analytic: light rising to a fold at x = 24 (1 + 0.2 x) and level and brighter across
    it (20). Told the fold, every cell whose neighbours surround it on its own side gets its
    side's field back exactly, those next to the fold too: the ramp's slope (0.2 x the cell's
    6 px), and no slope on the level side. Not told, the step across the fold steepens the
    ramp's last column (2.4x: 2.88 for 1.2)."""
    labels = _grid(6, 8, 6)
    geometry = CellGeometry.from_labels(labels, 48)
    y, x = np.mgrid[:36, :48].astype(np.float64)
    field = np.where(x < 24, 1.0 + 0.2 * x, 20.0)
    means = _means(geometry, field)
    fold = [(np.array([24.0 - 0.5, -1.0]), np.array([24.0 - 0.5, 40.0]))]   # pixel 24's left edge
    told, blind = NeighbourSlopes(geometry, np.ones(48, bool), folds=fold), NeighbourSlopes(geometry,
                                                                                           np.ones(48, bool))
    rows = range(1, 5)
    left = np.array([r * 8 + c for r in rows for c in (1, 2, 3)])      # column 3 beside the fold
    right = np.array([r * 8 + c for r in rows for c in (4, 5, 6)])     # column 4 beside it
    coefficients = told.coefficients(means)
    np.testing.assert_allclose(coefficients[0, left, 0], 0.2 * 6, rtol=1e-10)
    np.testing.assert_allclose(coefficients[:, right, 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(coefficients[1, left, 0], 0.0, atol=1e-12)
    rebuilt = _planes(geometry, told, means)[:, 0]
    inside = np.isin(geometry.label, np.concatenate([left, right]))
    np.testing.assert_allclose(rebuilt[inside], field.ravel()[geometry.inside][inside], atol=1e-12)
    beside = np.array([r * 8 + 3 for r in rows])
    np.testing.assert_allclose(blind.coefficients(means)[0, beside, 0], 2.88, rtol=1e-10)
    # and the bound is still every neighbour's: light falling away across a flatland fold (a
    # step down to 0) leaves the column beside it, the highest of its side, flat; beside a 3D
    # fold the bound takes in its own side's ramp carried on, and that column gets the ramp whole
    dropped = _means(geometry, np.where(x < 24, 1.0 + 0.2 * x, 0.0))
    assert np.all(told.coefficients(dropped)[:, beside, 0] == 0)
    solid = NeighbourSlopes(geometry, np.ones(48, bool), folds=[(*fold[0], True)])
    coefficients = solid.coefficients(dropped)
    np.testing.assert_allclose(coefficients[0, left, 0], 0.2 * 6, rtol=1e-10)
    np.testing.assert_allclose(coefficients[1, left, 0], 0.0, atol=1e-12)


def test_crosses_needs_both_ends_strictly_either_side():
    """Segment pairs against a fold from (0, 0) to (10, 0): across, beside its end, along it,
    touching it."""
    from ilt.isf.slopes import crosses

    fold = [((0.0, 0.0), (10.0, 0.0))]
    a = np.array([(5, -1), (11, -1), (2, 1), (5, 0), (5, -3)], float)
    b = np.array([(5, 1), (11, 1), (8, 1), (5, 2), (6, 3)], float)
    assert crosses(a, b, fold).tolist() == [True, False, False, False, True]
    assert not crosses(a, b, []).any()
