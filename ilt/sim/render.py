"""Camera frames of the synthetic scenes, as a real rig would record them.

The exact scenes of :mod:`ilt.sim.scene` put one patch under each beam, so a beam
lights its whole patch and a pixel at the patch's centre says everything.  A real
laser spot is far smaller than the beam spacing, and the surface is continuous.
This module renders that situation, still with exact transport:

- The surface is a **fine** discretisation of the same geometry (``fine`` patches per
  beam spacing along each axis, built by the same builders), so it is finer than the
  beam grid.
- A beam of unit power hits the surface at the centre of its coarse patch and lights
  a Gaussian footprint of standard deviation ``spot`` x beam spacing (on the surface,
  truncated to the facet hit and renormalised).  Fine patch k receives the footprint's
  power over it, so its direct radiosity is ``rho_k w_k / area_k``; the radiosity of
  every fine patch is the exact solve ``B = (I - A_fine)^-1 L1``.
- A pixel is the area average over ``supersample`` sub-pixel rays of what they see:
  the analytic direct spot ``rho E(q)`` at the surface point q (so spots are smooth
  sub-pixel blobs) plus the interreflected radiosity ``B - L1`` of the fine patch hit.
  Photos (room light, flashlight, projector) are ``B`` of the fine patches, averaged
  the same way.  Void pixels are 0.

Cameras: the flatland scenes are seen by an orthographic camera looking down (pixel
column from x) and **extruded** along the depth axis: every one of the ``rows``
image rows sees the same cross-section.  The laser spot is drawn as a 2D blob, the
footprint along the row times a Gaussian across rows whose sum over the rows is
``rows``, so its flux in the frame equals that of a line beam over the frame's depth
and frame sums over any column range agree with the flatland transport.  That is the
one approximation (a real round spot would light less of the depth).  The box is
truly 3D: a pinhole camera at :data:`~ilt.sim.geometry.BOX_EYE` looking at the corner.

Radiometric unit: a pixel value is the radiosity of the surface it sees (unit gain),
as in :mod:`ilt.sim.scene`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
import scipy.linalg
import scipy.sparse
from scipy.special import ndtr

from .geometry import BOX_EYE, M_VERTICES, Geometry, box_geometry, m_geometry, occluded_geometry
from .lighting import direct_light
from .memory import render_bytes, require
from .scene import _textured_albedo

#: scenes that can be rendered as frames
FRAME_SCENES = ("m", "textured", "occluded", "box")
#: default beams per scene for frames
DEFAULT_FRAME_BEAMS = {"m": 64, "textured": 64, "occluded": 64, "box": 3 * 6 * 6}
#: default fine patches per beam spacing (flatland; the box uses a quarter per axis)
DEFAULT_FINE = 16
#: default sub-pixel rays per pixel axis
SUPERSAMPLE = 4
_MARGIN = 8


@dataclass(frozen=True)
class RenderedScene:
    """A scene with a continuous (finely discretised) surface, m beams and a camera.

    Fields:
        name: scene name.
        geometry: the fine :class:`~ilt.sim.geometry.Geometry` (N patches, N >> m).
        targets: (m, d) float64 scene points the beams hit (coarse patch centres).
        target_facet: (m,) int facet each beam hits.
        centres: (m, 2) float64 true spot centres in pixels (x right, y down, centre of
            the top-left pixel at (0, 0)): the first moment of the imaged spot (flatland:
            exactly the beam axis; box: within ~0.02 px of the projected axis).
        layout: (rows, cols) of the beam plan, scanline order.
        frame_shape: (H, W) pixels.
        spot_sigma: (m,) float64 footprint standard deviation on the surface (scene units).
        image_sigma: (m,) float64 about that in pixels (flatland: exact across rows).
        spacing: beam spacing on the surface (scene units; flatland: along x).
        sub_patch: (P, S) int fine patch seen by each of S sub-pixel rays of P pixel
            positions (-1: void); P = W (flatland columns) or H * W (box).
        sub_point: (P, S, d) float64 the surface points those rays hit.
        extruded: True for flatland (P = W, rows repeat).
    """

    name: str
    geometry: Geometry = field(repr=False)
    targets: np.ndarray = field(repr=False)
    target_facet: np.ndarray = field(repr=False)
    centres: np.ndarray = field(repr=False)
    layout: tuple[int, int]
    frame_shape: tuple[int, int]
    spot_sigma: np.ndarray = field(repr=False)
    image_sigma: np.ndarray = field(repr=False)
    spacing: float
    sub_patch: np.ndarray = field(repr=False)
    sub_point: np.ndarray = field(repr=False)
    extruded: bool

    @property
    def m(self) -> int:
        return len(self.targets)

    @cached_property
    def pixel_average(self) -> scipy.sparse.csr_matrix:
        """(P, N) sparse: the area average over sub-pixel rays, frame values = this @ radiosity."""
        p, s = self.sub_patch.shape
        rows = np.repeat(np.arange(p), s)
        cols = self.sub_patch.ravel()
        keep = cols >= 0
        return scipy.sparse.csr_matrix(
            (np.full(keep.sum(), 1.0 / s), (rows[keep], cols[keep])), shape=(p, len(self.geometry.area)))

    @cached_property
    def _solve(self):
        n = len(self.geometry.area)
        return scipy.linalg.lu_factor(np.eye(n) - self.geometry.transport)

    def radiosity(self, direct: np.ndarray) -> np.ndarray:
        """(N,) or (N, k) float64 ``B = (I - A_fine)^-1 L1`` (paper Eq. 5), exact solve."""
        return scipy.linalg.lu_solve(self._solve, direct)

    def to_frame(self, values: np.ndarray) -> np.ndarray:
        """(N,) fine-patch radiosity -> (H, W) float64 frame (area average per pixel)."""
        flat = self.pixel_average @ values
        if self.extruded:
            return np.broadcast_to(flat, self.frame_shape).copy()
        return flat.reshape(self.frame_shape)

    # ------------------------------------------------------------------ beams

    def _footprint(self, j: int, points: np.ndarray, facet: np.ndarray) -> np.ndarray:
        """Irradiance density (per unit area/length) of unit-power beam j at surface points."""
        sigma = self.spot_sigma[j]
        d2 = np.sum((points - self.targets[j]) ** 2, axis=-1)
        dim = self.geometry.dim - 1
        density = np.exp(-0.5 * d2 / sigma**2) / ((np.sqrt(2 * np.pi) * sigma) ** dim)
        return np.where(facet == self.target_facet[j], density, 0.0) / self._footprint_mass[j]

    @cached_property
    def _patch_weights(self) -> tuple[np.ndarray, np.ndarray]:
        """Per beam, the fraction of its power on each fine patch (m, N) and the untruncated mass (m,)."""
        g = self.geometry
        if g.dim == 2:  # a Gaussian in arc length over segments
            w = _segment_weights(g, self.targets, self.target_facet, self.spot_sigma)
        else:           # a Gaussian over axis-aligned rectangles: separable
            half = np.where(np.abs(g.normal) > 0.5, 0.0, np.sqrt(g.area)[:, None] / 2)
            w = (g.facet[None] == self.target_facet[:, None]).astype(float)
            s = self.spot_sigma[:, None]
            for axis in range(3):
                lo, hi = g.centre[:, axis] - half[:, axis], g.centre[:, axis] + half[:, axis]
                t = self.targets[:, axis, None]
                frac = ndtr((hi - t) / s) - ndtr((lo - t) / s)
                w *= np.where(half[None, :, axis] == 0, 1.0, frac)
        mass = w.sum(axis=1)
        return w / mass[:, None], mass

    @property
    def _footprint_mass(self) -> np.ndarray:
        return self._patch_weights[1]

    def beam_direct(self, j: int) -> np.ndarray:
        """(N,) float64 direct radiosity of the fine patches under unit-power beam j."""
        g = self.geometry
        return g.albedo * self._patch_weights[0][j] / g.area

    def spot_image(self, j: int) -> np.ndarray:
        """(H, W) float64: the direct light of beam j as the camera sees it (analytic spot)."""
        height, width = self.frame_shape
        albedo = np.where(self.sub_patch >= 0, self.geometry.albedo[np.maximum(self.sub_patch, 0)], 0.0)
        facet = np.where(self.sub_patch >= 0, self.geometry.facet[np.maximum(self.sub_patch, 0)], -1)
        cx, cy = self.centres[j]
        radius = 6.0 * self.image_sigma[j] + 3
        if self.extruded:
            cols = np.arange(max(0, int(cx - radius)), min(width, int(cx + radius) + 2))
            values = (albedo[cols] * self._footprint(j, self.sub_point[cols], facet[cols])).mean(axis=1)
            row_sigma = self.image_sigma[j]
            edges = np.arange(height + 1) - 0.5
            profile = np.diff(ndtr((edges - cy) / row_sigma)) * height
            out = np.zeros(self.frame_shape)
            out[:, cols] = profile[:, None] * values[None]
            return out
        ys = np.arange(max(0, int(cy - radius)), min(height, int(cy + radius) + 2))
        xs = np.arange(max(0, int(cx - radius)), min(width, int(cx + radius) + 2))
        index = (ys[:, None] * width + xs[None]).ravel()
        values = (albedo[index] * self._footprint(j, self.sub_point[index], facet[index])).mean(axis=1)
        out = np.zeros(self.frame_shape)
        out[np.ix_(ys, xs)] = values.reshape(len(ys), len(xs))
        return out

    def beam_frame(self, j: int) -> np.ndarray:
        """(H, W) float32 frame under unit-power beam j: analytic spot + exact interreflections."""
        direct = self.beam_direct(j)
        scattered = self.radiosity(direct) - direct
        return (self.spot_image(j) + self.to_frame(scattered)).astype(np.float32)

    def beam_between(self, position) -> RenderedScene:
        """The scene with one beam landing at a fractional plan position ``(col, row)``
        (``(col,)`` on a line): between the plan's beams, as a pan-tilt unit aimed between
        their angles puts it. Inside a face the point, footprint and spot centre are the
        bilinear blend of the (up to 4) neighbouring beams'; where they span a fold or a
        gap (different facets) the beam lands where the nearest plan beam does. Shares the
        exact solve with this scene (``beam_frame(0)`` of the result is the frame)."""
        rows, cols = self.layout
        pos = np.asarray(position, dtype=np.float64).ravel()
        col, row = float(pos[0]), float(pos[1]) if pos.size > 1 and rows > 1 else 0.0
        if not (np.isfinite(col) and np.isfinite(row)):
            raise ValueError(f"beam position {list(pos)} is not finite")
        corners, weights = [], []
        for axis_pos, n in ((row, rows), (col, cols)):
            lo = int(np.clip(np.floor(axis_pos), 0, max(n - 2, 0)))
            t = float(np.clip(axis_pos - lo, 0.0, 1.0)) if n > 1 else 0.0
            corners.append((lo, min(lo + 1, n - 1)))
            weights.append((1.0 - t, t))
        beams, w = [], []
        for (r, wr) in zip(corners[0], weights[0]):
            for (c, wc) in zip(corners[1], weights[1]):
                if wr * wc > 0:
                    beams.append(r * cols + c)
                    w.append(wr * wc)
        beams, w = np.asarray(beams), np.asarray(w)
        blend = w / w.sum()
        target, facet = blend @ self.targets[beams], self.target_facet[beams[:1]]
        sigma = np.array([blend @ self.spot_sigma[beams]])
        if len(np.unique(self.target_facet[beams])) > 1:
            if self.extruded:   # flatland: the surface the camera column between them sees
                point, facet, sigma = self._flatland_point(float(target[0]))
                target = point if point is not None else self.targets[beams[int(np.argmax(w))]]
            if not self.extruded or point is None:   # the box across faces: the nearest beam's point
                beams, blend = beams[[int(np.argmax(w))]], np.ones(1)
                target, facet, sigma = self.targets[beams[0]], self.target_facet[beams], self.spot_sigma[beams]
        one = replace(self, targets=np.asarray(target, dtype=np.float64)[None], target_facet=np.asarray(facet),
                      centres=(blend @ self.centres[beams])[None], layout=(1, 1), spot_sigma=np.asarray(sigma),
                      image_sigma=np.array([blend @ self.image_sigma[beams]]))
        for name in ("_solve", "pixel_average"):   # the geometry's: computed once, shared
            if name in self.__dict__:
                one.__dict__[name] = self.__dict__[name]
        return _true_centres(one)

    def _flatland_point(self, x: float):
        """The topmost surface point at ``x`` (what a flatland beam between facets hits),
        its facet (1,) and footprint sigma (1,) (a plan beam's on that facet: the slope
        sets it); (None, ..) when no plan beam shares the facet or x sees no surface."""
        patch, point = _flatland_topmost(self.geometry, np.array([[x]]))
        patch = int(patch[0, 0])
        on = np.flatnonzero(self.target_facet == self.geometry.facet[patch]) if patch >= 0 else []
        if len(on) == 0:
            return None, self.target_facet[:1], self.spot_sigma[:1]
        return point[0, 0], self.target_facet[on[:1]], self.spot_sigma[on[:1]]

    # ------------------------------------------------------------------ photos

    def photo(self, kind: str, n_bounces: int = 8, **params) -> tuple[np.ndarray, np.ndarray]:
        """A photo under illumination ``kind`` and its true bounce frames.

        Returns: (H, W) float32 frame of ``B = (I - A)^-1 L1`` and (n_bounces, H, W)
        float32 frames of ``A^(n-1) L1`` (the fine scene's true n-bounce images).
        """
        first = direct_light(self.geometry, kind, **params)
        bounces = np.empty((n_bounces, *self.frame_shape), dtype=np.float32)
        b = first
        for n in range(n_bounces):
            bounces[n] = self.to_frame(b)
            b = self.geometry.transport @ b
        return self.to_frame(self.radiosity(first)).astype(np.float32), bounces


def _tangents(g: Geometry) -> np.ndarray:
    """(N, 2) unit tangents of flatland patches (p0 -> p1)."""
    return np.stack([g.normal[:, 1], -g.normal[:, 0]], axis=1)


def _segment_weights(g: Geometry, targets, target_facet, sigma) -> np.ndarray:
    """(m, N) power fraction of an arc-length Gaussian footprint on each flatland segment."""
    t = _tangents(g)
    s_centre = np.einsum("nk,mnk->mn", t, g.centre[None] - targets[:, None])
    half = g.area[None] / 2
    s = sigma[:, None]
    w = ndtr((s_centre + half) / s) - ndtr((s_centre - half) / s)
    return w * (g.facet[None] == target_facet[:, None])


# ---------------------------------------------------------------------- builders


def render_scene(name: str, beams: int | None = None, albedo: float | None = None, seed: int = 0,
                 spot: float = 0.05, fine: int = DEFAULT_FINE, px_per_beam: float = 32.0, rows: int | None = None,
                 supersample: int = SUPERSAMPLE) -> RenderedScene:
    """Build a renderable scene.

    Parameters:
        name: one of :data:`FRAME_SCENES`.
        beams: m (flatland: multiple of 4, default 64; box: 3 n^2, default 108).
        albedo: uniform albedo (default 0.7; "textured" varies about it).
        seed: texture seed and the spot rows' sub-pixel jitter (flatland).
        spot: footprint standard deviation as a fraction of the beam spacing
            (0.05: a laser spot far smaller than its cell; ~0.4: spots that fill it).
        fine: fine patches per beam spacing along each surface axis (flatland 16,
            the box uses max(2, fine // 4) per axis to keep N manageable).
        px_per_beam: pixels between neighbouring spots (flatland exactly; box about).
        rows: image rows of the extruded flatland frames (default: 32, more for wide spots).
        supersample: sub-pixel rays per pixel axis.
    Raises: ValueError on a bad parameter; InsufficientMemory (a ValueError) when the
        fine patches' transport would not fit in the memory available.
    """
    if name not in FRAME_SCENES:
        raise ValueError(f"unknown scene {name!r} for frames; choose one of {FRAME_SCENES}")
    beams = DEFAULT_FRAME_BEAMS[name] if beams is None else int(beams)
    albedo = 0.7 if albedo is None else float(albedo)
    if not 0 < spot <= 1:
        raise ValueError(f"spot must be in (0, 1] beam spacings, got {spot}")
    require(render_bytes(name, beams, fine, px_per_beam, supersample),
            f"rendering scene {name!r} with {beams} beams ({fine} fine patches per beam spacing)")
    if name == "box":
        return _render_box(beams, albedo, spot, fine, px_per_beam, supersample)
    return _render_flatland(name, beams, albedo, seed, spot, fine, px_per_beam, rows, supersample)


def _render_flatland(name, beams, albedo, seed, spot, fine, px_per_beam, rows, supersample):
    if beams < 4 or beams % 4:
        raise ValueError(f"scene {name!r}: beams must be a positive multiple of 4, got {beams}")
    per_facet = beams // 4
    if name == "occluded":
        if beams % 8:
            raise ValueError(f"scene 'occluded' frames: beams must be a multiple of 8, got {beams}")
        coarse = occluded_geometry(per_facet, per_facet, albedo)[0]
        geometry = occluded_geometry(per_facet * fine, per_facet * fine, albedo)[0]
    else:
        coarse = m_geometry(per_facet, albedo)[0]
        geometry = m_geometry(per_facet * fine, albedo)[0]
        if name == "textured":
            geometry = replace(geometry, albedo=_textured_albedo(geometry.centre[:, 0], albedo, seed))
    visible = coarse.visible
    targets, target_facet = coarse.centre[visible], coarse.facet[visible]
    spacing = 1.0 / per_facet                       # in x, for every facet of the M
    scale = px_per_beam / spacing                   # pixels per unit x
    x_lo, x_hi = M_VERTICES[:, 0].min(), M_VERTICES[:, 0].max()
    width = int(np.ceil(scale * (x_hi - x_lo))) + 2 * _MARGIN + 1
    x0 = x_lo - _MARGIN / scale                     # x of the centre of column 0
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    xs = x0 + (np.arange(width)[:, None] + sub[None]) / scale
    sub_patch, sub_point = _flatland_topmost(geometry, xs)
    # a footprint round in the image: sigma along the surface = image sigma / cos(slope)
    cos = np.abs(coarse.normal[visible, 1])
    sigma = spot * spacing / cos
    rows = rows or max(32, 2 * int(np.ceil(5 * spot * px_per_beam)))
    rng = np.random.default_rng(seed)
    row_centres = (rows - 1) / 2 + rng.uniform(-0.5, 0.5, len(targets))
    centres = np.stack([(targets[:, 0] - x0) * scale, row_centres], axis=1)
    scene = RenderedScene(name=name, geometry=geometry, targets=targets, target_facet=target_facet,
                         centres=centres, layout=(1, len(targets)), frame_shape=(rows, width),
                         spot_sigma=sigma, image_sigma=np.full(len(targets), spot * px_per_beam),
                         spacing=spacing, sub_patch=sub_patch, sub_point=sub_point, extruded=True)
    return _true_centres(scene)


def _flatland_topmost(g: Geometry, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For x positions (W, S), the topmost up-facing fine patch (W, S) int (-1 none) and the point (W, S, 2)."""
    t = _tangents(g)
    half = g.area / 2
    a = g.centre - t * half[:, None]
    b = g.centre + t * half[:, None]
    best_y = np.full(xs.shape, -np.inf)
    best = np.full(xs.shape, -1)
    for f in np.unique(g.facet):
        sel = np.nonzero((g.facet == f) & (g.normal[:, 1] > 0))[0]
        if sel.size == 0:
            continue
        left = np.minimum(a[sel, 0], b[sel, 0])
        right = np.maximum(a[sel, 0], b[sel, 0])
        order = np.argsort(left)
        sel, left, right = sel[order], left[order], right[order]
        k = np.clip(np.searchsorted(left, xs, side="right") - 1, 0, len(sel) - 1)
        inside = (xs >= left[k]) & (xs < right[k])
        p = sel[k]
        frac = (xs - a[p, 0]) / (b[p, 0] - a[p, 0])
        y = a[p, 1] + frac * (b[p, 1] - a[p, 1])
        better = inside & (y > best_y)
        best_y = np.where(better, y, best_y)
        best = np.where(better, p, best)
    point = np.stack([xs, np.where(best >= 0, best_y, 0.0)], axis=-1)
    return best, point


def _box_camera():
    forward = -BOX_EYE / np.linalg.norm(BOX_EYE)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return forward, right, up


def _project(points, forward, right, up):
    rel = points - BOX_EYE
    depth = rel @ forward
    return np.stack([rel @ right / depth, -(rel @ up) / depth], axis=-1)


def _render_box(beams, albedo, spot, fine, px_per_beam, supersample):
    n = max(1, round(np.sqrt(beams / 3)))
    per = max(2, fine // 4)
    coarse, _, _, layout = box_geometry(n, albedo)
    geometry = box_geometry(n * per, albedo)[0]
    targets, target_facet = coarse.centre, coarse.facet
    forward, right, up = _box_camera()
    uv = _project(targets, forward, right, up)
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
    corners = corners[(corners == 0).any(axis=1)]
    cuv = _project(corners, forward, right, up)
    # mean distance between neighbouring beam points in the image plane
    d = np.linalg.norm(uv[:, None] - uv[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    focal = px_per_beam / np.median(d.min(axis=1))
    origin = cuv.min(axis=0) - _MARGIN / focal
    size = np.ceil((cuv.max(axis=0) - origin) * focal).astype(int) + _MARGIN + 1
    width, height = int(size[0]), int(size[1])
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    su, sv = np.meshgrid(sub, sub, indexing="xy")
    px = np.arange(width)[None, :, None] + su.ravel()[None, None]
    py = np.arange(height)[:, None, None] + sv.ravel()[None, None]
    u = origin[0] + np.broadcast_to(px, (height, width, su.size)) / focal
    v = origin[1] + np.broadcast_to(py, (height, width, su.size)) / focal
    direction = forward + u[..., None] * right - v[..., None] * up
    best_t = np.full(u.shape, np.inf)
    face = np.full(u.shape, -1)
    for f, axis in enumerate((1, 2, 0)):                 # faces of box_geometry: y=0, z=0, x=0
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -BOX_EYE[axis] / direction[..., axis]
        hit = BOX_EYE + t[..., None] * direction
        ok = (t > 0) & np.all((hit >= -1e-12) & (hit <= 1 + 1e-12), axis=-1) & (t < best_t)
        best_t = np.where(ok, t, best_t)
        face = np.where(ok, f, face)
    point = BOX_EYE + np.where(np.isfinite(best_t), best_t, 0.0)[..., None] * direction
    m_fine = n * per
    grid = {}
    for f, axis in enumerate((1, 2, 0)):
        sel = np.nonzero(geometry.facet == f)[0]
        a1, a2 = [k for k in range(3) if k != axis]
        i1 = np.minimum((geometry.centre[sel, a1] * m_fine).astype(int), m_fine - 1)
        i2 = np.minimum((geometry.centre[sel, a2] * m_fine).astype(int), m_fine - 1)
        table = np.full((m_fine, m_fine), -1)
        table[i1, i2] = sel
        grid[f] = (table, a1, a2)
    patch = np.full(u.shape, -1)
    for f, (table, a1, a2) in grid.items():
        on = face == f
        i1 = np.clip((point[..., a1][on] * m_fine).astype(int), 0, m_fine - 1)
        i2 = np.clip((point[..., a2][on] * m_fine).astype(int), 0, m_fine - 1)
        patch[on] = table[i1, i2]
    projected = (_project(targets, forward, right, up) - origin) * focal
    scene = RenderedScene(name="box", geometry=geometry, targets=targets, target_facet=target_facet,
                         centres=projected, layout=layout, frame_shape=(height, width),
                         spot_sigma=np.full(len(targets), spot / n),
                         image_sigma=spot / n * focal / ((targets - BOX_EYE) @ forward), spacing=1.0 / n,
                         sub_patch=patch.reshape(height * width, -1),
                         sub_point=point.reshape(height * width, -1, 3), extruded=False)
    return _true_centres(scene)


def _true_centres(scene: RenderedScene) -> RenderedScene:
    """The scene with its true spot centres: the first moment of each imaged spot.

    It is the beam axis's pixel for a small flatland spot; perspective (box) moves it
    up to ~0.02 px off the projected axis, and a wide spot cut by a crease further.
    """
    return replace(scene, centres=np.array([_first_moment(scene.spot_image(j)) for j in range(scene.m)]))


def _first_moment(image: np.ndarray) -> np.ndarray:
    """(x, y) intensity-weighted centroid of an (H, W) image, pixel convention of DESIGN.md."""
    total = image.sum()
    return np.array([image.sum(axis=0) @ np.arange(image.shape[1]), image.sum(axis=1) @ np.arange(image.shape[0])]) / total
