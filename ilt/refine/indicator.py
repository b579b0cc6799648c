"""Where the next beams help: an error indicator from T alone, and greedy placement.

The full-resolution bounces are worst where the scene's transport changes faster than
the beam spacing: at folds, occluding edges and texture, where one cell holds surfaces
that the neighbouring beams light differently (docs/fullres.md, Limits). T shows it
without any ground truth. Where the scene is smooth, a beam's column of T is close to
the affine interpolation of its neighbours' columns (the neighbours: the spots'
Delaunay triangulation, or consecutive spots of a line); across a fold it is not. The
**prediction residual** of beam j

    r_j = || t_j - sum_k w_k t_k || / || t_j ||

over T's unit columns, with the rows of the spots of j and its neighbours k left out, and
``w`` the least-norm weights that reproduce an affine function of the spot pixels at j,
is 0 where the columns vary linearly across the spots (a fine cell's plane models that:
ilt.isf.fine) and of order 1 where they jump. A line of spots (flatland) places by it; a
grid places its folds by the build's fold lines and its other beams by how far apart its
neighbouring beams are in what they light ("A grid's edges" below).

On a line, an edge ``e = (i, k)`` has the share ``s_e = w_e (r_i^2 + r_k^2) / 2``, ``w_e`` the
region it stands for (its length in pixels), and the scan's **indicator** is
``E = sqrt(sum_e s_e / sum_e w_e)``. Two
new beams at the thirds of edge e split it in three: the third holding the change keeps
the residual and the other two are smooth, so the edge's share falls by two thirds (the
**gain**, ``s_e / 3`` for each of the two beams, in units of E^2), and each third is left
with ``s_e / 9``. Placement is greedy on the gain, with the thirds back in the queue; no
beam lands closer than ``min_spacing`` pixels to another, nor outside the ISF's cells
(where the scan saw no surface).

Thirds, not halves, on a line: where the change is a fold between two beams, halfway is
the fold itself, and a beam there lights both faces with a spot the crease cuts; and a beam
halfway between two others leaves the cells next to the fold uneven (one end at the
fold, the other a quarter spacing away). The thirds land a sixth of the spacing to each
side of a fold halfway between its beams, and with the two old beams make a lattice a
third as wide whose cells end at the fold. On the rendered M (16 beams, exact frames),
the 3 fold edges halved: bounce error 0.177 against the 16 beams' 0.102; trisected: 0.076
(docs/refine.md).

**A grid's edges.** On a grid of spots the edge's share is the **transport change**
``s_e = D_e^2``, the squared distance between its two beams' unit columns off their own
rows, with the noise's expected share taken off (:func:`transport_change`), over a weight of
1 an edge; the indicator is the root mean square of D over the edges. One beam at the
middle of the edge halves it: each half keeps a quarter of the share (the change along a
smooth edge is about linear), so the gain is ``s_e / 2`` and each half goes back in the
queue with ``s_e / 4``. Why a distance in T and not the residual, nor the pixels: the scene's
grid is not in the pixels. The box's floor images its square cells as rhombi whose short
diagonal (12.8 px) is shorter than their sides (14.3 px), so a pixel-length weight splits the
floor's sides first, and the cells' centres (the best beams there: the quincunx with the fold
pairs is the best half-lattice scan measured) come last. In T the floor's diagonals are
1.8 x its sides in D^2, about the scene's 2 (the walls, seen square: 1.2-1.5 x). On the box's
2x lattice (2e4 e-, three draws of the noise), after the fold pairs: +108 beams 0.0557 ->
0.0539 by D^2 halves, within 0.1% of the fold midpoints + centres' 0.0540. On two draws each:
the residual by pixel length, halved, 0.0560; the residual weighted by D^2, halved, 0.0550
(docs/refine.md, "A grid by what its beams light").
The residual still shades refine.png, and a line's placement is as below.

**Which Delaunay edges are neighbours.** An edge bridges a gap (void between surfaces, an
isolated spot, the hull's slivers) when it is longer than :data:`MAX_EDGE_RATIO` times either
end's spacing, a spot's distance to its :data:`SPACING_RANK`-th nearest; a sliver between two
close rows of spots (the beams either side of a crease) when it is also longer than that many
times the farther end's nearest distance. Not each end's nearest distance: on the box's 4x
lattice (4 x 4 beams a face) the beams beside a crease stand 3 px from their partner across it
and 19 px from their own grid; that rule cut all their edges, refine never saw the cells beside
the creases and put its beams inside the faces, worse than random beams (+24: 0.1432 against the
base's 0.1331); with these edges, 0.0873 (docs/refine.md, "The 4x box lattice").

**Noise.** Under a sensor's noise every column's residual holds the noise of the entries
it sums: on the noisy box (2e4 e-) a median 0.41 of the column away from its folds, 0.53 in
the folds' rows, so the greedy went mostly by the noise. With build-isf's
``T_var.npy`` (each entry's variance) the residual's expected square from the noise, ``sum_r
(V_rj + sum_k w_k^2 V_rk)``, is taken off its square: the folds' rows 0.50, the rest 0.25.

**Folds.** A 2D scan's error lies along its folds (the box's three creases hold most of it at
every density: docs/refine.md "Folds first"): the cells next to a fold exchange light that
changes over the fold's distance, far less than the spacing along it. Beams added on one side
of a fold only leave the cells across it unmatched and made the box *worse* (quincunx + 16 at
folds: 0.0573 -> 0.0642); the same beams with a partner across the fold made it better
(0.0535). So where the build found folds (its ``fold_transfer`` lines, their light corrected or not),
the spots within :data:`ROW_REACH` spacings of a fold on each side are its **rows**, and the
gaps between their places along it are split at the middle by a **pair**: one beam each side,
at the rows' distance from the fold. The pair's gain is half the share of the two rows' edges
along the gap (a halved edge keeps a quarter each half); until the rows are
:data:`FOLD_SPACING` of the spacing apart, pairs go before any edge, then by gain. The edges
within the rows, and any edge across the fold, are the pairs' to split. Flatland scans (a line
of spots) have no rows: their folds are points, split in thirds as above.

**Rows on the fold.** On a scan whose rows stand within :data:`ROW_MIN_DEPTH` spacings of the
fold (the box's 4x lattice: 1.2-1.8 px at a 22 px spacing, spots that light both faces) a pair
at the rows' depth is two more beams on the crease. What such a scan lacks first is beams on
the faces beside it, the middles of the edges across the fold; then beams along it. So there
the pairs rank with the edges by their gain, and the edges across the fold are split as any.
On the 4x box (2e4 e-, the one draw of three whose build found two fold lines at 48 beams):
pairs first, +24 0.1283 (random 0.1190); by gain, 0.0881; +48 0.0791 -> 0.0778; no pairs at
all, 0.0859 / 0.0872 (docs/refine.md, "The 4x box lattice").

Costs: one pass over T's rows in blocks, a sparse product of O(m x edges) (about 3 m
edges in 2D) and on a grid the edges' dot products in the same pass, so the decision at
m = 4096 reads T once (benchmarks/bench_refine.py --timing-m).
"""

from __future__ import annotations

import heapq
import itertools
from dataclasses import dataclass

import numpy as np
import scipy.sparse
from scipy.spatial import Delaunay, QhullError, cKDTree

#: rows of T read at once (a block of rows x edges float64 is about 25 MB at 12 k edges)
ROW_BLOCK = 256
#: a Delaunay edge longer than this many times either end's spacing (:data:`SPACING_RANK`), or
#: than this many times the farther of its ends' nearest-neighbour distances, bridges a gap in the
#: scan (void between surfaces, the hull's slivers): not a neighbour (:func:`neighbour_edges`)
MAX_EDGE_RATIO = 2.5
#: a spot's spacing, for the edges' test: the distance to its third nearest spot (a beam beside a
#: crease has one spot across it, at a corner where three faces meet two)
SPACING_RANK = 3
#: a spot within this many spacings of a fold line is in the row beside it (module doc, "Folds")
ROW_REACH = 0.75
#: a fold whose row on either side stands closer to it than this many spacings has its beams on it
#: (a spot a few pixels from a crease lights both faces): its pairs rank with the edges, and the
#: edges across it are split as any (module doc, "Folds")
ROW_MIN_DEPTH = 0.125
#: the rows beside a fold are split in pairs before anything else until their spots are this
#: many of the scan's spacings apart along it (module doc, "Folds")
FOLD_SPACING = 0.5


class RefineError(ValueError):
    """Refinement that cannot be decided; the message names the file or the value."""


@dataclass(frozen=True)
class Edges:
    """Neighbouring spots: ``pairs`` (E, 2) int rows of T; ``length`` (E,) pixels;
    ``dimension`` 1 (spots on a line) or 2; ``coords`` (m, dimension) the spots in it
    (a line: the position along it, so that a pixel of jitter across it is no slope)."""

    pairs: np.ndarray
    length: np.ndarray
    dimension: int
    coords: np.ndarray


def neighbour_edges(samples: np.ndarray) -> Edges:
    """The neighbour pairs of (m, 2) spot pixels: consecutive along the line when the
    spots are collinear, else the Delaunay edges that do not bridge a gap."""
    from ilt.isf.folds import spot_line

    samples = np.asarray(samples, dtype=np.float64)
    centred = samples - samples.mean(axis=0)
    # a line (ilt.isf.folds.LINE_SPREAD); one or two spots are one, along their own axis
    axis = spot_line(samples) if len(samples) >= 3 else np.linalg.svd(centred, full_matrices=False)[2][0]
    if axis is not None:
        coords = (centred @ axis)[:, None]
        order = np.argsort(coords[:, 0], kind="stable")
        pairs, dimension = np.stack([order[:-1], order[1:]], axis=1), 1
    else:
        try:
            simplices = Delaunay(samples).simplices
        except QhullError as exc:
            raise RefineError(f"the spots cannot be triangulated ({exc})") from None
        pairs = np.concatenate([simplices[:, [0, 1]], simplices[:, [1, 2]], simplices[:, [0, 2]]])
        pairs = np.unique(np.sort(pairs, axis=1), axis=0)
        dimension, coords = 2, samples
    length = np.linalg.norm(samples[pairs[:, 0]] - samples[pairs[:, 1]], axis=1)
    if dimension == 2:
        # an edge to a spot far from the rest is longer than the near end's spacing; a sliver along
        # two close rows (the beams beside a crease) is longer than both ends' nearest distances.
        # Not each end's nearest distance alone: a beam 3 px across a crease from another, with
        # the grid 20 px off, would lose every edge to the grid, and the cells between it and
        # the grid would never be refined (the box's 4x lattice, docs/refine.md)
        k = min(SPACING_RANK, len(samples) - 1)
        near = cKDTree(samples).query(samples, k=k + 1)[0]
        spacing, nn = near[:, k], near[:, 1]
        keep = ((length <= MAX_EDGE_RATIO * np.minimum(spacing[pairs[:, 0]], spacing[pairs[:, 1]]))
                & (length <= MAX_EDGE_RATIO * np.maximum(nn[pairs[:, 0]], nn[pairs[:, 1]])))
        pairs, length = pairs[keep], length[keep]
    return Edges(pairs, length, dimension, coords)


def neighbour_lists(edges: Edges, m: int) -> list[np.ndarray]:
    """Each spot's neighbours (rows of T) from the edges; a spot with fewer than
    dimension + 1 (the end of a line, a corner of a grid: too few to interpolate an affine
    function) also takes its neighbours' neighbours, so that it is extrapolated."""
    direct = [set() for _ in range(m)]
    for a, b in edges.pairs.tolist():
        direct[a].add(b)
        direct[b].add(a)
    out = []
    for j, near in enumerate(direct):
        if 0 < len(near) < edges.dimension + 1:
            near = near | set().union(*(direct[k] for k in near)) - {j}
        out.append(np.array(sorted(near), dtype=np.int64))
    return out


def interpolation_weights(coords: np.ndarray, j: int, neighbours: np.ndarray) -> np.ndarray:
    """The least-norm weights that reproduce an affine function of the spots' coordinates
    (m, d) at spot j from its neighbours: sum w = 1, sum w (x_k - x_j) = 0."""
    rel = coords[neighbours] - coords[j]
    A = np.vstack([np.ones(len(neighbours)), rel.T])                 # (1 + d, n)
    rhs = np.zeros(A.shape[0])
    rhs[0] = 1.0
    return np.linalg.lstsq(A, rhs, rcond=1e-9)[0]


def prediction_residual(T: np.ndarray, coords: np.ndarray, neighbours: list[np.ndarray],
                        variance: np.ndarray | None = None) -> np.ndarray:
    """(m,) ``r_j`` of the module doc: how far beam j's column of T is from the affine
    interpolation of its neighbours' columns, relative to its own, over the rows that are
    not the spots of j or its neighbours. T may be a memory map: one pass over its rows
    in blocks; the interpolation is a sparse (m, m) matrix W, and T W the residuals.

    variance: (m, m) each entry's noise variance (build-isf's ``T_var.npy``), or None: the
    residual's expected square from the noise, ``sum_r V_rj + sum_k w_k^2 V_rk``, is taken
    off its square (module doc, "Noise"): what is left is the transport's own change."""
    W, weights = _interpolation(coords, neighbours)
    sums = _row_pass(T, variance, W=W)
    return _residual(T, variance, W, weights, neighbours, sums)


def transport_change(T: np.ndarray, pairs: np.ndarray, variance: np.ndarray | None = None) -> np.ndarray:
    """(E,) the squared distance between the unit columns of each pair's two beams,
    ``D_e^2 = sum_r (T_ri / |t_i| - T_rk / |t_k|)^2`` over the rows that are not the two
    spots' own, with the noise's expected share (``sum_r V_ri / |t_i|^2 + V_rk / |t_k|^2``,
    ``variance`` from ``T_var.npy``) taken off: how far apart the two beams are in what they
    light (module doc, "A grid's edges"). One pass over T's rows (and V's) in blocks."""
    return _change(T, variance, pairs, _row_pass(T, variance, pairs=pairs))


@dataclass
class _RowSums:
    """What one pass over T's rows (and V's) gives: ``residual2`` (m,) the squared columns of
    T W (or None), ``norm2`` (m,) the squared columns of T, ``dots`` (E,) each pair's columns'
    dot product (or None), ``variance`` (m,) V's column sums (or None)."""

    residual2: np.ndarray | None
    norm2: np.ndarray
    dots: np.ndarray | None
    variance: np.ndarray | None


def _row_pass(T, variance, W=None, pairs=None) -> _RowSums:
    """Read T (a memory map, say) once in blocks of :data:`ROW_BLOCK` rows for the sums the
    residual (``W``) and the pairs' change (``pairs``) need."""
    m = T.shape[0]
    sums = _RowSums(np.zeros(m) if W is not None else None, np.zeros(m),
                    np.zeros(len(pairs)) if pairs is not None else None, np.zeros(m) if variance is not None else None)
    for r0 in range(0, m, ROW_BLOCK):
        block = np.asarray(T[r0:r0 + ROW_BLOCK], dtype=np.float64)
        sums.norm2 += np.einsum("rj,rj->j", block, block)
        if W is not None:
            R = (W.T @ block.T).T                               # block @ W, W sparse
            sums.residual2 += np.einsum("rj,rj->j", R, R)
        if pairs is not None:
            sums.dots += np.einsum("re,re->e", block[:, pairs[:, 0]], block[:, pairs[:, 1]])
        if variance is not None:
            sums.variance += np.asarray(variance[r0:r0 + ROW_BLOCK], dtype=np.float64).sum(axis=0)
    return sums


def _interpolation(coords, neighbours) -> tuple[scipy.sparse.csr_matrix, list[np.ndarray]]:
    """The sparse (m, m) W whose column j is e_j minus j's interpolation weights on its
    neighbours, and the weights."""
    m = len(neighbours)
    weights = [interpolation_weights(coords, j, near) if near.size else np.empty(0)
               for j, near in enumerate(neighbours)]
    rows = np.concatenate([np.concatenate([[j], near]) for j, near in enumerate(neighbours)])
    cols = np.concatenate([np.full(1 + near.size, j) for j, near in enumerate(neighbours)])
    vals = np.concatenate([np.concatenate([[1.0], -w]) for w in weights])
    return scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(m, m)), weights


def _residual(T, variance, W, weights, neighbours, sums: _RowSums) -> np.ndarray:
    """:func:`prediction_residual` from the pass's sums."""
    m = T.shape[0]
    residual2, norm2 = sums.residual2.copy(), sums.norm2.copy()
    noise2 = W.multiply(W).T @ sums.variance if variance is not None else np.zeros(m)   # all rows, through W^2
    # leave out the rows of the spots of j and its neighbours: a difference of sums, so what
    # is left below their rounding (a few eps of the sum over all rows) is zero, not
    # sqrt(eps) of a residual (1.5e-7 where the rows left out held all of it)
    floor = 64 * np.finfo(np.float64).eps * residual2
    for j, (near, w) in enumerate(zip(neighbours, weights)):
        own = np.concatenate([[j], near])
        column = np.asarray(T[own, j], dtype=np.float64)
        local = column - (np.asarray(T[np.ix_(own, near)], dtype=np.float64) @ w if near.size else 0.0)
        residual2[j] -= float(local @ local)
        norm2[j] -= float(column @ column)
        if variance is not None:
            noise2[j] -= float(np.asarray(variance[own, j], dtype=np.float64).sum()
                               + (np.asarray(variance[np.ix_(own, near)], dtype=np.float64) @ w ** 2).sum())
    residual2 = np.where(residual2 > floor, residual2 - np.maximum(noise2, 0.0), 0.0)
    scale = np.sqrt(np.maximum(norm2, 0.0))
    return np.where(scale > 0, np.sqrt(np.maximum(residual2, 0.0)) / np.where(scale > 0, scale, 1.0), 0.0)


def _change(T, variance, pairs, sums: _RowSums) -> np.ndarray:
    """:func:`transport_change` from the pass's sums."""
    i, k = pairs[:, 0], pairs[:, 1]
    n = np.sqrt(np.maximum(sums.norm2, np.finfo(np.float64).tiny))
    # all rows: |t_i/n_i - t_k/n_k|^2 = 2 - 2 t_i.t_k / (n_i n_k); then the two own rows' terms off
    change = 2.0 - 2.0 * sums.dots / (n[i] * n[k])
    for row in (i, k):
        change -= (np.asarray(T[row, i], np.float64) / n[i] - np.asarray(T[row, k], np.float64) / n[k]) ** 2
    if variance is not None:
        noise = sums.variance[i] / n[i] ** 2 + sums.variance[k] / n[k] ** 2
        for row in (i, k):
            noise -= (np.asarray(variance[row, i], np.float64) / n[i] ** 2
                      + np.asarray(variance[row, k], np.float64) / n[k] ** 2)
        change -= noise
    return np.maximum(change, 0.0)


@dataclass(frozen=True)
class Placement:
    """The chosen beams, best first: ``targets`` (K, 2) pixels (x, y), ``gain`` (K,) what
    each removes from E^2; ``before`` / ``after`` the indicator E of the scan and of the
    scan with the targets added; ``residual`` (m,) each beam's ``r_j``, for reports;
    ``fold_pairs`` how many of the targets' pairs straddle a fold."""

    targets: np.ndarray
    gain: np.ndarray
    before: float
    after: float
    residual: np.ndarray
    fold_pairs: int = 0


@dataclass(frozen=True)
class FoldRows:
    """The spots in the row next to a straight fold on each side of it (a 2D scan).

    ``start`` (2,) one end of the fold (pixels), ``along`` and ``normal`` its unit vectors;
    ``side`` {spot row of T: +1 / -1}; ``place`` {spot row: its position along the fold};
    ``depth`` (2,) the rows' median distance from the fold (+ side, - side); ``stations`` the
    sorted positions along the fold of the two rows' spots, merged where closer than a
    quarter spacing; ``on_fold``: a row stands within :data:`ROW_MIN_DEPTH` spacings of it,
    its beams on the fold (module doc, "Folds")."""

    start: np.ndarray
    along: np.ndarray
    normal: np.ndarray
    side: dict
    place: dict
    depth: tuple
    stations: list
    on_fold: bool = False

    def crosses(self, samples: np.ndarray, pairs: np.ndarray) -> np.ndarray:
        """(E,) bool: the edges ``pairs`` of spots ``samples`` whose ends lie on the two sides of
        the fold, crossing it between its first and last stations (half a gap beyond)."""
        rel = samples - self.start
        d, t = rel @ self.normal, rel @ self.along
        da, db = d[pairs[:, 0]], d[pairs[:, 1]]
        across = da * db < 0
        at = t[pairs[:, 0]] + (t[pairs[:, 1]] - t[pairs[:, 0]]) * da / np.where(across, da - db, 1.0)
        reach = 0.5 * (float(np.median(np.diff(self.stations))) if len(self.stations) > 1 else 0.0)
        return across & (at >= self.stations[0] - reach) & (at <= self.stations[-1] + reach)

    def pair(self, t: float) -> list[np.ndarray]:
        """The two targets at ``t`` along the fold, one each side at its row's distance."""
        foot = self.start + t * self.along
        return [foot + self.depth[0] * self.normal, foot - self.depth[1] * self.normal]


def fold_rows(samples: np.ndarray, folds, spacing: float) -> list[FoldRows]:
    """The rows of spots beside each fold (``folds``: (start, end) pixel pairs, the build's
    fold lines): spots within :data:`ROW_REACH` spacings of the line and along it, at least
    two on each side; folds without such rows are left out."""
    out = []
    for start, end in folds:
        start, end = np.asarray(start, np.float64), np.asarray(end, np.float64)
        length = float(np.linalg.norm(end - start))
        if length <= 0:
            continue
        u = (end - start) / length
        normal = np.array([-u[1], u[0]])
        rel = samples - start
        t, d = rel @ u, rel @ normal
        near = (np.abs(d) < ROW_REACH * spacing) & (t > -0.5 * spacing) & (t < length + 0.5 * spacing)
        plus, minus = np.flatnonzero(near & (d > 0)), np.flatnonzero(near & (d < 0))
        if plus.size < 2 or minus.size < 2:
            continue
        stations = []
        for value in np.sort(t[near]):
            if stations and value - stations[-1][-1] < spacing / 4:
                stations[-1].append(value)
            else:
                stations.append([value])
        depth = (float(np.median(d[plus])), float(np.median(-d[minus])))
        side = {**{int(k): 1 for k in plus}, **{int(k): -1 for k in minus}}
        out.append(FoldRows(start, u, normal, side, {k: float(t[k]) for k in side}, depth,
                            [float(np.mean(group)) for group in stations],
                            on_fold=min(depth) < ROW_MIN_DEPTH * spacing))
    return out


def place_beams(T: np.ndarray, samples: np.ndarray, count: int, min_spacing: float | None = None,
                covered=None, folds=None, variance: np.ndarray | None = None) -> Placement:
    """Up to ``count`` new beam targets (pixels) for the scan of T (m, m) with spots at
    ``samples`` (m, 2), greedy on the gain of the module doc.

    On a grid of spots an edge takes one beam at its middle, a fold two (one each side);
    on a line an edge takes two, at its thirds, so that an odd ``count`` places one fewer.
    min_spacing: no target closer than this (pixels) to a spot or another target (default:
    a quarter of the median neighbour distance, so an edge is split once);
    covered: ``covered(points (n, 2)) -> (n,) bool``, False where no beam should go (no
    cell there); None: everywhere. variance: T's entries' noise (:func:`prediction_residual`).
    folds: the scene's fold lines ((start, end) pixels,
    the build's): along each, the rows of spots beside it are split in pairs, one beam
    each side at the same place along it (module doc, "Folds"). Fewer than ``count``
    targets come back when no edge has room or gain left.
    """
    if count < 1:
        raise RefineError(f"the number of new beams must be at least 1, got {count}")
    samples = np.asarray(samples, dtype=np.float64)
    edges = neighbour_edges(samples)
    if count < 2 and edges.dimension == 1:
        raise RefineError(f"the number of new beams must be at least 2 on a line of spots (they come in pairs: "
                          f"an edge is split in thirds), got {count}")
    if not len(edges.pairs) or float(edges.length.sum()) <= 0:
        raise RefineError("the spots have no neighbours at a distance: nothing to refine")
    # one pass over T: the residual, and on a grid the edges' change too
    neighbours = neighbour_lists(edges, len(samples))
    W, weights = _interpolation(edges.coords, neighbours)
    grid = edges.dimension == 2
    sums = _row_pass(T, variance, W=W, pairs=edges.pairs if grid else None)
    residual = _residual(T, variance, W, weights, neighbours, sums)
    median = float(np.median(edges.length))
    if grid:                                      # module doc, "A grid's edges"
        weight = np.ones(len(edges.pairs))
        score = _change(T, variance, edges.pairs, sums)
    else:
        weight = edges.length
        score = weight * (residual[edges.pairs[:, 0]] ** 2 + residual[edges.pairs[:, 1]] ** 2) / 2
    total_weight = float(weight.sum())
    before = float(np.sqrt(score.sum() / total_weight))
    spacing = median / 4 if min_spacing is None else float(min_spacing)
    rows = fold_rows(samples, folds, median) if folds and grid else []
    if rows:        # each spot's change: the mean share of its edges (a fold gap's share)
        spot_change = (np.bincount(edges.pairs.ravel(), weights=np.repeat(score, 2), minlength=len(samples))
                       / np.maximum(np.bincount(edges.pairs.ravel(), minlength=len(samples)), 1))
    # the edges within a fold's rows (along it, and across it from row to row), and any edge
    # across the fold (a row's spot to the far side's next row), are split by the fold's pairs
    in_rows = np.zeros(len(edges.pairs), bool)
    for row in rows:
        member = np.zeros(len(samples), bool)
        member[list(row.side)] = True
        in_rows |= member[edges.pairs[:, 0]] & member[edges.pairs[:, 1]]
        if not row.on_fold:
            in_rows |= row.crosses(samples, edges.pairs)
    points = list(samples)                        # the spots, then the targets as they are placed
    # a heap on (class: fold gaps first, -gain of the entry's two beams, tie-break, kind, entry)
    tie = itertools.count()                       # unique: the entries themselves are never compared
    # a line's edges split in thirds (two beams, 2/3 of the share), a grid's at the middle
    # (one beam, half of it): module doc
    split, first = ("halves", 1 / 2) if grid else ("thirds", 2 / 3)
    heap = [(1, -first * float(s), next(tie), split, (int(a), int(b)))
            for n, (s, (a, b)) in enumerate(zip(score, edges.pairs)) if s > 0 and not in_rows[n]]
    for f, row in enumerate(rows):
        for t0, t1 in zip(row.stations[:-1], row.stations[1:]):
            s = _gap_score(row, t0, t1, spot_change, median)
            if s > 0:
                heap.append((_fold_class(t1 - t0, median, row), -s / 2, next(tie), "fold", (f, t0, t1, s)))
    heapq.heapify(heap)
    tree, targets, gains = cKDTree(samples), [], []
    remaining = float(score.sum())
    pairs = 0
    while heap and len(targets) < count:
        _, neg, _, kind, entry = heapq.heappop(heap)
        gain = -neg
        if kind == "halves":
            a, b = entry
            s = 2 * gain
            new = [(points[a] + points[b]) / 2]
            if np.linalg.norm(points[a] - points[b]) / 2 < spacing:
                continue
        elif kind == "thirds":
            a, b = entry
            s = 3 * gain / 2
            new = [points[a] + (points[b] - points[a]) * f for f in (1 / 3, 2 / 3)]
            if np.linalg.norm(points[a] - points[b]) / 3 < spacing:
                continue
        else:
            f, t0, t1, s = entry
            row = rows[f]
            if (t1 - t0) / 2 < spacing:
                continue
            new = row.pair((t0 + t1) / 2)
        if len(targets) + len(new) > count:      # a pair where one beam is left
            continue
        if covered is not None and not bool(np.all(covered(np.array(new)))):
            continue
        if any(tree.query(t)[0] < spacing * (1 - 1e-9) or any(np.hypot(*(t - q)) < spacing for q in targets)
               for t in new):
            continue
        n = len(points)
        points.extend(new)
        targets.extend(new)
        gains.extend([gain / len(new)] * len(new))
        remaining -= gain
        if kind == "halves":
            for x, y in ((a, n), (n, b)):          # each half keeps a quarter of the share
                heapq.heappush(heap, (1, -s / 8, next(tie), "halves", (x, y)))
        elif kind == "thirds":
            for x, y in ((a, n), (n, n + 1), (n + 1, b)):
                heapq.heappush(heap, (1, -2 * s / 27, next(tie), "thirds", (x, y)))
        else:
            pairs += 1
            middle = (t0 + t1) / 2
            for u0, u1 in ((t0, middle), (middle, t1)):
                heapq.heappush(heap, (_fold_class(u1 - u0, median, row), -s / 8, next(tie), "fold", (f, u0, u1, s / 4)))
    after = float(np.sqrt(max(remaining, 0.0) / total_weight))
    return Placement(targets=np.array(targets).reshape(-1, 2), gain=np.array(gains) / total_weight,
                     before=before, after=after, residual=residual, fold_pairs=pairs)


def _fold_class(gap: float, spacing: float, row: FoldRows) -> int:
    """0 (before every edge) for a gap along a fold wider than :data:`FOLD_SPACING` of the
    scan's spacing, else 1 (ranked with the edges by its gain); 1 always when the fold's
    rows are on it (``row.on_fold``)."""
    return 0 if gap > FOLD_SPACING * spacing * (1 + 1e-9) and not row.on_fold else 1


def _gap_score(row: FoldRows, t0: float, t1: float, spot_change, spacing: float) -> float:
    """The share of a gap between two stations along a fold: the two edges along it (one
    each side), each the mean share of the edges of the rows' spots at the gap's ends, by
    the gap's length in spacings squared (a halved gap keeps a quarter each half)."""
    ends = [k for k, t in row.place.items() if min(abs(t - t0), abs(t - t1)) < spacing / 4]
    if not ends:
        return 0.0
    return 2 * ((t1 - t0) / spacing) ** 2 * float(np.mean(spot_change[ends]))
