"""The light cells send across a concave fold (ilt.isf.fold_transfer), against the kernel's
own double integrals: two facets unfolded into the frame, the fold the column x = FOLD."""

import numpy as np
import pytest

from ilt.isf import fold_transfer as ft

FOLD, ROWS, COLS = 50.0, 24, 101


def flatland(a, b):
    """The flatland form factor kernel between points a and b from a right-angled fold."""
    return a * b / (2 * (a * a + b * b) ** 1.5)


def solid(a, b, du):
    """... in 3D, between points a and b from the fold and du apart along it."""
    return a * b / (np.pi * (a * a + b * b + du * du) ** 2)


def vertical_line(x=FOLD):
    return ft.FoldLine(np.array([x, (ROWS - 1) / 2]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]),
                       -(ROWS - 1) / 2 - 0.5, (ROWS - 1) / 2 + 0.5)


def cells_across(receiving=(42, 49), emitting=(51, 62)):
    """Cell 0 the columns ``receiving`` left of the fold, cell 1 ``emitting`` right of it."""
    labels = np.full((ROWS, COLS), -1)
    labels[:, receiving[0]:receiving[1] + 1] = 0
    labels[:, emitting[0]:emitting[1] + 1] = 1
    return labels


def solid_fold(shape, fold, rows, receiving, emitting, spot_from_fold):
    """A vertical 3D fold at x = ``fold`` in a frame of ``shape``: cell 0 the columns
    ``receiving`` left of it, cell 1 ``emitting`` right of it (both over ``rows``), the spot
    ``spot_from_fold`` px right of the fold mid-rows, and its frame (the 3D kernel's light on
    the left facet). Returns labels, spot, frame and the fold's line (the frame's height)."""
    labels = np.full(shape, -1)
    labels[rows[0]:rows[1], receiving[0]:receiving[1]] = 0
    labels[rows[0]:rows[1], emitting[0]:emitting[1]] = 1
    y, x = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    middle = (rows[0] + rows[1] - 1) / 2
    spot = np.array([fold + spot_from_fold, middle])
    frame = np.where(x < fold, solid(np.maximum(fold - x, 1e-9), spot_from_fold, y - middle), 0.0)
    half = shape[0] / 2
    line = ft.FoldLine(np.array([fold, middle]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]), -half, half)
    return labels, spot, frame, line


def assert_double_integrals(found, labels, fold, spot, bq, rel):
    """Cells 0 and 2 receive from cell 1 (its pixels' distances from the fold ``bq``, as
    taken): each correction in ``found`` against the kernel's double integral over the two
    cells' pixels, within ``rel``; returns the two ratios to the spot's light."""
    ey = np.nonzero(labels == 1)[0]
    ratios = []
    for i in (0, 2):
        ry, rx = np.nonzero(labels == i)
        point = solid(fold - rx, spot[0] - fold, ry - spot[1]).sum()
        spread = np.mean([solid(fold - rx, b, ry - v).sum() for b, v in zip(bq, ey)])
        assert 1.0 + found[(i, 1)] / point == pytest.approx(spread / point, rel=rel)
        ratios.append(spread / point)
    return ratios


@pytest.mark.parametrize("spot_x", [52.0, 55.0, 59.0])
def test_a_flatland_cells_light_across_the_fold_is_the_kernels_double_integral(spot_x):
    """Frame of a spot at b_k across the fold: the kernel on the receiving facet. The cell's
    light spread over its pixels, against its spot's, is the ratio of the kernel's sums over
    the two cells' pixels (within 3%: bilinear samples of the frame): 0.4-1.6 here."""
    labels = cells_across()
    x = np.arange(COLS, dtype=float)
    a = np.where(x < FOLD, FOLD - x, 0.0)
    bk = spot_x - FOLD
    frame = np.broadcast_to(np.where(x < FOLD, flatland(np.maximum(a, 1e-9), bk), 0.0), (ROWS, COLS)).copy()
    spots = np.array([[45.5, 11.5], [spot_x, 11.5]])
    cells = ft._cell_pixels(labels, 2)
    line = vertical_line()
    found = ft.cross_fold_corrections(line, cells, spots, spacing=12.0, frame_of=lambda k: frame, flatland=True,
                                      placement=0.0, min_ratio=1.0)
    assert set(found) == {(0, 1)}
    ap = FOLD - np.arange(42, 50.0)
    bq = np.maximum(np.arange(51, 63.0) - FOLD, bk / ft.MAX_SCALE)
    point = flatland(ap, bk).sum()
    spread = flatland(ap[:, None], bq[None, :]).sum(axis=0).mean()
    expected = spread / point
    got = 1.0 + found[(0, 1)] / (ROWS * point)
    assert got == pytest.approx(expected, rel=0.03)
    assert 0.3 < expected < 2.0
    # the cell's light spread as the far light falls off toward the fold (a V): the kernel's sums
    # over the emitting pixels weighted by it
    valley = np.broadcast_to(np.abs(x - FOLD), (ROWS, COLS))
    weighted = ft.cross_fold_corrections(line, cells, spots, spacing=12.0, frame_of=lambda k: frame, flatland=True,
                                         placement=0.0, min_ratio=1.0, emission=valley)
    sums = flatland(ap[:, None], bq[None, :]).sum(axis=0)
    expected_weighted = np.average(sums, weights=np.arange(51, 63.0) - FOLD) / point
    # (within 6%: the emitting cell's 288 pixels thinned to MAX_EMITTERS, unevenly across its columns)
    assert 1.0 + weighted[(0, 1)] / (ROWS * point) == pytest.approx(expected_weighted, rel=0.06)
    assert expected_weighted < expected                 # the pixels nearest the fold, which send most, count less
    # the fold's place uncertain by a quarter pixel: the correction of the three places nearest none
    sure = ft.cross_fold_corrections(line, cells, spots, spacing=12.0, frame_of=lambda k: frame, flatland=True,
                                     min_ratio=1.0)
    moved = [ft.cross_fold_corrections(line.shifted(t), cells, spots, spacing=12.0, frame_of=lambda k: frame,
                                       flatland=True, placement=0.0, min_ratio=1.0)[(0, 1)] for t in (-0.25, 0.0, 0.25)]
    assert (0, 1) not in sure if min(moved) < 0 < max(moved) else \
        sure[(0, 1)] == pytest.approx(min(moved, key=abs))
    # and none within a factor MIN_RATIO of the spot's
    small = ft.cross_fold_corrections(line, cells, spots, spacing=12.0, frame_of=lambda k: frame, flatland=True)
    assert ((0, 1) in small) == (abs(np.log(got)) >= np.log(ft.MIN_RATIO) + 0.05) or \
        abs(abs(np.log(got)) - np.log(ft.MIN_RATIO)) < 0.05


def test_a_3d_cells_light_across_the_fold_is_the_kernels_double_integral():
    """The same with the 3D kernel (light falls off along the fold): the spot's frame scaled
    about the fold and shifted along it stands for every point of its cell (within 3%; the
    frame reaching as far as the scaling takes the cells, as a facet's does)."""
    fold = 100.0
    labels, spot, frame, line = solid_fold((128, 201), fold, (58, 70), (90, 100), (101, 111), 8.0)
    bk = spot[0] - fold
    found = ft.cross_fold_corrections(line, ft._cell_pixels(labels, 2), np.array([[95.0, 63.5], spot]),
                                      spacing=10.0, frame_of=lambda k: frame, flatland=False, placement=0.0,
                                      min_ratio=1.0)
    ry, rx = np.nonzero(labels == 0)
    ey, ex = np.nonzero(labels == 1)
    point = solid(fold - rx, bk, ry - spot[1]).sum()
    bq = np.maximum(ex - fold, bk / ft.MAX_SCALE)
    spread = np.mean([solid(fold - rx, b, ry - v).sum() for b, v in zip(bq, ey)])
    assert 1.0 + found[(0, 1)] / point == pytest.approx(spread / point, rel=0.03)
    # a cell across the fold that does not touch it gets its share too (the light a point sends
    # to the facet across is the same wherever the point lies: the spot's excess straight across
    # is the cells' beyond), and so does one whose frame reaches past the line's end, over the
    # pixels whose scaled points lie within it (beyond, the frame shows another face, or nothing)
    labels[58:70, 79:90] = 2
    cells, spots = ft._cell_pixels(labels, 3), np.array([[95.0, 63.5], spot, [84.5, 63.5]])
    short = ft.FoldLine(line.centre, line.direction, line.normal, -64.0, 12.0)      # ends 6.5 px past the cells
    for fold_line in (line, short):
        found = ft.cross_fold_corrections(fold_line, cells, spots, spacing=10.0, frame_of=lambda k: frame,
                                          flatland=False)
        assert set(found) == {(0, 1), (2, 1)}
        ratios = assert_double_integrals(found, labels, fold, spot, bq, rel=0.05)
        # the spot 8 px from the fold, its cell's pixels 1-11: the near cell gains, the far one loses
        assert ratios[0] > 1.1 and ratios[1] < 0.9
    lit = np.ones(frame.shape, bool)
    assert ft.is_flatland(line, frame, spot, lit) is False
    flat = np.broadcast_to(frame[int(spot[1])], frame.shape)
    assert ft.is_flatland(line, flat, spot, lit) is True
    assert ft.is_flatland(line, flat, spot, labels >= 0) is None      # nothing lit far enough along


def test_receivers_scaled_off_the_facet_are_read_by_the_kernels_symmetry():
    """The facet across the fold ends 30 px from it (past that the frame is dark, as past a
    scene's rim): the emitting pixels nearest the fold scale the receiving pixels off it.
    Their light is read where the kernel's symmetry puts it (K(a, b, t) = K(b, a, t)): the
    cell touching the fold and the one past it both within 3% of the double integrals. (Such
    pairs left out of the ratio took the far cell's 20% high, 0.88 against 0.73; counted as
    none, 20% low, 0.59.)"""
    fold = 100.0
    labels, spot, frame, line = solid_fold((128, 201), fold, (58, 70), (90, 100), (101, 111), 8.0)
    labels[58:70, 79:90] = 2
    cells, spots = ft._cell_pixels(labels, 3), np.array([[95.0, 63.5], spot, [84.5, 63.5]])
    facet = np.zeros(frame.shape, bool)
    facet[:, 70:] = True
    frame = frame * facet
    found = ft.cross_fold_corrections(line, cells, spots, spacing=10.0, frame_of=lambda k: frame, flatland=False,
                                      facet=facet, min_ratio=1.0)
    bq = np.maximum(np.nonzero(labels == 1)[1] - fold, max((spot[0] - fold) / ft.MAX_SCALE, ft.NEAR_PX))
    expected = assert_double_integrals(found, labels, fold, spot, bq, rel=0.03)
    assert expected[0] > 1.4 and expected[1] < 0.8


def test_a_large_cells_pixels_binned_give_the_kernels_double_integral(monkeypatch):
    """Cells of 1200 px (past ft.EXACT_PIXELS) are binned by their distance from the fold
    (ft.quadrature: the bins' weights are the pixels' counts and their points the pixels'
    means), and the correction stays the kernel's double integral: within 3% of it, and
    within 1% of every pixel taken (the spot's 3D frame as above, on a frame as far as the
    scaling reaches)."""
    fold = 300.0
    labels, spot, frame, line = solid_fold((480, 601), fold, (220, 260), (270, 300), (301, 331), 8.0)
    bk = spot[0] - fold
    cells = ft._cell_pixels(labels, 2)
    points, weights, bins = ft.quadrature(line, cells[1])
    assert len(points) < len(cells[1]) // 4 and weights.sum() == len(cells[1])
    assert np.allclose(weights @ points / weights.sum(), cells[1].mean(axis=0))
    assert np.array_equal(np.bincount(bins), weights)
    small = cells[1][:ft.EXACT_PIXELS]
    assert np.array_equal(ft.quadrature(line, small)[0], small)
    assert len(ft.quadrature(line, cells[1], count=40)[0]) <= 40

    def corrected():
        return ft.cross_fold_corrections(line, cells, np.array([[290.0, 240.0], spot]), spacing=30.0,
                                         frame_of=lambda k: frame, flatland=False)[(0, 1)]

    binned = corrected()
    monkeypatch.setattr(ft, "EXACT_PIXELS", 10 ** 6)
    every = corrected()
    ry, rx = np.nonzero(labels == 0)
    ey, ex = np.nonzero(labels == 1)
    point = solid(fold - rx, bk, ry - spot[1]).sum()
    bq = np.maximum(ex - fold, max(bk / ft.MAX_SCALE, ft.NEAR_PX))
    spread = np.mean([solid(fold - rx, b, ry - v).sum() for b, v in zip(bq, ey)])
    assert 1.0 + binned / point == pytest.approx(spread / point, rel=0.03)
    assert binned == pytest.approx(every, rel=0.01)


def test_the_line_is_moved_onto_the_valley_floor_and_turned_along_it():
    """Far light with a valley whose floor runs from x = 50.3 to 51.1 down 96 rows: a line
    fitted to barrier pixels a pixel off is moved and turned onto it (within 0.1 px)."""
    rows = 96
    y, x = np.mgrid[0:rows, 0:COLS].astype(float)
    floor = 50.3 + 0.8 * y / (rows - 1)
    rows_floor = floor[:, 0]
    light = np.minimum(np.abs(x - floor), 6.0) + 1.0
    barriers = np.zeros((rows, COLS), bool)
    barriers[np.arange(rows), np.round(rows_floor + 0.6).astype(int)] = True
    lines = ft.fold_lines(barriers, spacing=8.0)
    assert len(lines) == 1
    moved, _ = ft.valley_floor(lines[0], light, spacing=8.0)
    for row in (0.0, 48.0, 95.0):
        u = (row - moved.centre[1]) / moved.direction[1]
        at = moved.centre + u * moved.direction
        assert at[0] == pytest.approx(50.3 + 0.8 * row / (rows - 1), abs=0.1)


def test_folds_meeting_at_a_corner_are_a_line_each_and_a_short_stray_is_none():
    """A box's corner: three folds meet at a point, each a line of its own; a ridge 4 px long
    and two folds' pixels in one row (a line through them has gaps) are no line."""
    barriers = np.zeros((80, 80), bool)
    barriers[10:41, 40] = True                          # up from the corner
    i = np.arange(40, 70)
    barriers[i, i] = True                               # down to the right
    barriers[i, 80 - i] = True                          # down to the left
    barriers[5, 5:9] = True                             # a stray ridge 4 px long
    lines = ft.fold_lines(barriers, spacing=10.0)
    assert len(lines) == 3
    directions = sorted(round(float(abs(line.direction[0])), 2) for line in lines)
    assert directions == pytest.approx([0.0, np.sqrt(0.5), np.sqrt(0.5)], abs=0.02)
    assert all(line.u1 - line.u0 >= 29 for line in lines)


def test_corrections_carry_through_the_further_bounces():
    """``T + T D^-1 delta``: the light added to cell i is sent on as beam i's spot's is."""
    rng = np.random.default_rng(1)
    T = np.eye(5) + 0.05 * rng.random((5, 5))
    rows, cols, values = np.array([1, 3]), np.array([2, 2]), np.array([0.01, -0.02])
    delta = np.zeros((5, 5))
    delta[rows, cols] = values
    expected = T + T @ np.diag(1 / np.diag(T)) @ delta
    assert np.allclose(ft.apply_corrections(T.copy(), rows, cols, values), expected)


def test_a_cell_whose_spot_hugs_the_fold_keeps_its_nearer_pixels():
    """A dense scan's crease cell: its spot 1.5 px from a 3D fold, its pixels 0.5-5.5 px from
    it. Against the kernel's exact double integral over the pixels where they are (no
    distance taken up to any floor), the ratio to the cell straight across is within 11% and to
    the cell beyond it within 5% (0.63 against 0.70, 1.36 against 1.32). With every pixel
    nearer the fold than 1.5 px taken at 1.5 px, as before, the cell read as lying beyond its
    spot: 0.60 and 1.43, 15% and 9% off."""
    fold = 100.5
    labels, spot, frame, line = solid_fold((128, 201), fold, (58, 70), (95, 101), (101, 107), 1.5)
    labels[58:70, 85:95] = 2
    cells = ft._cell_pixels(labels, 3)
    found = ft.cross_fold_corrections(line, cells, np.array([[92.0, 63.5], spot, [88.0, 63.5]]), spacing=6.0,
                                      frame_of=lambda k: frame, flatland=False, placement=0.0, min_ratio=1.0)
    ey, ex = np.nonzero(labels == 1)
    for i, rel in ((0, 0.11), (2, 0.05)):
        ry, rx = np.nonzero(labels == i)
        point = solid(fold - rx, spot[0] - fold, ry - spot[1]).sum()
        exact = np.mean([solid(fold - rx, b, ry - v).sum() for b, v in zip(ex - fold, ey)]) / point
        assert 1.0 + found[(i, 1)] / point == pytest.approx(exact, rel=rel)


def test_a_crease_cell_a_pixel_over_the_fold_is_still_a_cell_of_its_side():
    """A dense scan's crease cell: its spot 1.4 px from the fold keeps its own disc, and a
    fifth or more of its pixels lie over the line (the 4x box lattice's 507 beams: 22-28%).
    It is a cell of its side, so it sends and receives corrections (at 0.8 of its pixels it
    was none, its bounces 2-3 16-26% short); a cell with 9 of its 21 pixels over the line is
    none (any majority was worse). The kernel's check keeps to cells with 0.8 on one side."""
    fold = 100.5
    labels, spot, frame, line = solid_fold((128, 201), fold, (58, 70), (95, 101), (101, 107), 1.5)
    labels[labels == 1] = -1
    labels[80:84, 99:104] = 1                               # 8 of 20 over the fold ...
    labels[84, 100] = 1                                     # ... and one more: 9 of 21
    labels[40:50, 101:106] = 3                              # 0 of 50
    labels[20:30, 100:106] = 4                              # 10 of 60 ...
    labels[20:24, 99] = 4                                   # ... and 4 more: 14 of 64
    cells = ft._cell_pixels(labels, 5)
    spots = np.array([[96.0, 63.5], [101.9, 82.0], [0.0, 0.0], [102.9, 44.5], [101.9, 24.5]])
    shares = ft.side_shares(line, cells, spots)
    assert shares[1] == (-1.0, pytest.approx(12 / 21)) and shares[4] == (-1.0, pytest.approx(50 / 64))
    assert ft.fold_sides(line, cells, spots) == {0: 1.0, 3: -1.0, 4: -1.0}
    assert ft.fold_sides(line, cells, spots, ft.CHECK_SHARE, shares) == {0: 1.0, 3: -1.0}


def test_the_kernels_check_takes_the_beam_behind_a_spot_that_hugs_the_fold(monkeypatch):
    """The homogeneity check on the 3D kernel's exact frames: a spot 1.2 px from the fold whose
    own light reaches over it (a Gaussian of sigma 1 px, 30 times the kernel's light beside the
    fold at its peak, as a spot's flank is) makes its frame, scaled
    about the fold for the beam behind it, miss; the next beam behind it (6 px) stands in, and
    the check holds on the exact frames (the beam 12 px away against the one at 6)."""
    fold, middle, shape = 100.0, 63.5, (128, 201)
    labels = np.full(shape, -1)
    labels[58:70, 88:100] = 0                                    # across the fold, touching it
    labels[58:70, 100:104] = 1
    labels[58:70, 104:109] = 2
    labels[58:70, 109:116] = 3
    distances = {1: 1.2, 2: 6.0, 3: 12.0}
    spots = np.array([[94.0, middle]] + [[fold + distances[k], middle] for k in (1, 2, 3)])
    y, x = np.mgrid[0:shape[0], 0:shape[1]].astype(float)

    def frame_of(k):
        frame = np.where(x < fold, solid(np.maximum(fold - x, 1e-9), distances[k], y - middle), 0.0)
        if k == 1:                                              # the spot's own light over the fold
            frame = frame + np.where(x < fold, 2.0 * np.exp(-((x - spots[1, 0]) ** 2 + (y - middle) ** 2) / 2), 0)
        return frame

    line = ft.FoldLine(np.array([fold, middle]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]), -64.0, 64.0)
    cells = ft._cell_pixels(labels, 4)
    side = {1: -1.0, 0: 1.0}
    miss = ft.homogeneity_miss(line, cells, spots, 10.0, frame_of, False, side)
    assert miss < 0.1
    monkeypatch.setattr(ft, "CHECK_NEAR_PX", 1.0)                # the hugging spot checked itself
    assert ft.homogeneity_miss(line, cells, spots, 10.0, frame_of, False, side) > ft.MAX_MISS


def test_cells_are_cut_at_a_fold_line_where_the_rows_across_stand_offset():
    """Spots 1.4 px either side of a horizontal fold (y = 20), the rows offset by half a spacing
    (an uneven scan): their Voronoi cells reach over the line, and cut_cells gives every pixel
    0.25 px or more over it to the nearest spot on its own side within a spacing; pixels nearer
    the line, past its end or with no spot on their side within a spacing, and the cells of
    spots nearer the line than CUT_SPOT_PX, keep their cells. A line not turned onto the valley
    floor (placed to half a pixel) cuts nothing."""
    from scipy.spatial import cKDTree

    height, width, fold, spacing = 40, 80, 20.0, 12.0          # the light goes on 23 px past the line's end
    above = [(x, fold - 1.4) for x in np.arange(2.0, 40.0, 8.0)]
    below = [(x, fold + 1.4) for x in np.arange(6.0, 40.0, 8.0)]
    near = [(44.0, fold + 0.6)]                                  # 0.6 px from the line: kept whole
    spots = np.array(above + below + near)
    ys, xs = np.mgrid[:height, :width]
    labels = cKDTree(spots).query(np.column_stack([xs.ravel(), ys.ravel()]))[1].reshape(height, width)
    line = ft.FoldLine(np.array([20.0, fold]), np.array([1.0, 0.0]), np.array([0.0, 1.0]), -20.0, 36.0, placement=0.05)
    cut, moved = ft.cut_cells(labels, spots, [line], spacing)
    unturned = ft.FoldLine(line.centre, line.direction, line.normal, line.u0, line.u1)
    same, none = ft.cut_cells(labels, spots, [unturned], spacing)
    assert none == 0 and np.array_equal(same, labels)       # a line only moved onto the floor cuts nothing

    d = ys - fold
    spot_side = np.sign(spots[:, 1] - fold)
    over = (xs <= 56) & (np.abs(d) >= ft.CUT_MARGIN_PX) & (labels != len(spots) - 1) & (np.sign(d) != spot_side[labels])
    expected = labels.copy()
    for side, group in ((-1, np.arange(len(above))), (1, len(above) + np.arange(len(below)))):
        sel = over & (np.sign(d) == side)
        distance, nearest = cKDTree(spots[group]).query(np.column_stack([xs[sel], ys[sel]]))
        expected[np.flatnonzero(sel.ravel())[distance <= spacing] // width,
                 np.flatnonzero(sel.ravel())[distance <= spacing] % width] = group[nearest[distance <= spacing]]
    assert moved == np.count_nonzero(expected != labels) > 20
    assert np.array_equal(cut, expected)
    tight, fewer = ft.cut_cells(labels, spots, [line], 4.5)    # a spacing of 4.5 px: only pixels with a spot that near
    went = tight != labels
    assert 0 < fewer == went.sum() < moved and np.array_equal(tight[went], cut[went])
    assert np.all(np.hypot(xs[went] - spots[tight[went], 0], ys[went] - spots[tight[went], 1]) <= 4.5)
    assert np.array_equal(cut == len(spots) - 1, labels == len(spots) - 1)   # the spot 0.6 px off: its cell kept
    loose = ft.FoldLine(line.centre, line.direction, line.normal, line.u0, line.u1, placement=0.4)
    wide, _ = ft.cut_cells(labels, spots, [loose], spacing)   # placed to 0.4 px: only pixels 0.8 px over move
    changed = wide != labels
    assert changed.any() and np.all(np.abs(d[changed]) >= 2 * 0.4) and np.array_equal(wide[changed], cut[changed])


def test_a_line_that_stops_short_of_the_silhouette_cuts_on_to_it():
    """A crease's line found 4 px short of the light's edge (x = 56, the light ends at x = 60):
    to_lit_edge carries it on to the first pixel off the light, and cut_cells then cuts the
    cells there too (a spot 1.4 px below the fold, past the line's end, whose Voronoi cell
    reached over it). With the light going on 23 px past the end (a corner, another face),
    the line stays as found, and so do those cells; off the frame counts as off the light."""
    from scipy.spatial import cKDTree

    height, width, fold, spacing = 40, 80, 20.0, 12.0
    spots = np.array([(x, fold - 4.0) for x in np.arange(4.0, 60.0, 8.0)] + [(57.5, fold + 1.4)]
                     + [(x, fold + 4.0) for x in np.arange(8.0, 56.0, 8.0)])
    ys, xs = np.mgrid[:height, :width]
    labels = cKDTree(spots).query(np.column_stack([xs.ravel(), ys.ravel()]))[1].reshape(height, width)
    lit = xs < 60
    line = ft.FoldLine(np.array([20.0, fold]), np.array([1.0, 0.0]), np.array([0.0, 1.0]), -20.0, 36.0, placement=0.05)
    carried = ft.to_lit_edge(line, lit, spacing)
    assert carried.u1 == 39.5 and carried.u0 == -21.0                # x = 59.5 (pixel 60) off the light, x = -1 off the frame
    assert ft.to_lit_edge(line, np.ones_like(lit), spacing).u1 == line.u1   # light 23 px on: no silhouette near
    assert ft.to_lit_edge(line, lit, 3.0).u1 == line.u1                     # the edge farther than the reach

    edge = np.where(lit, labels, -1)
    low = 7                                                           # the spot 1.4 px below, past the line's end
    assert spots[low, 0] == 57.5 and np.any((edge == low) & (ys < fold - ft.CUT_MARGIN_PX))   # its cell reaches over
    cut, moved = ft.cut_cells(edge, spots, [line], spacing)
    over = (edge == low) & (ys <= fold - ft.CUT_MARGIN_PX)
    assert moved >= over.sum() > 0 and np.all(spots[cut[over], 1] < fold)   # all now the spots above
    went = cut != edge
    d = ys - fold
    assert np.array_equal(cut[~lit], edge[~lit]) and np.all(np.abs(d[went]) >= ft.CUT_MARGIN_PX)
    assert np.all(np.sign(spots[cut[went], 1] - fold) == np.sign(d[went]))    # each to a spot on its own side
    short, _ = ft.cut_cells(labels, spots, [line], spacing)          # the whole frame lit: the light on past the end
    assert np.array_equal(short[over], labels[over])                  # past the line's end: not cut


def test_a_stretch_off_the_floor_at_the_line_s_end_does_not_turn_it():
    """The valley of the test above with its first 12 rows' floor 1.4 px off (where a fold meets
    the silhouette): the line still follows the floor over the rest, within 0.1 px; a least
    squares fit through the stretches' floors was 0.22 px off at row 24 (0.11 at the far end)."""
    rows = 96
    y, x = np.mgrid[0:rows, 0:COLS].astype(float)
    floor = 50.3 + 0.8 * y / (rows - 1)
    light_floor = floor + np.where(y < 12, 1.4, 0.0)
    light = np.minimum(np.abs(x - light_floor), 6.0) + 1.0
    barriers = np.zeros((rows, COLS), bool)
    barriers[np.arange(rows), np.round(floor[:, 0]).astype(int)] = True
    moved, _ = ft.valley_floor(ft.fold_lines(barriers, spacing=8.0)[0], light, spacing=8.0)
    for row in (24.0, 48.0, 95.0):
        at = moved.centre + (row - moved.centre[1]) / moved.direction[1] * moved.direction
        assert at[0] == pytest.approx(50.3 + 0.8 * row / (rows - 1), abs=0.1)
