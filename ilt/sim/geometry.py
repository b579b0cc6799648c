"""Patch geometry of the synthetic scenes: the flatland M (paper Fig. 3), the M
under a floating plank, and three inside faces of a box (paper Fig. 7).

A :class:`Geometry` holds *every* patch that takes part in the transport, hidden
ones included, with exact form factors; which patches the camera sees, and where,
is part of it too.  Scene coordinates are unitless lengths; flatland is the
(x, y) plane with y up, the box is the unit cube corner with z up.
"""

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.linalg
from scipy.spatial.distance import pdist

from .formfactors import _TOL, flatland_exchange, rays_blocked, rectangle_exchange, segment_normals

#: Vertices of the flatland M (paper Fig. 3): high outer ends, a lower middle peak,
#: two valleys.  Facets 0 and 2 are parallel, as are 1 and 3, so facet 0 lights
#: facets 1 and 3 only (facet 3 over the middle peak, partly hidden by it).
M_VERTICES = np.array([[0.0, 2.0], [1.0, 0.0], [2.0, 1.2], [3.0, 0.0], [4.0, 2.0]])

#: The occluder of the "occluded" scene: a two-sided plank at height 1.7 over
#: x in [1.5, 2.5], above the middle peak and below the outer ends of the M.
PLANK = np.array([[1.5, 1.7], [2.5, 1.7]])

#: Pixels of empty frame around the samples.
_MARGIN = 8


@dataclass(frozen=True)
class Geometry:
    """All N patches of a scene and their exact diffuse transport.

    Fields:
        centre: (N, d) float64 patch centres, d = 2 (flatland) or 3.
        normal: (N, d) float64 unit front normals.
        area: (N,) float64 patch areas (lengths in flatland).
        facet: (N,) int planar facet of each patch.
        albedo: (N,) float64 Lambertian albedo rho in [0, 1].
        form_factors: (N, N) float64 F[i, j], fraction of the energy leaving i that
            arrives at j; area_i F[i, j] is symmetric, rows sum to <= 1.
        visible: (m,) int patches the camera sees, in the order of the sample points.
        occluders: flatland (S, 2, 2) float64 segments; 3D (S, 2, 3) float64
            (lo, hi) corners of axis-aligned rectangles.  They cast shadows.
    """

    centre: np.ndarray
    normal: np.ndarray
    area: np.ndarray
    facet: np.ndarray
    albedo: np.ndarray
    form_factors: np.ndarray
    visible: np.ndarray
    occluders: np.ndarray

    @property
    def dim(self) -> int:
        return self.centre.shape[1]

    @cached_property
    def hidden(self) -> np.ndarray:
        """(N - m,) int patches that take part in the transport but have no sample."""
        return np.setdiff1d(np.arange(len(self.area)), self.visible)

    @cached_property
    def transport(self) -> np.ndarray:
        """(N, N) float64 full transport A_full[i, j] = rho_i F[i, j] (paper Eq. 14, C1 = I - P K)."""
        return self.albedo[:, None] * self.form_factors

    @cached_property
    def _hidden_solve(self):
        a_hh = self.transport[np.ix_(self.hidden, self.hidden)]
        return scipy.linalg.lu_factor(np.eye(len(self.hidden)) - a_hh)

    def _through_hidden(self, x_h: np.ndarray) -> np.ndarray:
        """A_vh (I - A_hh)^-1 x_h: light that reaches the visible set only via hidden patches."""
        if len(self.hidden) == 0:
            return np.zeros((len(self.visible), *x_h.shape[1:]))
        a_vh = self.transport[np.ix_(self.visible, self.hidden)]
        return a_vh @ scipy.linalg.lu_solve(self._hidden_solve, x_h)

    @cached_property
    def collapsed(self) -> tuple[np.ndarray, np.ndarray]:
        """The transport among visible points with hidden bounces collapsed (paper Sec. 3.1.2).

        A' = A_vv + A_vh (I - A_hh)^-1 A_hv; light that leaves a visible point and comes
        back to it through hidden ones counts as direct, so with g = 1 / (1 - diag A'):
        returns (A, g), A = diag(g) offdiag(A') (m, m) float64 with zero diagonal, g (m,).
        """
        v, h = self.visible, self.hidden
        a_prime = self.transport[np.ix_(v, v)] + self._through_hidden(self.transport[np.ix_(h, v)])
        gain = 1.0 / (1.0 - np.diag(a_prime))
        a = gain[:, None] * a_prime
        np.fill_diagonal(a, 0.0)
        return a, gain

    def fold(self, direct_full: np.ndarray) -> np.ndarray:
        """Collapsed direct light L1 = g (L1_v + A_vh (I - A_hh)^-1 L1_h) (paper Sec. 3.1.2).

        Parameters: direct_full (N,) or (N, k) float64 direct radiosity of all patches.
        Returns: (m,) or (m, k) float64, with ``(I - A)^-1 L1 = [(I - A_full)^-1 L1_full]_v``.
        """
        gain = self.collapsed[1].reshape(-1, *([1] * (direct_full.ndim - 1)))
        return gain * (direct_full[self.visible] + self._through_hidden(direct_full[self.hidden]))

    def blocked(self, p: np.ndarray, q: np.ndarray) -> np.ndarray:
        """(...,) bool: whether an occluder properly cuts the segment between points p and q (..., d)."""
        if self.dim == 2:
            return rays_blocked(p, q, self.occluders)
        out = np.zeros(np.broadcast_shapes(p.shape, q.shape)[:-1], dtype=bool)
        for lo, hi in self.occluders:
            axis = int(np.argmin(hi - lo))
            dp = q[..., axis] - p[..., axis]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (lo[axis] - p[..., axis]) / dp
            hit = p + t[..., None] * (q - p)
            inside = np.all((hit > lo + _TOL) & (hit < hi - _TOL) | (np.arange(3) == axis), axis=-1)
            out |= (np.abs(dp) > _TOL) & (t > _TOL) & (t < 1 - _TOL) & inside
        return out


def _subdivide(p: np.ndarray, q: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    t = np.linspace(0.0, 1.0, count + 1)[:, None]
    ends = p + t * (q - p)
    return ends[:-1], ends[1:]


def _flatland(p0: np.ndarray, p1: np.ndarray, facet: np.ndarray, occluders: np.ndarray,
              surface: np.ndarray, visible: np.ndarray, albedo: float):
    length = np.linalg.norm(p1 - p0, axis=1)
    k = flatland_exchange(p0, p1, occluders, surface)
    centre = 0.5 * (p0 + p1)
    visible = visible[np.argsort(centre[visible, 0], kind="stable")]
    geometry = Geometry(centre=centre, normal=segment_normals(p0, p1), area=length, facet=facet,
                        albedo=np.full(len(length), albedo), form_factors=k / length[:, None],
                        visible=visible, occluders=occluders)
    # Orthographic camera looking down: pixel column from x, at least 2 pixels apart.
    x = centre[visible, 0]
    scale = 2.0 / np.diff(x).min()
    x_min, x_max = occluders[..., 0].min(), occluders[..., 0].max()
    cols = _MARGIN + np.round(scale * (x - x_min))
    samples = np.stack([cols, np.full_like(cols, _MARGIN)], axis=1)
    frame_shape = (2 * _MARGIN + 1, 2 * _MARGIN + 1 + int(np.ceil(scale * (x_max - x_min))))
    return geometry, samples, frame_shape, (1, len(visible))


def m_geometry(per_facet: int, albedo: float):
    """The flatland M: 4 facets of ``per_facet`` equal patches; all 4 * per_facet seen from above."""
    ends = [_subdivide(M_VERTICES[f], M_VERTICES[f + 1], per_facet) for f in range(4)]
    p0 = np.concatenate([e[0] for e in ends])
    p1 = np.concatenate([e[1] for e in ends])
    facet = np.repeat(np.arange(4), per_facet)
    occluders = np.stack([M_VERTICES[:-1], M_VERTICES[1:]], axis=1)
    return _flatland(p0, p1, facet, occluders, facet, np.arange(len(p0)), albedo)


def occluded_geometry(per_facet: int, plank_patches: int, albedo: float):
    """The M (``per_facet`` patches a facet, even) under the two-sided :data:`PLANK`.

    Facets 0-3 are the M, facet 4 the plank's top (seen) and facet 5 its underside
    (hidden).  The camera looks down, so terrain under the plank (x in [1.5, 2.5],
    half of facets 1 and 2) is hidden; the rest of the M and the plank's top are seen:
    m = 3 per_facet + plank_patches points of N = 4 per_facet + 2 plank_patches patches.
    """
    top = _subdivide(PLANK[0], PLANK[1], plank_patches)
    under = _subdivide(PLANK[1], PLANK[0], plank_patches)
    ends = [_subdivide(M_VERTICES[f], M_VERTICES[f + 1], per_facet) for f in range(4)] + [top, under]
    p0 = np.concatenate([e[0] for e in ends])
    p1 = np.concatenate([e[1] for e in ends])
    facet = np.repeat(np.arange(6), [per_facet] * 4 + [plank_patches] * 2)
    occluders = np.concatenate([np.stack([M_VERTICES[:-1], M_VERTICES[1:]], axis=1), PLANK[None]])
    surface = np.minimum(facet, 4)
    x = 0.5 * (p0[:, 0] + p1[:, 0])
    under_plank = (facet < 4) & (x > PLANK[0, 0]) & (x < PLANK[1, 0])
    visible = np.nonzero(~under_plank & (facet != 5))[0]
    return _flatland(p0, p1, facet, occluders, surface, visible, albedo)


#: Box camera: perspective, from here towards the corner at the origin, z up.
BOX_EYE = np.array([2.5, 2.5, 2.0])

#: Box faces as seen left to right: (normal axis, row axis, column axis, column reversed).
#: Rows run from z = 1 down on the walls, along x on the floor.
_BOX_FACES = ((1, 2, 0, True), (2, 0, 1, False), (0, 2, 1, False))


def box_geometry(n: int, albedo: float):
    """Three inside faces of the unit cube's corner (walls y = 0, floor z = 0, wall x = 0), n x n patches each.

    Points are in scanline order of the (3n, n) layout: the three faces stacked,
    left wall y = 0, floor, right wall x = 0, so T has 3 x 3 blocks of n^2 x n^2,
    one per pair of faces (paper Fig. 8).  Form
    factors are exact (:func:`rectangle_exchange`); the faces never occlude each other.
    """
    cells = (np.arange(n) + 0.5) / n
    faces, rows, cols = np.meshgrid(np.arange(3), np.arange(n), np.arange(n), indexing="ij")
    rows, faces, cols = rows.ravel(), faces.ravel(), cols.ravel()
    centre = np.zeros((3 * n * n, 3))
    normal_axis = np.array([_BOX_FACES[f][0] for f in faces])
    for f, (_, row_axis, col_axis, reverse) in enumerate(_BOX_FACES):
        sel = faces == f
        centre[sel, row_axis] = cells[::-1][rows[sel]] if row_axis == 2 else cells[rows[sel]]
        centre[sel, col_axis] = cells[::-1][cols[sel]] if reverse else cells[cols[sel]]
    half = np.full((len(centre), 3), 0.5 / n)
    half[np.arange(len(centre)), normal_axis] = 0.0
    lo, hi = centre - half, centre + half
    sign = np.ones(len(centre), dtype=int)
    k = np.zeros((len(centre), len(centre)))
    for f in range(3):
        for g in range(f + 1, 3):
            i, j = np.nonzero(faces == f)[0], np.nonzero(faces == g)[0]
            block = rectangle_exchange((normal_axis[i], sign[i], lo[i], hi[i]),
                                       (normal_axis[j], sign[j], lo[j], hi[j]))
            k[np.ix_(i, j)] = block
            k[np.ix_(j, i)] = block.T
    area = np.full(len(centre), 1.0 / n**2)
    occluders = np.array([[[0, 0, 0], [1, 0, 1]], [[0, 0, 0], [1, 1, 0]], [[0, 0, 0], [0, 1, 1]]], dtype=float)
    geometry = Geometry(centre=centre, normal=np.eye(3)[normal_axis], area=area, facet=faces,
                        albedo=np.full(len(centre), albedo), form_factors=k / area[:, None],
                        visible=np.arange(len(centre)), occluders=occluders)
    samples, frame_shape = _perspective_samples(centre, occluders.reshape(-1, 3))
    return geometry, samples, frame_shape, (3 * n, n)


def _perspective_samples(points: np.ndarray, extent: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
    """Integer pixels (m, 2) of ``points`` seen from :data:`BOX_EYE`, at least 2 pixels apart, and the frame (H, W) holding ``extent``."""
    forward = -BOX_EYE / np.linalg.norm(BOX_EYE)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)

    def project(p):
        rel = p - BOX_EYE
        depth = rel @ forward
        return np.stack([rel @ right / depth, -(rel @ up) / depth], axis=1)

    uv = project(points)
    corners = np.vstack([project(extent), uv])   # rounding puts a point near an edge a pixel past it
    scale = 2.0 / pdist(uv).min()
    origin = corners.min(axis=0)
    samples = _MARGIN + np.round(scale * (uv - origin))
    size = np.ceil(scale * (corners.max(axis=0) - origin)).astype(int) + 2 * _MARGIN + 1
    if len(np.unique(samples, axis=0)) != len(samples):
        raise RuntimeError("box camera: two sample points fall on one pixel")
    return samples, (int(size[1]), int(size[0]))
