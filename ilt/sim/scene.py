"""Synthetic Lambertian scenes with exactly known discrete light transport.

Radiosity over patches: ``B = L1 + A B`` with ``A[i, j] = rho_i F[i, j]`` (paper
Eq. 14, ``C1 = I - P K``), so a photo is ``L = (I - A)^-1 L1`` (paper Eq. 3) and the
camera's sample of point i is its radiosity (unit gain).  Hidden patches are folded
into the transport among the m visible points as in paper Sec. 3.1.2.
"""

from dataclasses import dataclass, replace

import numpy as np

from .geometry import Geometry, box_geometry, m_geometry, occluded_geometry
from .lighting import direct_light
from .memory import require, scene_bytes

SCENES = ("m", "box", "textured", "occluded")

_DEFAULT_BEAMS = {"m": 128, "textured": 128, "occluded": 128, "box": 3 * 8 * 8}


@dataclass(frozen=True)
class Scene:
    """A scene seen by m beams/sample points, with its exact transport.

    Fields:
        name: one of :data:`SCENES`.
        A: (m, m) float64 transport among the visible points, hidden bounces
            collapsed (paper Sec. 3.1.2); zero diagonal, spectral radius < 1.
        direct: (m,) float64 > 0, radiosity of point j lit directly by a unit-power
            beam (albedo / area, collapsed): the unnormalised diagonal T1.
        facet: (m,) int planar facet of each point (a facet cannot light itself).
        samples: (m, 2) float64 integer-valued unique pixel (x right, y down, centre of
            the top-left pixel at (0, 0)) where point i is seen.
        frame_shape: (H, W) of a camera frame holding every sample.
        layout: (rows, cols), rows * cols == m; points are in scanline order.
        albedo: (m,) float64.
        geometry: every patch, hidden ones included (:class:`~ilt.sim.geometry.Geometry`).
    """

    name: str
    A: np.ndarray
    direct: np.ndarray
    facet: np.ndarray
    samples: np.ndarray
    frame_shape: tuple[int, int]
    layout: tuple[int, int]
    albedo: np.ndarray
    geometry: Geometry

    @property
    def m(self) -> int:
        """Number of visible points (beams)."""
        return len(self.direct)

    def _bounces(self, first: np.ndarray, n_bounces: int) -> np.ndarray:
        """(n_bounces, *first.shape): A^(n-1) first for n = 1..n_bounces, by recursion."""
        out = np.empty((n_bounces, *first.shape))
        out[0] = first
        for n in range(1, n_bounces):
            out[n] = self.A @ out[n - 1]
        return out

    def _isf_raw(self) -> np.ndarray:
        return np.linalg.solve(np.eye(self.m) - self.A, np.diag(self.direct))

    def isf(self, max_bounces: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The impulse scatter function T (paper Sec. 3): column j is the photo under a beam on point j.

        ``T_raw = (I - A)^-1 diag(direct)`` (exact solve) or, with ``max_bounces = K``,
        the forward tracer truncated at K bounces ``sum_{n=1..K} A^(n-1) diag(direct)``.
        Returns: T (m, m) float64 with unit 2-norm columns and the column scales
        s (m,) float64, ``T = T_raw / s``.
        """
        if max_bounces is None:
            raw = self._isf_raw()
        else:
            _check_count("max_bounces", max_bounces)
            raw = self._bounces(np.diag(self.direct), max_bounces).sum(axis=0)
        scale = np.linalg.norm(raw, axis=0)
        return raw / scale, scale

    def bounce_isfs(self, n_bounces: int) -> np.ndarray:
        """(n_bounces, m, m) float64 true n-bounce ISFs ``A^(n-1) diag(direct) / s`` (paper Fig. 5).

        Every column is divided by the scale s of the exact :meth:`isf`, so the sum
        over all n is T.
        """
        _check_count("n_bounces", n_bounces)
        scale = np.linalg.norm(self._isf_raw(), axis=0)
        return self._bounces(np.diag(self.direct / scale), n_bounces)

    def illumination(self, kind: str, **params) -> np.ndarray:
        """(m,) float64 >= 0 direct light L1 of a photo under ``kind`` (one of ``ILLUMINATIONS``).

        Parameters (all optional, scene defaults in ``ilt.sim.lighting.DEFAULTS``):
        flashlight: position, target, half_angle_deg, power;
        room: lamp, ambient, lamp_power; projector: position, target,
        half_angle_deg, period_deg, pattern ("stripes" | "checker"), power.
        Hidden patches' direct light is folded in (paper Sec. 3.1.2).
        """
        return self.geometry.fold(direct_light(self.geometry, kind, **params))

    def photo(self, kind: str, n_bounces: int = 8, **params) -> tuple[np.ndarray, np.ndarray]:
        """A photo and its true bounces under :meth:`illumination` ``kind``.

        Returns: L (m,) float64 ``(I - A)^-1 L1`` (paper Eq. 3, exact solve) and
        (n_bounces, m) float64 ``L_n = A^(n-1) L1`` (by recursion).
        """
        _check_count("n_bounces", n_bounces)
        first = self.illumination(kind, **params)
        return np.linalg.solve(np.eye(self.m) - self.A, first), self._bounces(first, n_bounces)


def _check_count(name: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")


def _textured_albedo(x: np.ndarray, albedo: float, seed: int) -> np.ndarray:
    """Albedo (N,) in [0.15, 0.95] about ``albedo``: a ramp along x in [0, 4], square-wave stripes of random period and phase, and a little per-patch jitter."""
    rng = np.random.default_rng(seed)
    period = rng.uniform(0.3, 0.7)
    phase = rng.uniform(0.0, period)
    stripes = np.where(np.floor((x + phase) / period) % 2 == 0, 0.12, -0.12)
    ramp = 0.15 * (x / 2.0 - 1.0)
    return np.clip(albedo + stripes + ramp + rng.uniform(-0.03, 0.03, len(x)), 0.15, 0.95)


def _build(name: str, beams: int, albedo: float, seed: int):
    if name in ("m", "textured"):
        if beams < 4 or beams % 4:
            raise ValueError(f"scene {name!r}: beams must be a positive multiple of 4 (one per patch, 4 facets), got {beams}")
        built = m_geometry(beams // 4, albedo)
        if name == "textured":
            geometry = built[0]
            built = (replace(geometry, albedo=_textured_albedo(geometry.centre[:, 0], albedo, seed)), *built[1:])
        return built
    if name == "occluded":
        if beams < 8:
            raise ValueError(f"scene 'occluded': beams must be >= 8, got {beams}")
        per_facet = 2 * (beams // 8)
        return occluded_geometry(per_facet, beams - 3 * per_facet, albedo)
    n = max(1, round(np.sqrt(beams / 3)))
    return box_geometry(n, albedo)


def make_scene(name: str, beams: int | None = None, albedo: float | None = None, seed: int = 0) -> Scene:
    """Build one of :data:`SCENES` with its exact transport.

    Parameters:
        name: "m" (flatland M, paper Fig. 3), "textured" (the M with striped,
            ramped albedo drawn with ``seed``), "occluded" (the M under a floating
            plank that hides part of it), "box" (three inside faces of a box, Fig. 7).
        beams: number of sample points m wanted.  "m"/"textured": a multiple of 4,
            m = beams, beams / 4 patches a facet (default 128).  "occluded": >= 8,
            m = beams (3 k terrain points with k = 2 floor(beams / 8), the rest on the
            plank's top; k terrain and as many plank-underside patches are hidden).
            "box": rounded to 3 n^2, n x n patches a face (default 192, n = 8).
            ``Scene.m`` is authoritative.
        albedo: uniform albedo in (0, 1] (default 0.7); "textured" varies about it.
        seed: random seed of the texture.
    Raises: ValueError on an unknown name or a bad beams/albedo; InsufficientMemory
        (a ValueError) when the scene would not fit in the memory available.
    """
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; choose one of {SCENES}")
    beams = _DEFAULT_BEAMS[name] if beams is None else beams
    _check_count("beams", beams)
    albedo = 0.7 if albedo is None else float(albedo)
    if not 0.0 < albedo <= 1.0:
        raise ValueError(f"albedo must be in (0, 1], got {albedo}")
    require(scene_bytes(name, int(beams)), f"scene {name!r} with {beams} beams")
    geometry, samples, frame_shape, layout = _build(name, int(beams), albedo, seed)
    a, gain = geometry.collapsed
    v = geometry.visible
    return Scene(name=name, A=a, direct=gain * geometry.albedo[v] / geometry.area[v], facet=geometry.facet[v],
                 samples=samples, frame_shape=frame_shape, layout=layout, albedo=geometry.albedo[v],
                 geometry=geometry)
