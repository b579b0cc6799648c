"""The light a cell sends across a concave fold, from the frames (build-isf; decompose applies it).

T's column k is the light of beam k's *spot*: a point. A photo lights the whole of cell k,
and the sample-level recursion uses column k for all of it. Where the light between two
cells varies smoothly with the point it leaves from, the spot stands for its cell well
enough. Across a concave fold it does not: two facets that meet at a fold light each
other the more, the nearer the fold both points are (the kernel between a point at
distance ``a`` from the fold on one facet and one at ``b`` on the other is homogeneous of
degree -1 in flatland, -2 in 3D: ``K(t a, t b) = K(a, b) / t^gamma``), so a spot 12 px from
the fold stands for the cell's pixels at 1 px from it badly. A point quadrature then takes
the light between the two cells next to a fold at 0.4-1.2 of the cell-to-cell light
(the same for any fold angle within 10%), by how far each spot lies from the fold; the
sample-level error follows, and so does which of two scans is better: on the M's 2x
lattice, scans of 58 and 77 beams whose spots fell 12 px from a fold on one side and 4 px on
the other were worse than 48 (docs/fullres.md, "Across a fold").

The frames know the kernel. Frame k shows, on the facet across the fold, the light of a
point at ``b_k`` reaching every pixel there, and by the kernel's homogeneity a point at
any ``b`` on the same line across the fold gives the same light scaled about the fold by
``b_k / b`` (and in 3D shifted along it): ``K(p, q) = (b_k / b_q)^gamma F_k(M_q(p))``, with
``M_q(p) = f_k + (b_k / b_q) (p - f_q)``, ``f`` each point's foot on the fold. So the light
cell k sends to cell i across the fold, spread over cell k's pixels, is the mean over q in
cell k of ``sum_{p in i} K(p, q)``, and the point's is ``sum_{p in i} F_k(p)``. Their
difference, in T's units, is :func:`cross_fold_corrections`'s ``delta[i, k]``; decompose
adds it to the split's T and carries it through T's further bounces
(:func:`apply_corrections`).

Folds: the barrier lines of :mod:`ilt.isf.folds`, as straight segments
(:func:`fold_lines`), each moved and turned onto the far light's valley floor to a tenth
of a pixel (:func:`valley_floor`): the correction is as sensitive to the fold's place as
to the spots' (half a pixel moved the M's figures by a third). Flatland or 3D
(:func:`is_flatland`): a simulator's flatland frames are the same along the fold, a 3D
scene's light falls off along it. ``q`` nearer the fold than ``b_k / MAX_SCALE`` is taken
at that distance: the mapped pixels would leave the facet.

Each cell's light is taken as spread over its pixels as the far light (:mod:`ilt.isf.folds`)
is: it falls off toward a concave fold (a point there sees the other facet at a grazing angle,
and less of a room's light), so the pixels nearest the fold, which send the most across it,
hold the least. Spread evenly instead, the correction overshot: under a path tracer's noise
the M's projector bounce 2 fell to 0.074 at 48 beams and 0.092 at 96, a denser scan worse
(docs/fullres.md, "Across a fold").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse
from scipy.ndimage import map_coordinates
from scipy.stats import median_abs_deviation, siegelslopes

#: barrier pixels within this many px of a line belong to it (:func:`fold_lines`), in a run
#: along it without a gap of more than this many px
LINE_TOLERANCE, MAX_GAP_PX = 1.0, 3.0
#: a fold line spans at least this many spot spacings, or this many px if fewer (a flatland
#: scene's frames are a few rows high)
MIN_LINE_SPACINGS, MIN_LINE_PX = 2.0, 16.0
#: the far light's valley floor (:func:`valley_floor`) is looked for this many spot spacings
#: (3 to 8 px) either side of the barrier line, along stretches of this many spacings
VALLEY_REACH, FLOOR_SPACINGS = 0.5, 1.0
#: a line is turned onto the floors only where it holds this many stretches
MIN_STRETCHES = 4
#: an emitting spot lies within this many spot spacings of the fold, its cell touching it
EMITTER_SPACINGS = 3.0
#: a cell touches a fold when a pixel of it lies within this many px of the line ...
TOUCH_PX = 2.0
#: ... and at least this share of its pixels lie on one side (the kernel's check,
#: :func:`homogeneity_miss`, on :data:`CHECK_SHARE`). 0.6 since: a dense scan's spot 1.4 px from a
#: crease keeps its own disc of 3 px (:func:`ilt.isf.folds.fold_cells`), a pixel or two over it,
#: and where the spots across stand offset along it (an uneven scan: the 4x box lattice's 363, 507
#: and 675 beams) such a cell held 22-28% of its pixels over the line; at 0.8 it neither sent nor
#: received a correction, its bounces 2-3 16-26% short (noise-free: 0.0479 / 0.0409 / 0.0378 ->
#: 0.0427 / 0.0371 / 0.0354; every other scan, and the noisy sweep, the same to 0.0001; 0.5, none,
#: 0.0376 at 507; its pixels over the line left out of the correction, worse than 0.8: they lie at
#: the crease, where the light across is strongest)
SIDE_SHARE = 0.6
#: the cells the kernel's homogeneity is checked on (:func:`homogeneity_miss`) have this share of
#: their pixels on one side: with the cells a pixel over the line the check missed by more (the 4x
#: box lattice's 507 beams at 2e4 e-: 0.33 -> 0.49, and 0.47 -> 0.52 on another draw, over
#: :data:`MAX_MISS`, which took every correction of that crease away, 3.4% worse)
CHECK_SHARE = 0.8
#: the emitting points are scaled to the spot by at most this factor (nearer the fold: there)
MAX_SCALE = 8.0
#: at a 3D fold, emitting pixels nearer it than this (px) are taken at this distance: the
#: scaling's factor grows as 1 / distance there, its square with it, and the fold's place is
#: known to a quarter pixel and a pixel's light spread over one, so a pixel half a pixel from
#: the fold came out 3-4 times the renderer's light (a box of 48 beams with its surface in
#: patches of 1.25 px, before the symmetric read and the factor MIN_RATIO). 0.75 px since:
#: at 1.5 px a cell whose spot stands 1.2-1.8 px from a crease read as lying wholly beyond its
#: spot, its pixels nearer the fold, which send the most to the cell straight across, sending
#: what the spot does; the 4x box lattice's 192 beams (cells 9 px across) were 23% worse than
#: with no transfer, the pixels within 2 px of a crease 4-12% short of their bounces 2-3
#: (noise-free). At 0.75 px every scan of that lattice gains 1.7-17% noise-free, the noisy sweep's
#: box within 0.4% (docs/fullres.md "Near the crease")
NEAR_PX = 0.75
#: the light along the fold, 1.5-2.5 spot distances from the spot's foot against within half
#: of one: above this share the frames are flatland (constant along the fold)
FLATLAND_SHARE = 0.6
#: pixels of a cell sampled at most, as emitters and as receivers
MAX_EMITTERS, MAX_RECEIVERS = 256, 2000
#: a correction's ratio to the point's light is kept within [1 / CAP, CAP]
CAP = 4.0
#: a correction is made only where the cell's light and its spot's differ by this factor or
#: more: within it the cell's own light, which is not spread evenly over it (less of a room's
#: light reaches into a fold), is as far from the even spread as that is from the spot (on the
#: M at 16 beams, spots 10.5 and 13.5 px from a fold, corrections of +11% and -4% doubled its
#: room photo's bounce 2 at the samples, 0.018 -> 0.040; 1.5 gave the noisy M's 96 beams 0.0585
#: against 0.0514 at 1.2; a share faded in from 1.1, or up to 1.3, instead of the threshold:
#: up to 10% and 3% worse on the noisy sweeps, docs/fullres.md "A correction faded in")
MIN_RATIO = 1.2
#: how far (px) the fold's place is uncertain: the far light's floor on noisy frames, against the
#: M's exact folds (:func:`cross_fold_corrections`)
PLACEMENT_PX = 0.25
#: a pixel this far (px) or farther over a fold line from its cell's spot goes to the nearest
#: spot on its side (:func:`cut_cells`). The Voronoi cells of spots whose rows stand offset
#: along a crease (an uneven scan: the 4x box lattice's 507 and 675 beams) reach a pixel or two
#: over it, and those pixels took the other face's light: noise-free, 0.0352 / 0.0331 ->
#: 0.0339 / 0.0321 with the limits below. Margins measured before the limits (least squares,
#: every line, any spot): 0.25 px 0.0334 / 0.0328, 0.5 px 0.0338 / 0.0328, 0 (which cuts at
#: spots on the line) 0.0369 / 0.0326 and 0.0346 at 432 beams, which 0.25 left as it was
CUT_MARGIN_PX = 0.25
#: ... or this many times the line's placement error where that is more (:func:`cut_cells`): the
#: 2x box lattice's 432 beams at 2e4 e- read floors scattered by a pixel along its creases
#: (placement 0.17-0.32 px, one draw), the 4x lattice's 507 beams 0.1 px (0.014-0.028)
PLACEMENT_SPREAD = 2.0
#: ... and only cells whose spot stands this far (px) or farther from the line are cut, or take
#: the pixels: a spot nearer has its own light over the line. refine puts beams there (a fold's
#: pair), and at the box's central corner a cell whose spot stood 0.4 px from one crease gave its
#: pixels over it to a spot 9 px away (refine's +24 beams on the 4x box lattice 2.5-6% worse on
#: two draws of three when the spots were held to 0.25 px, as the pixels)
CUT_SPOT_PX = 1.0
#: a line's kernel is checked on this many pairs of beams (:func:`homogeneity_miss`), and the
#: line is no fold of two planes where it misses by more than this share
CHECKS, MAX_MISS = 6, 0.5
#: the check's front beam stands at least this far (px) from the fold: a spot nearer has its own
#: light over it (its disc is 3 px, :func:`ilt.isf.folds.fold_cells`), and its frame scaled 6-8
#: times about the fold read 1.5-2.3x what the beam behind sends (the 4x box lattice's 147 beams,
#: spots 1.6 px from the centre crease: it missed by 0.64 / 0.74 on two draws of three at 2e4 e-,
#: over MAX_MISS, and went uncorrected). The next beam behind such a spot, within half a spacing
#: along, stands in for it: the crease's misses 0.03-0.24, its 48 / 75 / 147 beams 18 / 8 / 8%
#: better, no other scan of the lattice worse (docs/fullres.md, "The check's front beam")
CHECK_NEAR_PX = 2.0
#: at a 3D fold, a cell touching it sends to every cell across it with a pixel within this
#: many spot spacings of the line and its spot within as many along it: a spot nearer the fold
#: than its cell's pixels sends too much to the cell straight across and too little to those
#: beyond it (the light a point sends to the facet across is the same wherever it lies), so the
#: cells touching the fold on the other side alone took only half of the correction (the box's
#: 108 beams, noise-free, against the renderer's T with each cell's light spread evenly: 0.0593
#: with them alone, 0.0563 with these, 0.0528 exact; 5 and 100 spacings as 3)
RECEIVER_SPACINGS = 3.0
#: a line's kernel is checked on beams 1.5 to this many times as far from it as the beam in
#: front (flatland: 4; at 3D folds as far as the scaling reaches, :data:`MAX_SCALE`: the box's
#: 147 and 192 beams have their second row 6 times as far from each crease as the first)
CHECK_REACH_FLATLAND = 4.0
FILE = "fold_transfer.npz"


@dataclass(frozen=True)
class FoldLine:
    """A straight fold in the frame: ``centre`` (x, y), unit ``direction`` and ``normal``,
    and its extent ``u0 .. u1`` along the direction from the centre (px). ``placement``: how
    far (px) its place is uncertain where it was turned onto the valley floor (the standard
    error of the floors' fit, :func:`valley_floor`), else infinite."""

    centre: np.ndarray
    direction: np.ndarray
    normal: np.ndarray
    u0: float
    u1: float
    placement: float = float("inf")

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(n,) signed distance (px) of (n, 2) points from the line, along its normal."""
        return (np.asarray(points, float) - self.centre) @ self.normal

    def along(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points, float) - self.centre) @ self.direction

    def shifted(self, offset: float) -> FoldLine:
        """The line moved ``offset`` px along its normal."""
        return FoldLine(self.centre + offset * self.normal, self.direction, self.normal, self.u0, self.u1,
                        self.placement)


def _longest_run(along: np.ndarray) -> np.ndarray:
    """Indices into ``along`` (positions on a line) of its longest run without a gap of
    :data:`MAX_GAP_PX`."""
    order = np.argsort(along)
    runs = np.split(order, np.flatnonzero(np.diff(along[order]) > MAX_GAP_PX) + 1)
    return max(runs, key=len)


def fold_lines(barriers: np.ndarray, spacing: float, seed: int = 0, tries: int = 300) -> list[FoldLine]:
    """The straight segments of a barrier mask (H, W) bool, longest first: repeatedly, of the
    lines through two barrier pixels (a fixed-seed sample of pairs), the one with the most
    barrier pixels within :data:`LINE_TOLERANCE` px of it in one run without a gap of
    :data:`MAX_GAP_PX` (a line through two folds' pixels in one row is none), fitted to
    them by least squares and taken out, while that spans :data:`MIN_LINE_SPACINGS` spot
    spacings (or :data:`MIN_LINE_PX`). Where folds meet (a box's corner) each arm is a line
    of its own."""
    ys, xs = np.nonzero(barriers)
    points = np.column_stack([xs, ys]).astype(np.float64)
    need = min(MIN_LINE_SPACINGS * spacing, MIN_LINE_PX)
    rng = np.random.default_rng(seed)
    lines = []
    while len(points) >= need:
        best = None
        for a, b in rng.integers(0, len(points), size=(tries, 2)):
            step = points[b] - points[a]
            length = float(np.hypot(*step))
            if length < 3.0:
                continue
            direction = step / length
            near = np.flatnonzero(np.abs((points - points[a]) @ np.array([-direction[1], direction[0]]))
                                  <= LINE_TOLERANCE)
            run = near[_longest_run(points[near] @ direction)]
            if best is None or len(run) > len(best):
                best = run
        if best is None:
            break
        chosen = points[best]
        centre = chosen.mean(axis=0)
        direction = np.linalg.svd(chosen - centre, full_matrices=False)[2][0]
        u = (chosen - centre) @ direction
        if u.max() - u.min() + 1.0 < need - 0.5:       # (a line of pixels counts them: rounding)
            break
        lines.append(FoldLine(centre, direction, np.array([-direction[1], direction[0]]), float(u.min()) - 0.5,
                              float(u.max()) + 0.5))
        points = np.delete(points, best, axis=0)
    return lines


def _floor(ts: np.ndarray, profile: np.ndarray) -> float:
    """Where a valley profile is least: its least sample moved to the least of a parabola
    through the samples within a pixel of it (when that lies within the pixel)."""
    j = int(np.argmin(profile))
    near = np.abs(ts - ts[j]) <= 1.0 + 1e-9
    if near.sum() >= 3:
        c2, c1, _ = np.polyfit(ts[near], profile[near], 2)
        if c2 > 0 and abs(-c1 / (2 * c2) - ts[j]) <= 1.0:
            return float(-c1 / (2 * c2))
    return float(ts[j])


def valley_floor(line: FoldLine, light: np.ndarray, spacing: float) -> tuple[FoldLine, float]:
    """``line`` moved and turned onto the far light's valley floor, and its move (px) at its
    centre: along stretches of :data:`FLOOR_SPACINGS` spot spacings (4 px at least), the light
    averaged along the stretch at offsets across the line (tenths of a pixel, within
    :data:`VALLEY_REACH` spacings), and where it is least (:func:`_floor`); a line fitted
    through those floors by repeated medians (a line of fewer than :data:`MIN_STRETCHES` only
    moved, to its whole length's floor: two or three noisy floors would turn it). The barrier pixels wander by a
    pixel with the noise and the valley test's smoothing: a line fitted to them was 0.7 px
    askew over 32 px on the noisy M. (Where two lines fitted to the valley's arms meet was
    tried first: 0.3 px off on noise-free frames, where this is within 0.1.)"""
    light = np.asarray(light, np.float64)
    reach = float(np.clip(VALLEY_REACH * spacing, 3.0, 8.0))
    stretches = int((line.u1 - line.u0) // max(4.0, FLOOR_SPACINGS * spacing))
    # a line of fewer stretches is moved, not turned: two or three noisy floors would turn it
    edges = np.linspace(line.u0, line.u1, stretches + 1) if stretches >= MIN_STRETCHES else \
        np.array([line.u0, line.u1])
    ts = np.arange(-reach, reach + 1e-9, 0.1)
    centres, floors = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        us = np.arange(a + 0.5, b, 1.0)
        if us.size == 0:
            continue
        points = line.centre + us[None, :, None] * line.direction + ts[:, None, None] * line.normal
        profile = map_coordinates(light, [points[..., 1].ravel(), points[..., 0].ravel()], order=1,
                                  mode="nearest").reshape(len(ts), len(us)).mean(axis=1)
        floor = _floor(ts, profile)
        if abs(floor) <= 1.5:
            centres.append(0.5 * (a + b))
            floors.append(floor)
    if not floors:
        return line, 0.0
    centres, floors = np.array(centres), np.array(floors)
    # repeated medians (Siegel): a stretch at a fold's end, where it meets the silhouette or another
    # fold, can read a floor 1-1.4 px off, and least squares turned the whole line by it
    placement = float("inf")
    if len(centres) >= MIN_STRETCHES:
        slope, offset = siegelslopes(floors, centres)
        placement = float(median_abs_deviation(floors - slope * centres - offset, scale="normal")
                          / np.sqrt(len(floors)))
    else:
        slope, offset = 0.0, float(np.mean(floors))
    direction = line.direction + slope * line.normal
    direction /= np.hypot(*direction)
    normal = np.array([-direction[1], direction[0]])
    if normal @ line.normal < 0:
        normal = -normal
    return FoldLine(line.centre + offset * line.normal, direction, normal, line.u0, line.u1, placement), \
        float(offset)


def floor_lines(barriers: np.ndarray, light: np.ndarray, spacing: float) -> list[tuple[FoldLine, float]]:
    """The barriers' fold lines (:func:`fold_lines`), each on the far light's valley floor, and
    its move there (:func:`valley_floor`). build-isf finds them once: its cells are cut at them
    (:func:`cut_cells`) and their light across corrected (:func:`fold_corrections`)."""
    return [valley_floor(line, light, spacing) for line in fold_lines(barriers, spacing)]


def to_lit_edge(line: FoldLine, lit: np.ndarray, reach: float) -> FoldLine:
    """``line`` with each end carried on to the edge of the ``lit`` mask (H, W bool) where
    that edge lies within ``reach`` px of it along the line (walked in half pixels; the first
    pixel off the mask or the frame ends it), else as it was: a crease runs on to the
    silhouette, where its valley fades (fewer far beams light it) and the line found on it
    stops short. On the 4x box lattice under a path tracer's noise (16 samples), refine's
    72 beams put a pair 1-2 px from the crease 3 px past the line's end: the cells there
    straddled it, uncut, and the scan's mean error was 0.1120, no better than its 48-beam base
    (0.1126); carried on, 0.1052. A line that ends inside the light (at a corner where three
    faces meet, the third face's pixels lie beyond it) stays as found."""
    height, width = lit.shape
    ends = []
    for end, sign in ((line.u0, -1.0), (line.u1, 1.0)):
        for step in np.arange(0.5, reach + 0.5, 0.5):
            x, y = line.centre + (end + sign * step) * line.direction
            i, j = int(round(float(y))), int(round(float(x)))
            if not (0 <= i < height and 0 <= j < width and lit[i, j]):
                end += sign * step
                break
        ends.append(end)
    return FoldLine(line.centre, line.direction, line.normal, ends[0], ends[1], line.placement)


def cut_cells(labels: np.ndarray, spots: np.ndarray, lines: list[FoldLine], spacing: float,
              margin: float = CUT_MARGIN_PX) -> tuple[np.ndarray, int]:
    """The cells (H, W labels, -1 outside) cut at the fold ``lines`` turned onto the valley
    floor (:func:`valley_floor`; a line only moved, through fewer than :data:`MIN_STRETCHES`
    floors, cuts none: on the 4x box lattice's 48 beams at 2e4 e- such a line lay half a pixel
    off): a lit pixel within a line's extent that lies ``margin`` px or more over it from its
    cell's spot, or :data:`PLACEMENT_SPREAD` times the line's ``placement`` where that is more
    (the spot as far from it too, and :data:`CUT_SPOT_PX` at least, within the extent), goes to
    the nearest such spot on its side, if one lies within ``spacing`` (the spots' median
    spacing) of it: past a silhouette the nearest could be 35 px away. A line's extent is
    first carried on to the lit edge within ``spacing`` of its ends (:func:`to_lit_edge`,
    the cells' lit pixels). Returns the labels (a
    copy) and how many pixels moved. The barriers (:func:`ilt.isf.folds.fold_cells`) end the
    cells only where they close a region, and the valley test's ridge wanders by a pixel; the
    line on the valley floor is straight and, on dense scans, placed to a few hundredths of a
    pixel (:data:`PLACEMENT_SPREAD`)."""
    from scipy.spatial import cKDTree

    out = labels.copy()
    flat = out.reshape(-1)
    lit = np.flatnonzero(flat >= 0)
    width = labels.shape[1]
    xy = np.column_stack([lit % width, lit // width]).astype(np.float64)
    spots = np.asarray(spots, np.float64)
    moved = 0
    lit_mask = labels >= 0
    for line in lines:
        if not np.isfinite(line.placement):
            continue
        line = to_lit_edge(line, lit_mask, spacing)
        reach = max(margin, PLACEMENT_SPREAD * line.placement)
        spot_d, spot_u = line.distance(spots), line.along(spots)
        d, u = line.distance(xy), line.along(xy)
        own = flat[lit]
        clear = np.abs(spot_d) >= max(reach, CUT_SPOT_PX)
        over = (u >= line.u0) & (u <= line.u1) & (np.abs(d) >= reach) & (np.sign(d) != np.sign(spot_d[own])) \
            & clear[own] & (spot_u[own] >= line.u0) & (spot_u[own] <= line.u1)
        for side in (-1.0, 1.0):
            pixels = np.flatnonzero(over & (np.sign(d) == side))
            mine = np.flatnonzero((np.sign(spot_d) == side) & clear)
            if pixels.size and mine.size:
                near, nearest = cKDTree(spots[mine]).query(xy[pixels], distance_upper_bound=spacing)
                found = np.isfinite(near)
                flat[lit[pixels[found]]] = mine[nearest[found]]
                moved += int(found.sum())
    return out, moved


def is_flatland(line: FoldLine, frame: np.ndarray, spot: np.ndarray, lit: np.ndarray) -> bool | None:
    """Whether a frame's light across ``line`` is the same along the fold (a flatland
    scene's rendered rows) or falls off along it (3D), from the light at 0.5-1.5 spot
    distances from the fold: 1.5-2.5 spot distances along it from the spot's foot against
    within 0.5; None when the frame has not both there."""
    b = abs(float(line.distance(spot[None])[0]))
    if b < 1.0:
        return None
    ys, xs = np.nonzero(lit)
    pixels = np.column_stack([xs, ys]).astype(np.float64)
    d = line.distance(pixels) * -np.sign(line.distance(spot[None])[0])
    du = np.abs(line.along(pixels) - line.along(spot[None])[0])
    band = (d >= 0.5 * b) & (d <= 1.5 * b)
    near, far = band & (du <= 0.5 * b), band & (du >= 1.5 * b) & (du <= 2.5 * b)
    if not near.any() or not far.any():
        return None
    level = float(np.mean(frame[ys[near], xs[near]]))
    return bool(level > 0 and np.mean(frame[ys[far], xs[far]]) >= FLATLAND_SHARE * level)


def _cell_pixels(labels: np.ndarray, m: int) -> list[np.ndarray]:
    ys, xs = np.nonzero(labels >= 0)
    label = labels[ys, xs].astype(np.int64)
    order = np.argsort(label, kind="stable")
    starts = np.searchsorted(label[order], np.arange(m + 1))
    xy = np.column_stack([xs, ys]).astype(np.float64)[order]
    return [xy[starts[j]:starts[j + 1]] for j in range(m)]


def _thinned(points: np.ndarray, count: int) -> np.ndarray:
    return points if len(points) <= count else points[np.linspace(0, len(points) - 1, count).astype(np.int64)]


def side_shares(line: FoldLine, cells: list[np.ndarray], spots: np.ndarray) -> dict[int, tuple[float, float]]:
    """The cells that touch ``line`` (a pixel within :data:`TOUCH_PX` of it within its
    extent), their spot within the line's extent and on the side of most of their pixels:
    cell -> (side (+-1), the share of its pixels on that side). Past a line's end (where a
    box's folds meet) a cell across its extension is across another fold."""
    out = {}
    spot_d, spot_u = line.distance(spots), line.along(spots)
    for j, pixels in enumerate(cells):
        if len(pixels) == 0 or not line.u0 <= spot_u[j] <= line.u1:
            continue
        d, u = line.distance(pixels), line.along(pixels)
        if not np.any((np.abs(d) <= TOUCH_PX) & (u >= line.u0) & (u <= line.u1)):
            continue
        s = float(np.sign(np.median(d)))
        if s == 0 or np.sign(spot_d[j]) != s:
            continue
        out[j] = (s, float(np.mean(np.sign(d) == s)))
    return out


def fold_sides(line: FoldLine, cells: list[np.ndarray], spots: np.ndarray, share: float = SIDE_SHARE,
               shares: dict[int, tuple[float, float]] | None = None) -> dict[int, float]:
    """The cells of :func:`side_shares` (given as ``shares``, or found) with ``share`` of
    their pixels on their side: cell -> side (+-1)."""
    shares = side_shares(line, cells, spots) if shares is None else shares
    return {j: s for j, (s, q) in shares.items() if q >= share}


def light_from(line: FoldLine, frame: np.ndarray, spot: np.ndarray, points: np.ndarray, receiving: np.ndarray,
               flatland: bool, facet: np.ndarray | None = None, seen: np.ndarray | None = None,
               groups: np.ndarray | None = None, counts: np.ndarray | None = None):
    """(n,) the light points (n, 2) on the spot's side of ``line`` send to the pixels
    ``receiving`` (r, 2) across it, from the spot's ``frame`` by the kernel's homogeneity
    (module docstring): ``(b_s / b_q)^gamma`` times the frame summed over the receiving
    pixels scaled about the fold by ``b_s / b_q`` (3D: and shifted along it). Points nearer
    the fold than ``b_s / MAX_SCALE`` are taken there (3D: than :data:`NEAR_PX`, or the spot).
    ``facet`` (H, W) bool: where the receiving facet is (the scan's lit pixels, bool or
    float32); mapped pixels outside it or past the line's ends count none (3D: light past a
    fold's end is not the kernel's; but see the symmetric read below). With ``seen`` (r,)
    weights of the receiving pixels, also returns (n,) their sums over the pixels whose mapped
    point lies within the line's ends: the point's light over the same pixels, where the
    spread's is known. At a 3D fold with ``facet``, a pair whose mapped point leaves the facet
    or the line is read where the kernel's symmetry puts it (``K(b_q, b_p, t) = K(b_p, b_q,
    t)``: the frame at ``b_q b_s / b_p`` from the fold, ``t b_s / b_p`` along it, times ``(b_s
    / b_p)^2``, nearer the fold than the spot), and counts none only where that leaves them
    too (cross_fold_corrections). With
    ``groups`` (g,) the start of each of g receiving cells in ``receiving`` (increasing),
    both are (n, g): each cell's own sums, from one pass over them all. ``counts`` (r,): how
    many pixels each receiving point stands for (:func:`quadrature`; ``seen`` then holds
    their sums)."""
    bs = abs(float(line.distance(spot[None])[0]))
    nearest = bs / MAX_SCALE if flatland else max(bs / MAX_SCALE, min(bs, NEAR_PX))
    bq = np.maximum(np.abs(line.distance(points)), nearest)                  # (n,)
    scale = bs / bq
    d, u = line.distance(receiving), line.along(receiving)
    us = line.along(spot[None])[0]
    gamma = 1.0 if flatland else 2.0
    if flatland:
        along = np.broadcast_to(u[None, :], (len(scale), len(u)))
    else:
        along = us + scale[:, None] * (u[None, :] - line.along(points)[:, None])
    values, on = _sample(line, frame, facet, along, scale[:, None] * d[None, :])
    known = np.ones(values.shape, bool)
    values *= scale[:, None] ** gamma
    if facet is not None:
        # past the line's ends the frame holds another face's light, not the kernel's: unknown
        known = (along >= line.u0) & (along <= line.u1)
        if not flatland:
            # the receiver read where the kernel's symmetry puts it, K(b_q, b_p, t) = K(b_p, b_q, t),
            # when scaled off the facet or past the ends: the spot's frame b_q b_s / b_p from the fold
            lam = bs / np.maximum(np.abs(d), nearest)                         # (r,)
            q, p = np.nonzero(~(known & on))
            along_sym = us + lam[p] * (u[p] - line.along(points)[q])
            sym, on_sym = _sample(line, frame, facet, along_sym, np.sign(d[p]) * lam[p] * bq[q])
            use = on_sym & (along_sym >= line.u0) & (along_sym <= line.u1)
            q, p = q[use], p[use]
            values[q, p] = sym[use] * lam[p] ** gamma
            on[q, p] = known[q, p] = True
        # (off the facet across the fold, past the scan's light, the little light a point sends that far: none)
        values *= known & on
    if counts is not None:
        values *= counts[None, :]
    if groups is not None:
        light = np.add.reduceat(values, groups, axis=1)
        return light if seen is None else (light, np.add.reduceat(known * seen[None, :], groups, axis=1))
    light = values.sum(axis=1)
    return light if seen is None else (light, known.astype(np.float64) @ seen)


def _sample(line: FoldLine, frame: np.ndarray, facet: np.ndarray | None, along: np.ndarray, across: np.ndarray):
    """The ``frame`` (bilinear, 0 outside) at the points ``along`` and ``across`` ``line`` (px,
    arrays of one shape), and whether each lies on ``facet`` (all True without one)."""
    # (rows, columns) each as one flat array, the same sums as centre + along dir + across normal
    where = [(line.centre[c] + along * line.direction[c] + across * line.normal[c]).ravel() for c in (1, 0)]
    values = map_coordinates(frame, where, order=1, cval=0.0).reshape(across.shape)
    if facet is None:
        return values, np.ones(values.shape, bool)
    return values, map_coordinates(np.asarray(facet, np.float32), where, order=0, cval=0.0).reshape(across.shape) > 0


def _receivers(line: FoldLine, cells: list[np.ndarray], side: dict[int, float], k: int, u: float,
               reach: float) -> list[int]:
    return [i for i, si in side.items() if si != side[k] and np.abs(line.along(cells[i]) - u).min() <= reach]


def _receivers_across(line: FoldLine, cells: list[np.ndarray], spots: np.ndarray, k: int, s: float,
                      reach: float) -> list[int]:
    """At a 3D fold: every cell on the other side of ``line`` from cell k (side ``s``; its
    spot there too, within the line's extent) with a pixel within ``reach`` px of the line and
    its spot within ``reach`` along it from k's (:data:`RECEIVER_SPACINGS`)."""
    spot_d, spot_u = line.distance(spots), line.along(spots)
    out = []
    for i, pixels in enumerate(cells):
        if i == k or len(pixels) == 0 or np.sign(spot_d[i]) != -s or not line.u0 <= spot_u[i] <= line.u1 or \
                abs(float(spot_u[i] - spot_u[k])) > reach:
            continue
        d = line.distance(pixels)
        if np.abs(d).min() <= reach and np.mean(np.sign(d) == -s) >= SIDE_SHARE:
            out.append(i)
    return out


#: at most this many (emitting pixel, receiving pixel) pairs mapped at once (:func:`_across_3d`)
BATCH_PAIRS = 2_000_000
#: a 3D fold's cells of more than :data:`EXACT_PIXELS` pixels are binned (:func:`quadrature`)
#: in bins this share of their distance from the fold (plus 2 px) across, twice that along it
QUADRATURE = 0.1
#: cells up to this many pixels keep every pixel (:func:`quadrature`)
EXACT_PIXELS = 256


def quadrature(line: FoldLine, pixels: np.ndarray, share: float = QUADRATURE, count: int = MAX_EMITTERS
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """((q, 2) points, (q,) weights, (n,) bin of each pixel): a cell's ``pixels`` (n, 2) as
    at most ``count`` points, each the mean of the pixels in its bin and weighted by their
    number; up to :data:`EXACT_PIXELS` pixels, each its own. The light a point sends across a
    fold, and the light a point across it receives, change over a distance in proportion to
    the point's own from the fold (the kernel is homogeneous about it), so bins grow with it:
    ``share`` x (distance + 2 px) across, twice that along; near the fold every pixel keeps
    its own bin. Past ``count`` bins, ``share`` grows 1.5x until they fit. On the box's 48
    beams at 20 px a beam (cells of 400 px) the corrections are within 1.4% of every pixel's
    (summed over the entries; the 256 pixels taken evenly before were within 6.6%) and take a
    fifth of their time; small cells' bins would be a pixel or two and save little (the box's
    432 beams, cells of 35 px, at 0.1: 9% off in a longer time), so they keep every pixel."""
    n = len(pixels)
    if n <= EXACT_PIXELS:
        return pixels.astype(np.float64), np.ones(n), np.arange(n)
    d, u = np.abs(line.distance(pixels)), line.along(pixels)
    while True:
        ring = np.floor(np.log1p(d / 2.0) / np.log1p(share)).astype(np.int64)
        width = 2.0 * share * 2.0 * (1.0 + share) ** ring       # twice the ring's width across, at its inner edge
        step = np.floor(u / np.maximum(width, 1.0)).astype(np.int64)
        step -= step.min()
        _, bin_of, counts = np.unique(ring * (int(step.max()) + 1) + step, return_inverse=True, return_counts=True)
        if len(counts) <= count:
            break
        share *= 1.5
    bin_of = bin_of.ravel()
    points = np.stack([np.bincount(bin_of, pixels[:, c].astype(np.float64)) for c in range(2)], axis=1)
    return points / counts[:, None], counts.astype(np.float64), bin_of


def _across_3d(line: FoldLine, cells: list[np.ndarray], spot: np.ndarray, k: int, receivers: list[int],
               frame: np.ndarray, emitters: np.ndarray, weights: np.ndarray, facet: np.ndarray | None,
               binned: dict[int, tuple], min_ratio: float = MIN_RATIO) -> dict[tuple[int, int], float]:
    """At a 3D fold: ``{(i, k): delta}`` for the ``receivers`` of cell k (its pixels as
    ``emitters`` (q, 2) with ``weights`` (q,), :func:`quadrature`, as are the receivers'; beam k's
    ``frame``), cell k's light spread evenly, each ratio over the receiving pixels whose
    mapped points count (:func:`cross_fold_corrections`); the receivers mapped together,
    :data:`BATCH_PAIRS` pixel pairs at a time (on the box's 432 beams each emitting cell has
    some 19 receivers). ``binned``: the receivers' :func:`quadrature` by cell, filled as met;
    no correction whose ratio lies within ``min_ratio`` of 1."""
    out = {}
    chosen, points, parts = [], [], []
    for i in receivers:
        own = map_coordinates(frame, [cells[i][:, 1], cells[i][:, 0]], order=1)
        point = float(own.sum())
        if point > 0:
            if i not in binned:
                binned[i] = quadrature(line, cells[i], count=MAX_RECEIVERS)
            receiving, counts, bin_of = binned[i]
            chosen.append(i)
            points.append(point)
            parts.append((receiving, np.bincount(bin_of, own, len(counts)), counts))
    # consecutive receivers, as many as BATCH_PAIRS pixel pairs allow (at least one)
    cumulative = np.cumsum([len(emitters) * len(part[0]) for part in parts])
    start = 0
    while start < len(chosen):
        done = cumulative[start - 1] if start else 0
        stop = max(start + 1, int(np.searchsorted(cumulative, done + BATCH_PAIRS, side="right")))
        batch = parts[start:stop]
        groups = np.cumsum([0] + [len(part[0]) for part in batch[:-1]]).astype(np.int64)
        spread, seen = light_from(line, frame, spot, emitters, np.concatenate([part[0] for part in batch]),
                                  False, facet, seen=np.concatenate([part[1] for part in batch]),
                                  groups=groups, counts=np.concatenate([part[2] for part in batch]))
        for g, j in enumerate(range(start, stop)):
            known = seen[:, g] > 0
            if not known.any():
                continue
            ratio = float(weights[known] @ spread[known, g]) / float(weights[known] @ seen[known, g])
            if abs(np.log(max(ratio, 1e-300))) >= np.log(min_ratio):
                out[(chosen[j], k)] = (np.clip(ratio, 1.0 / CAP, CAP) - 1.0) * points[j]
        start = stop
    return out


def cross_fold_corrections(line: FoldLine, cells: list[np.ndarray], spots: np.ndarray, spacing: float,
                           frame_of, flatland: bool, side: dict[int, float] | None = None,
                           facet: np.ndarray | None = None, placement: float = PLACEMENT_PX,
                           min_ratio: float = MIN_RATIO, emission: np.ndarray | None = None
                           ) -> dict[tuple[int, int], float]:
    """``{(i, k): delta}`` in frame units: for each cell k touching ``line`` whose spot lies
    within :data:`EMITTER_SPACINGS` of it, and each cell i touching it on the other side
    within two spacings along it, the light cell k sends to cell i spread over cell k's
    pixels, less what its spot sends (:func:`light_from`), as sure of it as the fold's place
    allows: the fold moved ``placement`` px either way too, the least of the three
    corrections, none where they disagree in sign (on the noisy M, a scan whose spots lie 4 px
    from the folds on both sides, corrected from the fold as found, was 2-3% worse), and none
    under ``min_ratio``.
    ``frame_of(k)``: beam k's frame
    (H, W), on the cells' grid; ``flatland``: gamma 1 and no shift along the fold, else 3D;
    ``facet``: the scan's lit pixels (:func:`light_from`); ``emission`` (H, W): how cell k's
    light is spread over its pixels (None: evenly; :func:`fold_corrections` gives the far
    light, which falls off toward the fold as a cell's light does).

    At a 3D fold (not ``flatland``) cell k sends to every cell across within
    :data:`RECEIVER_SPACINGS` (:func:`_receivers_across`), its light spread evenly (the far
    light is a flatland scan's proxy: on the box's creases it made the 432 beams 5% worse where
    the even spread makes them 3% better), none under ``min_ratio`` (a spot mid-cell gets small
    corrections: the native 48-beam box 0.6 / 4.6 / 7.3% worse than none at 10 / 20 / 40 px a
    beam with every one made, 2% better / 2% better / 3.5% worse with the factor, in the
    renderer's patches of 2.5 / 5 / 10 px; the 2x lattice rendered at 40 px, spots centred,
    6.5% worse -> 0.6% better; placement is not used). A receiving pixel that an emitting one
    scales off the facet or past the line's ends is read by the kernel's symmetry
    (:func:`light_from`); where that too leaves them, each ratio is taken over the receiving
    pixels whose mapped points lie within the line's extent: past a fold's end (a box's
    corner) the frame holds another face's light, and counted as none it took the corrections
    there 25% high (the corner's cells, against the renderer's T spread evenly); off the facet
    across the fold it counts as none, the little light a point sends that far. Such pairs were
    all left out of the ratio before the symmetric read, and with them the emitting pixels
    nearest the fold from every receiver past the cells touching it, which they light least
    (the native box seen from 10x as far at 80 px a beam: ratios 1.21-1.39 where the
    renderer's are 0.93-1.09, the split 9.7% worse than without the transfer; with the read
    1.8% better; docs/fullres.md "3D folds")."""
    side = fold_sides(line, cells, spots) if side is None else side
    spot_d, spot_u = line.distance(spots), line.along(spots)
    out, binned = {}, {}
    for k in side:
        if abs(float(spot_d[k])) > EMITTER_SPACINGS * spacing:
            continue
        receivers = _receivers(line, cells, side, k, spot_u[k], 2.0 * spacing) if flatland else \
            _receivers_across(line, cells, spots, k, side[k], RECEIVER_SPACINGS * spacing)
        if not receivers:
            continue
        frame = np.asarray(frame_of(k), np.float64)
        if not flatland:
            points, weights, _ = quadrature(line, cells[k])
            out.update(_across_3d(line, cells, spots[k], k, receivers, frame, points, weights, facet, binned,
                                  min_ratio))
            continue
        emitters = _thinned(cells[k], MAX_EMITTERS)
        shares = np.ones(len(emitters)) if emission is None else \
            np.maximum(map_coordinates(emission, [emitters[:, 1], emitters[:, 0]], order=1), 0.0)
        if not shares.sum() > 0:
            continue
        for i in receivers:
            receiving = _thinned(cells[i], MAX_RECEIVERS)
            weight = len(cells[i]) / len(receiving)
            point = float(map_coordinates(frame, [receiving[:, 1], receiving[:, 0]], order=1).sum()) * weight
            if not point > 0:
                continue
            # the ratio with the fold where it was found and PLACEMENT_PX either side: the one
            # nearest 1, or none where they disagree on which side of 1 it lies
            ratios = [float(np.average(light_from(placed, frame, spots[k], emitters, receiving, flatland, facet),
                                       weights=shares)) * weight / point
                      for placed in (line, *(line.shifted(t) for t in (-placement, placement)))]
            if min(ratios) < 1.0 < max(ratios):
                continue
            ratio = min(ratios, key=lambda r: abs(np.log(max(r, 1e-300))))
            if abs(np.log(max(ratio, 1e-300))) < np.log(min_ratio):
                continue
            out[(i, k)] = (np.clip(ratio, 1.0 / CAP, CAP) - 1.0) * point
    return out


def homogeneity_miss(line: FoldLine, cells: list[np.ndarray], spots: np.ndarray, spacing: float, frame_of,
                     flatland: bool, side: dict[int, float], facet: np.ndarray | None = None) -> float | None:
    """How far the kernel's homogeneity about ``line`` misses on the scan's own frames: for
    up to :data:`CHECKS` beams k whose cell touches the fold (or, where k's spot is nearer the
    fold than :data:`CHECK_NEAR_PX`, the next beam behind it), the beam k' behind it on the
    same side (its spot 1.5 to :data:`CHECK_REACH_FLATLAND` times as far from the fold, at 3D
    folds to :data:`MAX_SCALE` times, within a spacing along it), the
    light k' sends to the cells touching the fold across from k, against what k's frame
    gives for a point at k''s spot (:func:`light_from`): the median of ``|given / sent - 1|``.
    None when no such pair lies about the line. On a concave fold between two planes it is
    small (the M's folds 0.02-0.1); a line that is no such fold (a silhouette's valley, a
    shadow's edge) misses."""
    spot_d, spot_u = line.distance(spots), line.along(spots)
    reach = CHECK_REACH_FLATLAND if flatland else MAX_SCALE
    misses, fronts = [], set()
    for k in side:
        if len(misses) >= CHECKS:
            break
        front, bk = k, abs(float(spot_d[k]))
        if bk < CHECK_NEAR_PX:               # the next beam behind it stands in (CHECK_NEAR_PX)
            stand_ins = [j for j in range(len(spots)) if np.sign(spot_d[j]) == side[k] and
                         abs(float(spot_d[j])) > bk and abs(float(spot_u[j] - spot_u[k])) <= spacing / 2]
            if not stand_ins:
                continue
            front = min(stand_ins, key=lambda b: abs(float(spot_d[b])))
            bk = abs(float(spot_d[front]))
        if front in fronts:                  # a stand-in for two front spots is checked once
            continue
        fronts.add(front)
        behind = [j for j in range(len(spots)) if np.sign(spot_d[j]) == side[k] and
                  1.5 * bk <= abs(float(spot_d[j])) <= reach * bk and
                  (flatland or abs(float(spot_u[j] - spot_u[front])) <= spacing)]
        receivers = _receivers(line, cells, side, k, spot_u[front], spacing)
        if not behind or not receivers:
            continue
        j = min(behind, key=lambda b: abs(float(spot_d[b])) + abs(float(spot_u[b] - spot_u[front])))
        receiving = np.concatenate([_thinned(cells[i], MAX_RECEIVERS) for i in receivers])
        far = np.asarray(frame_of(j), np.float64)
        sent = float(map_coordinates(far, [receiving[:, 1], receiving[:, 0]], order=1).sum())
        given = float(light_from(line, np.asarray(frame_of(front), np.float64), spots[front], spots[j][None],
                                 receiving, flatland, facet)[0])
        if sent > 0:
            misses.append(abs(given / sent - 1.0))
    return float(np.median(misses)) if misses else None


def fold_corrections(labels: np.ndarray, spots: np.ndarray, lines: list[tuple[FoldLine, float]],
                     light: np.ndarray, spacing: float, frame_of, scales: np.ndarray, solid: bool = False):
    """Every fold's corrections: ``(rows, cols, values, record)``, values in T's units
    (frame units over each column's scale), for the cells ``labels`` (H, W; -1 outside),
    the spots (m, 2) on the cells' grid, the fold lines on the valley floor and their moves
    (:func:`floor_lines`), the far light of :mod:`ilt.isf.folds`, and ``frame_of(k)`` beam
    k's frame. The record: per line its
    ends, its move to the valley floor, flatland or 3D, how far the kernel's homogeneity
    misses on its frames (:func:`homogeneity_miss`; a line missing by more than
    :data:`MAX_MISS`, or that cannot be checked, gives nothing) and the entries it gave.
    ``solid``: at 3D folds too (:func:`cross_fold_corrections`; the box's scans 3-10% better,
    docs/fullres.md), else flatland ones only. At flatland folds each cell's light is spread as
    the far light ``light`` is."""
    m = len(spots)
    cells = _cell_pixels(labels, m)
    lit = labels >= 0
    facet = lit.astype(np.float32)       # the lit mask as map_coordinates reads it, made once
    entries: dict[tuple[int, int], float] = {}
    record = []
    for line, offset in lines:
        shares = side_shares(line, cells, spots)     # the corrections' cells and the check's, one pass
        side, checked = fold_sides(line, cells, spots, shares=shares), \
            fold_sides(line, cells, spots, CHECK_SHARE, shares)
        frames: dict[int, np.ndarray] = {}        # this line's beams, each read once

        def frame(k):
            if k not in frames:
                frames[k] = np.asarray(frame_of(k), np.float64)
            return frames[k]

        near = [k for k in checked if abs(float(line.distance(spots[k][None])[0])) <= EMITTER_SPACINGS * spacing]
        votes = [v for v in (is_flatland(line, frame(k), spots[k], lit) for k in near[:5]) if v is not None]
        flatland = bool(votes) and float(np.mean(votes)) > 0.5
        used = bool(votes) and (flatland or solid)
        miss = homogeneity_miss(line, cells, spots, spacing, frame, flatland, checked, facet) if used else None
        found = cross_fold_corrections(line, cells, spots, spacing, frame, flatland, side, facet, emission=light) \
            if miss is not None and miss <= MAX_MISS else {}
        for key, value in found.items():      # a pair beside two folds (a corner): the longer line's
            entries.setdefault(key, value)
        ends = [line.centre + u * line.direction for u in (line.u0, line.u1)]
        record.append({"from": [round(float(v), 2) for v in ends[0]], "to": [round(float(v), 2) for v in ends[1]],
                       "moved_px": round(offset, 2), "flatland": flatland if votes else None,
                       "miss": None if miss is None else round(miss, 3), "entries": len(found)})
    rows = np.array([i for i, _ in entries], np.int64)
    cols = np.array([k for _, k in entries], np.int64)
    values = np.array(list(entries.values()), np.float64) / np.asarray(scales, np.float64)[cols] if entries \
        else np.empty(0)
    return rows, cols, values, record


def write_corrections(path, rows: np.ndarray, cols: np.ndarray, values: np.ndarray, m: int) -> None:
    """``fold_transfer.npz``: the corrections as a sparse (m, m) matrix."""
    scipy.sparse.save_npz(path, scipy.sparse.coo_matrix((values, (rows, cols)), shape=(m, m)).tocsc())


def recorded_lines(isf_dir) -> list[tuple[np.ndarray, np.ndarray, bool]]:
    """The fold lines a build found (its manifest's ``fold_transfer.lines``), as (start, end,
    solid): frame-grid pixels, and True at a 3D fold (:func:`is_flatland` False; a flatland or
    undecided line is False). Empty when the build had none, or no fold transfer. Every line,
    whether or not the light across it was corrected: a line the build could not check is
    still the barriers' fold."""
    from ilt.io.manifest import StageError, read_manifest

    try:
        lines = read_manifest(isf_dir).get("fold_transfer", {}).get("lines", [])
    except (StageError, AttributeError, OSError):
        return []
    return [(np.asarray(line["from"], np.float64), np.asarray(line["to"], np.float64), line.get("flatland") is False)
            for line in lines if isinstance(line, dict) and "from" in line and "to" in line]


def apply_corrections(T: np.ndarray, rows: np.ndarray, cols: np.ndarray, values: np.ndarray) -> np.ndarray:
    """T (m, m), owned (changed in place and returned), with ``delta`` (entries at ``rows``,
    ``cols``, T's units) added and carried through the scene's further bounces: ``T + (T
    D^-1) delta``, D T's diagonal. Light ``v`` more arriving in cell i is ``v / T_ii`` of
    beam i's spot, which sends on T's column i (its own cell's entry the ``v`` itself).
    Only delta's columns change; each from T as given."""
    diagonal = np.diag(T).copy()
    updates = {}
    for k in np.unique(cols):
        at = cols == k
        updates[int(k)] = T[:, rows[at]] @ (values[at] / diagonal[rows[at]])
    for k, column in updates.items():
        T[:, k] += column
    return T


__all__ = ["CUT_MARGIN_PX", "FILE", "FoldLine", "apply_corrections", "cross_fold_corrections", "cut_cells", "floor_lines",
           "fold_corrections", "fold_lines", "fold_sides", "homogeneity_miss", "side_shares", "is_flatland", "light_from", "recorded_lines",
           "to_lit_edge",
           "valley_floor", "write_corrections"]
