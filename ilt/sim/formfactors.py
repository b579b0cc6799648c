"""Exact diffuse form factors between patches.

Flatland: Hottel's crossed strings, with visibility sampled on sub-segments where
something may stand between two patches.  3D: the contour-integral (Stokes) form
for axis-aligned rectangles, in closed form.

Both return the *exchange* ``K[i, j] = area_i F[i, j]`` (in flatland the area is a
length), which is symmetric by reciprocity; ``F[i, j] = K[i, j] / area_i`` is the
fraction of the energy leaving patch i that arrives at patch j, the ``K`` of paper
Eq. (14) (``C1 = I - P K``).
"""

import numpy as np

#: Tolerance (scene units squared) below which a signed area counts as zero.
_TOL = 1e-10


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _dist(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    return np.linalg.norm(p - q, axis=-1)


def crossed_strings(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Hottel's crossed-strings exchange between flatland segments ab and cd.

    Parameters: a, b, c, d: (..., 2) float64 endpoints, broadcastable.
    Returns: (...,) float64 ``K = |ab| F = |(|ac| + |bd|) - (|ad| + |bc|)| / 2``, the
    crossed pair minus the uncrossed pair (Hottel 1954).  Exact for two segments
    that face each other with nothing between them; meaningless otherwise.
    """
    return 0.5 * np.abs(_dist(a, c) + _dist(b, d) - _dist(a, d) - _dist(b, c))


def segment_normals(p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """Unit front normals (N, 2): the direction p0 -> p1 turned 90 degrees counter-clockwise."""
    t = p1 - p0
    return np.stack([-t[:, 1], t[:, 0]], axis=1) / np.linalg.norm(t, axis=1)[:, None]


def rays_blocked(p: np.ndarray, q: np.ndarray, occluders: np.ndarray) -> np.ndarray:
    """Whether the open segment p -> q properly crosses any occluder segment.

    Parameters: p, q: (..., 2) float64 ray ends; occluders: (S, 2, 2) float64 segments.
    Returns: (...,) bool.  Touching (a ray that starts or ends on an occluder, or
    grazes an endpoint) does not block, so a patch never shadows itself.
    """
    blocked = np.zeros(np.broadcast_shapes(p.shape, q.shape)[:-1], dtype=bool)
    pq = q - p
    for u, v in occluders:
        o1, o2 = _cross(pq, u - p), _cross(pq, v - p)
        o3, o4 = _cross(v - u, p - u), _cross(v - u, q - u)
        blocked |= (((o1 > _TOL) & (o2 < -_TOL)) | ((o1 < -_TOL) & (o2 > _TOL))) \
            & (((o3 > _TOL) & (o4 < -_TOL)) | ((o3 < -_TOL) & (o4 > _TOL)))
    return blocked


def _clip_to_front(p: np.ndarray, q: np.ndarray, origin: np.ndarray, normal: np.ndarray):
    """The part of segments p -> q (P, 2) in front of the lines through ``origin`` with ``normal`` (P, 2)."""
    sp = np.einsum("pk,pk->p", normal, p - origin)[:, None]
    sq = np.einsum("pk,pk->p", normal, q - origin)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        cut = p + (q - p) * sp / (sp - sq)
    return np.where(sp < 0, cut, p), np.where(sq < 0, cut, q)


def _any_inside_quad(points: np.ndarray, a, b, c, d) -> np.ndarray:
    """(...,) bool: whether any of ``points`` (V, 2) lies strictly inside the convex quadrilateral a, b, c, d (..., 2), counter-clockwise."""
    inside = np.zeros(np.broadcast_shapes(a.shape, b.shape, c.shape, d.shape)[:-1], dtype=bool)
    for v in points:
        inside |= ((_cross(b - a, v - a) > _TOL) & (_cross(c - b, v - b) > _TOL)
                   & (_cross(d - c, v - c) > _TOL) & (_cross(a - d, v - d) > _TOL))
    return inside


def flatland_exchange(p0: np.ndarray, p1: np.ndarray, occluders: np.ndarray,
                      surface: np.ndarray, subdivisions: int = 6) -> np.ndarray:
    """Symmetric exchange matrix ``K[i, j] = L_i F[i, j]`` between flatland patches.

    Parameters:
        p0, p1: (N, 2) float64 patch endpoints; the front side is to the left of
            p0 -> p1 (:func:`segment_normals`).
        occluders: (S, 2, 2) float64 segments that may block light (the facets).
        surface: (N,) int, index into ``occluders`` of the segment patch i lies on;
            a patch's own segment never blocks it (touching does not count).
        subdivisions: sub-segments per patch where visibility must be sampled.
    Returns: (N, N) float64 K, exactly symmetric, zero diagonal.

    Only the part of patch i in front of patch j's line exchanges light with the
    part of j in front of i's line, so each pair is first clipped to those parts;
    with nothing between them their crossed strings are exact.  Pairs whose
    bounding box meets another occluder are split into ``subdivisions`` sub-segments
    each (unless nothing enters the pair's own hull); a sub-pair contributes its
    exact crossed strings if nothing enters the convex hull of its two
    sub-segments, else nothing.  So K is exact where the view is clear and errs
    low only by the sub-pairs that are partly visible: rows of F never sum above 1
    (up to rounding).  The test is symmetric in i and j, so reciprocity is exact.
    """
    n_patch = len(p0)
    normal = segment_normals(p0, p1)
    length = np.linalg.norm(p1 - p0, axis=1)

    offset = np.einsum("ik,ik->i", normal, p0)[:, None]
    side0 = normal @ p0.T - offset      # [i, j]: p0_j relative to the line of i
    side1 = normal @ p1.T - offset
    some_front = np.maximum(side0, side1) > _TOL * length[:, None]
    exchange = np.triu(some_front & some_front.T, 1)

    box_lo, box_hi = np.minimum(p0, p1), np.maximum(p0, p1)
    occ_lo, occ_hi = occluders.min(axis=1), occluders.max(axis=1)
    pair_lo = np.minimum(box_lo[:, None], box_lo[None])
    pair_hi = np.maximum(box_hi[:, None], box_hi[None])
    maybe_blocked = np.zeros((n_patch, n_patch), dtype=bool)
    for o in range(len(occluders)):
        own = (surface == o)
        overlap = np.all((occ_lo[o] < pair_hi) & (pair_lo < occ_hi[o]), axis=-1)
        maybe_blocked |= overlap & ~own[:, None] & ~own[None]

    i, j = np.nonzero(exchange)
    a, b = _clip_to_front(p0[i], p1[i], p0[j], normal[j])
    c, d = _clip_to_front(p0[j], p1[j], p0[i], normal[i])
    k = np.zeros((n_patch, n_patch))
    k[i, j] = crossed_strings(a, b, c, d)

    vertices = np.unique(occluders.reshape(-1, 2), axis=0)

    def hull_clear(a, b, c, d):
        # Segments that face each other span the convex quadrilateral a, b, c, d; no
        # occluder crosses a patch, so one that enters must cross a side string b-c or
        # d-a, or end inside.
        return ~(rays_blocked(b, c, occluders) | rays_blocked(d, a, occluders)
                 | _any_inside_quad(vertices, a, b, c, d))

    refine = np.nonzero(maybe_blocked[i, j])[0]
    refine = refine[~hull_clear(a[refine], b[refine], c[refine], d[refine])]
    t = np.linspace(0.0, 1.0, subdivisions + 1)[:, None]
    chunk = max(1, 2**19 // subdivisions**2)
    for start in range(0, len(refine), chunk):
        r = refine[start:start + chunk]
        ends_i = a[r, None] + t * (b[r] - a[r])[:, None]       # (P, s+1, 2)
        ends_j = c[r, None] + t * (d[r] - c[r])[:, None]
        sa, sb = ends_i[:, :-1, None], ends_i[:, 1:, None]      # (P, s, 1, 2)
        sc, sd = ends_j[:, None, :-1], ends_j[:, None, 1:]      # (P, 1, s, 2)
        clear = hull_clear(sa, sb, sc, sd)
        k[i[r], j[r]] = np.where(clear, crossed_strings(sa, sb, sc, sd), 0.0).sum(axis=(1, 2))
    return k + k.T


# --------------------------------------------------------------------------- 3D


def _log_kernel_antiderivative(u: np.ndarray, d: np.ndarray) -> np.ndarray:
    """H(u) with H''(u) = ln sqrt(u^2 + d^2): (u^2 - d^2)/4 ln(u^2 + d^2) + d u atan(u/d) - 3u^2/4.

    Defined by continuity at d = 0 and at u = d = 0 (both give 0 for the log term).
    """
    w = u * u + d * d
    log_term = np.where(w > 0, 0.25 * (u * u - d * d) * np.log(np.where(w > 0, w, 1.0)), 0.0)
    return log_term + d * u * np.arctan2(u, d) - 0.75 * u * u


def rectangle_edges(normal_axis: np.ndarray, normal_sign: np.ndarray,
                    lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Directed boundary edges of axis-aligned rectangles, counter-clockwise seen from the front.

    Parameters: normal_axis (N,) int in {0,1,2}; normal_sign (N,) +1/-1 (front side);
        lo, hi: (N, 3) float64 corners (lo == hi along the normal axis).
    Returns: axis (N, 4) int, the axis each edge runs along; start, end (N, 4, 3) float64.
    """
    n_rect = len(normal_axis)
    p = (normal_axis + 1) % 3
    q = (normal_axis + 2) % 3
    rows = np.arange(n_rect)
    corners = np.repeat(lo[:, None, :], 4, axis=1)       # (p_lo,q_lo),(p_hi,q_lo),(p_hi,q_hi),(p_lo,q_hi)
    corners[rows, 1, p] = hi[rows, p]
    corners[rows, 2, p] = hi[rows, p]
    corners[rows, 2, q] = hi[rows, q]
    corners[rows, 3, q] = hi[rows, q]
    start, end = corners, np.roll(corners, -1, axis=1)
    flip = normal_sign < 0
    start[flip], end[flip] = end[flip], start[flip].copy()
    axis = np.stack([p, q, p, q], axis=1)
    return axis, start, end


def rectangle_exchange(rects_i: tuple, rects_j: tuple) -> np.ndarray:
    """Exchange ``K[i, j] = area_i F[i, j]`` between axis-aligned rectangles, in closed form.

    Parameters: rects_i, rects_j: tuples ``(normal_axis, normal_sign, lo, hi)`` as in
        :func:`rectangle_edges`, with N_i and N_j rectangles.
    Returns: (N_i, N_j) float64.

    Stokes' theorem turns the area integral into ``area_i F_ij = (1/2pi) sum over
    edge pairs of the double line integral of ln r (dr_i . dr_j)`` (Sparrow 1963),
    with both contours counter-clockwise seen from the front.  Only parallel
    edges contribute; for two parallel lines at distance d the double integral
    of ln r is ``H(b1-a2) - H(a1-a2) - H(b1-b2) + H(a1-b2)``
    (:func:`_log_kernel_antiderivative`), exact also for collinear edges (d = 0)
    such as those along a shared corner.  Valid for rectangles that see each other
    whole (no occlusion, each entirely in front of the other); meaningless for
    coplanar pairs, whose F is 0.
    """
    axis_i, start_i, end_i = rectangle_edges(*rects_i)
    axis_j, start_j, end_j = rectangle_edges(*rects_j)
    rows_i, rows_j = np.arange(len(axis_i)), np.arange(len(axis_j))
    h = _log_kernel_antiderivative
    total = np.zeros((len(axis_i), len(axis_j)))
    for k in range(4):
        a = axis_i[:, k]
        s1, e1 = start_i[rows_i, k, a][:, None], end_i[rows_i, k, a][:, None]
        for l in range(4):
            same = a[:, None] == axis_j[None, :, l]
            if not same.any():
                continue
            b = axis_j[:, l]
            s2, e2 = start_j[rows_j, l, b][None], end_j[rows_j, l, b][None]
            gap = start_i[:, None, k, :] - start_j[None, :, l, :]
            along = np.take_along_axis(gap, np.broadcast_to(a[:, None, None], (*gap.shape[:2], 1)), axis=2)[..., 0]
            d = np.sqrt(np.maximum(np.einsum("ijk,ijk->ij", gap, gap) - along**2, 0.0))
            term = h(e1 - s2, d) - h(s1 - s2, d) - h(e1 - e2, d) + h(s1 - e2, d)
            total += np.where(same, term, 0.0)
    return total / (2.0 * np.pi)
