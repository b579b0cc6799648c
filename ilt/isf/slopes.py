"""Slopes for the fine operator's flat cells, from their neighbours' means (docs/fullres.md,
"Flat cells take their neighbours' slope").

A cell the build keeps flat (:class:`ilt.isf.fine.FineAccumulator`: its plane explains too
little of the frames' variation, or no more than their noise would) models the indirect
light across it as its mean. Where the light has a gradient over a surface (the box's faces,
which curve towards the creases) every flat cell then shows the same ramp of error, which
only a denser scan shrinks. But the field being spread, ``Phi_n``, is known cell by cell:
its cell means ``r_(n+1)[i] / area_i`` come from the sample-level recursion. Its gradient
across a flat cell is read from the means of the cells about it, as a finite-volume
scheme reconstructs a piecewise-linear field from cell averages (Barth & Jespersen, "The
design and application of upwind schemes on unstructured meshes", AIAA 89-0366):

1. **Gradient**: the least-squares plane through the neighbours' means, weighted by
   ``1 / d^2`` (``d``: the distance between the cells' centroids), through the cell's own
   mean; neighbours are cells that share a pixel edge.
2. **Limiter** (Barth-Jespersen): the gradient is scaled down, by one factor per cell and
   channel, until the plane stays, on every pixel of the cell, between the smallest and
   largest mean of the cell and its neighbours. On a linear ramp the factor is 1 (a cell's
   pixels reach half the way to its neighbours' centroids); at a peak or a valley of the
   field, and where the cell ends the light (no neighbour beyond), it is 0: the cell stays
   flat there, as before; at a jump it cannot overshoot what either side holds.
3. **Not across a fold**: a neighbour on the far side of one of the build's fold lines
   (:func:`ilt.isf.fold_transfer.recorded_lines`; the line between the two centroids crosses
   it) still bounds the plane, but gives it no gradient. Indirect light peaks at a concave
   fold from both sides and steps across it; read into the gradient, the step tilted the
   cells beside the fold. Beside a 3D fold (a crease of a room, not a flatland scene's) the
   bounds also take in the cell's own side carried on past it, ``2 mean - (its side's
   lowest mean)`` above and the same below: there the light still rises to the crease, and
   a cell brighter than every neighbour of its side, bounded by them, stayed flat
   (docs/fullres.md, "Not across a fold").

The plane is added about the cell's centroid in the fine basis (``dx``, ``dy`` in units of
the cell's size, :meth:`ilt.isf.fine.CellGeometry.basis`), so it sums to zero over the
cell and the full-resolution images still integrate to the sample-level bounces.

The plane's extremes over a cell's pixels are bounded by its **support** in eight
directions (multiples of 45 degrees), precomputed once: a gradient between two of them is
a non-negative sum of the two, so its maximum over the pixels is at most the same sum of
their supports (exact for a rectangle; larger, so the limiter is safe, for other shapes).

Measured in docs/fullres.md: on noisy frames (2e4 e-) the box's full-resolution error falls
5-16% at every density; flatland scenes within 2% either way.
"""

from __future__ import annotations

import numpy as np

#: the eight directions of the support, counter-clockwise from +x; consecutive ones
#: (cyclically) span the cones a gradient is split over
DIRECTIONS = np.array([(1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1)], np.float64)
#: singular values of a cell's least-squares system below this share of its largest are
#: dropped: a row of cells (a flatland scan) gets no gradient across the row
RCOND = 1e-2


def _cone_inverses() -> np.ndarray:
    """(8, 2, 2): for cone k (between DIRECTIONS[k] and [k + 1]) the matrix whose product
    with a gradient gives its two non-negative weights on them."""
    return np.stack([np.linalg.inv(np.stack([DIRECTIONS[k], DIRECTIONS[(k + 1) % 8]], axis=1))
                     for k in range(8)])


_CONES = _cone_inverses()


def crosses(a: np.ndarray, b: np.ndarray, segments) -> np.ndarray:
    """(e,) bool: the segment from ``a[k]`` to ``b[k]`` ((e, 2) points) crosses one of
    ``segments`` ((start, end) pairs of points), the two ends strictly on either side."""
    a, b = np.asarray(a, np.float64).reshape(-1, 2), np.asarray(b, np.float64).reshape(-1, 2)
    out = np.zeros(len(a), bool)

    def side(p, q, r):                        # sign of (q - p) x (r - p)
        return np.sign((q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1])
                       - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0]))

    for start, end in segments:
        p, q = np.asarray(start, np.float64), np.asarray(end, np.float64)
        out |= (side(p, q, a) * side(p, q, b) < 0) & (side(a, b, p) * side(a, b, q) < 0)
    return out


class NeighbourSlopes:
    """The limited least-squares slopes of flat cells (module docstring).

    geometry : a :class:`ilt.isf.fine.CellGeometry`; flat : (m,) bool, the cells that get
    a slope (the others get 0: theirs is in the fine coefficients); basis : its degree-1
    basis ``dx, dy`` (2, n) when the caller has it; folds : the scene's fold lines, (start,
    end) pixel pairs, or (start, end, solid) with ``solid`` True at a 3D fold: a neighbour
    across one (the line between the two centroids crosses it) bounds the plane but gives it no
    gradient, and beside a 3D fold the bound also takes in the cell's own side's ramp carried
    on past it (module docstring, 3).
    """

    def __init__(self, geometry, flat: np.ndarray, basis: np.ndarray | None = None, folds=()):
        m, (height, width) = geometry.m, geometry.shape
        self.m, self.flat = m, np.asarray(flat, bool)
        labels = np.full(height * width, -1, np.int64)
        labels[geometry.inside] = geometry.label
        labels = labels.reshape(height, width)
        pairs = []
        for a, b in ((labels[:, :-1], labels[:, 1:]), (labels[:-1], labels[1:])):
            edge = (a >= 0) & (b >= 0) & (a != b)
            pairs.append(np.stack([np.minimum(a[edge], b[edge]), np.maximum(a[edge], b[edge])], axis=1))
        pairs = np.unique(np.concatenate(pairs), axis=0) if sum(p.shape[0] for p in pairs) else np.empty((0, 2), int)
        # both directions of every edge, only edges into a flat cell (the others' slopes are not used)
        i, j = np.concatenate([pairs[:, 0], pairs[:, 1]]), np.concatenate([pairs[:, 1], pairs[:, 0]])
        keep = self.flat[i]
        # the limiter's bounds: every neighbour; the gradient: the neighbours on the cell's side of every fold
        self.bound_i, self.bound_j = i[keep], j[keep]
        across = np.zeros(i.size, bool)
        solid = np.zeros(i.size, bool)        # across a 3D fold
        for fold in folds:                     # each edge tested once a line
            hit = crosses(geometry.centre[i], geometry.centre[j], [tuple(fold)[:2]])
            across |= hit
            if len(fold) > 2 and fold[2]:
                solid |= hit
        self.beside_solid = np.bincount(i[keep & solid], minlength=m) > 0
        keep &= ~across
        self.i, self.j = i[keep], j[keep]
        # in the basis' units: positions over the cell's size (the gradient comes out as coefficients)
        size = geometry.size
        self.d = (geometry.centre[self.j] - geometry.centre[self.i]) / size[self.i][:, None]
        self.w = 1.0 / np.maximum((self.d * self.d).sum(axis=1), 1e-12)
        A = np.zeros((m, 2, 2))
        for a in range(2):
            for b in range(2):
                A[:, a, b] = np.bincount(self.i, self.w * self.d[:, a] * self.d[:, b], m)
        self.A_inv = np.linalg.pinv(A, rcond=RCOND, hermitian=True)
        # support of every cell's pixels in the eight directions, basis units
        B = geometry.basis(1) if basis is None else basis[:2]
        self.support = np.zeros((m, 8))
        for k, u in enumerate(DIRECTIONS):
            np.maximum.at(self.support[:, k], geometry.label, u[0] * B[0] + u[1] * B[1])

    def _reach(self, grad: np.ndarray) -> np.ndarray:
        """(m, c) an upper bound of the plane ``grad`` (m, 2, c) over each cell's pixels."""
        angle = np.mod(np.arctan2(grad[:, 1], grad[:, 0]), 2 * np.pi)
        cone = np.minimum((angle // (np.pi / 4)).astype(np.int64), 7)               # (m, c)
        weights = np.einsum("mcab,mbc->mac", _CONES[cone], grad)                   # (m, 2, c), >= 0
        first = np.take_along_axis(self.support, cone, axis=1)
        second = np.take_along_axis(self.support, (cone + 1) % 8, axis=1)
        return np.maximum(weights[:, 0], 0.0) * first + np.maximum(weights[:, 1], 0.0) * second

    def coefficients(self, means: np.ndarray) -> np.ndarray:
        """(2, m, c) float64 ``dx``, ``dy`` coefficients of each flat cell's plane, for the
        field whose cell means are ``means`` (m, c); 0 for the other cells."""
        means = np.asarray(means, np.float64)
        c = means.shape[1]
        out = np.zeros((2, self.m, c))
        if self.bound_i.size == 0:
            return out
        diff = means[self.j] - means[self.i]                                        # (e, c)
        rhs = np.stack([np.stack([np.bincount(self.i, self.w * self.d[:, a] * diff[:, k], self.m)
                                  for k in range(c)], axis=1) for a in range(2)], axis=1)   # (m, 2, c)
        grad = np.einsum("mab,mbc->mac", self.A_inv, rhs)
        high, low = means.copy(), means.copy()
        np.maximum.at(high, self.bound_i, means[self.bound_j])
        np.minimum.at(low, self.bound_i, means[self.bound_j])
        if self.beside_solid.any():      # beside a 3D fold: as far again as its own side's neighbours
            side_high, side_low = means.copy(), means.copy()
            np.maximum.at(side_high, self.i, means[self.j])
            np.minimum.at(side_low, self.i, means[self.j])
            at = self.beside_solid
            high[at] = np.maximum(high[at], 2 * means[at] - side_low[at])
            low[at] = np.minimum(low[at], 2 * means[at] - side_high[at])
        up, down = self._reach(grad), self._reach(-grad)                            # above / below the mean
        with np.errstate(divide="ignore", invalid="ignore"):
            limit = np.minimum(np.where(up > 0, (high - means) / up, 1.0),
                               np.where(down > 0, (means - low) / down, 1.0))
        grad *= np.clip(np.nan_to_num(limit, nan=0.0), 0.0, 1.0)[:, None, :]
        grad[~self.flat] = 0.0
        return grad.transpose(1, 0, 2)


__all__ = ["NeighbourSlopes", "DIRECTIONS", "crosses"]
