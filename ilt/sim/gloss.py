"""Non-Lambertian flatland scenes: a glossy lobe in patch-to-patch transport.

For a Lambertian surface the light a patch sends toward another does not depend on
where it came from, so the transport is a matrix over patches (radiosity,
:mod:`ilt.sim.scene`) and the ISF is a diagonal scaling of a symmetric matrix. A
glossy patch sends part of its light toward the mirror direction of the light it
received, so the state is the power on each directed pair of patches, ``x[i -> j]``,
and one bounce is ``x[j -> k] = sum_i rho_j F[j, k] ((1 - g) + g l_j(i -> k)) x[i -> j]``:
m^3 entries over m^2 pairs (fine at test sizes). ``g`` is the glossy share of the
reflected light and ``l`` a Gaussian lobe of width ``lobe_deg`` about the mirror
direction, scaled so that ``integral l cos = integral cos`` over the half-plane
(``l = 1`` is Lambertian): a glossy patch reflects as much light as a matte one, in
other directions. ``gloss = 0`` is :meth:`ilt.sim.scene.Scene.isf` exactly.

The camera (orthographic, looking down, as in :mod:`ilt.sim.scene`) reads patch j's
radiance toward it, ``rho_j ((1 - g) + g l_j(in -> up))`` times the power arriving, over
its area. The laser comes from a direction (:data:`LASER_DIRECTION`) a little off the
camera's, and reaches every visible patch. Flatland scenes only ("m", "textured",
"occluded").
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse
import scipy.sparse.linalg

from .lighting import DEFAULTS, ILLUMINATIONS, direct_light
from .scene import Scene, _check_count

#: unit direction from the scene toward the camera (orthographic, looking down)
CAMERA_DIRECTION = np.array([0.0, 1.0])
#: unit direction from the scene toward the laser: 10 degrees off the camera's
LASER_DIRECTION = np.array([np.sin(np.radians(10.0)), np.cos(np.radians(10.0))])
_QUADRATURE = np.linspace(-np.pi / 2, np.pi / 2, 1441)


@dataclass(frozen=True)
class GlossyScene:
    """A flatland :class:`~ilt.sim.scene.Scene` with a glossy share ``gloss`` of every patch's reflection.

    Fields: scene (its geometry, samples and layout), gloss (N,) float64 in [0, 1] per
    patch, lobe_deg the lobe's width (Gaussian sigma, degrees).
    """

    scene: Scene
    gloss: np.ndarray
    lobe_deg: float

    @property
    def m(self) -> int:
        return self.scene.m

    @cached_property
    def _pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """(P,) source and target patch of every directed pair that exchanges light."""
        return np.nonzero(self.scene.geometry.form_factors > 0)

    def _lobe(self, j: np.ndarray, incoming: np.ndarray, outgoing: np.ndarray) -> np.ndarray:
        """l_j for light arriving along ``incoming`` (K, 2) and leaving along ``outgoing`` (K, 2), unit vectors."""
        normal = self.scene.geometry.normal[j]
        mirror = incoming - 2.0 * np.einsum("kd,kd->k", incoming, normal)[:, None] * normal
        sigma = np.radians(self.lobe_deg)
        angle = np.arctan2(_cross(mirror, outgoing), np.einsum("kd,kd->k", mirror, outgoing))
        mirror_angle = np.arctan2(_cross(normal, mirror), np.einsum("kd,kd->k", normal, mirror))
        # integral over the half-plane of the lobe times cos, against integral cos = 2
        lobe = np.exp(-0.5 * ((_QUADRATURE[None, :] - mirror_angle[:, None]) / sigma) ** 2)
        scale = np.trapezoid(lobe * np.cos(_QUADRATURE), _QUADRATURE, axis=1) / 2.0
        return np.exp(-0.5 * (angle / sigma) ** 2) / scale

    def _reflect(self, j: np.ndarray, incoming: np.ndarray, outgoing: np.ndarray) -> np.ndarray:
        g = self.gloss[j]
        return self.scene.geometry.albedo[j] * ((1.0 - g) + g * self._lobe(j, incoming, outgoing))

    @cached_property
    def _system(self):
        """K (P, P) one bounce over the pairs, R (m, P) the camera's readout, factorised I - K."""
        g = self.scene.geometry
        src, dst = self._pairs
        rows, cols, vals = [], [], []
        for j in range(len(g.area)):
            into = np.flatnonzero(dst == j)
            out = np.flatnonzero(src == j)
            if len(into) == 0 or len(out) == 0:
                continue
            i_in, k_out = np.meshgrid(into, out, indexing="ij")
            incoming = _unit(g.centre[j] - g.centre[src[i_in.ravel()]])
            outgoing = _unit(g.centre[dst[k_out.ravel()]] - g.centre[j])
            jj = np.full(i_in.size, j)
            vals.append(g.form_factors[j, dst[k_out.ravel()]] * self._reflect(jj, incoming, outgoing))
            rows.append(k_out.ravel())
            cols.append(i_in.ravel())
        n = len(src)
        K = scipy.sparse.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
        v = g.visible
        row_of = np.full(len(g.area), -1)
        row_of[v] = np.arange(len(v))
        into = np.flatnonzero(row_of[dst] >= 0)       # pairs arriving at a patch the camera sees
        j = dst[into]
        up = np.broadcast_to(CAMERA_DIRECTION, (len(into), 2))
        readout = self._reflect(j, _unit(g.centre[j] - g.centre[src[into]]), up) / g.area[j]
        R = scipy.sparse.csr_matrix((readout, (row_of[j], into)), shape=(len(v), n))
        return K, R, scipy.sparse.linalg.splu(scipy.sparse.identity(n, format="csc") - K)

    def _respond(self, power: np.ndarray, incoming: np.ndarray, bounces: int | None = None) -> np.ndarray:
        """Camera samples (m, k) [or (bounces, m, k)] for power (N, k) arriving at each patch along ``incoming``.

        ``incoming``: (N, 2) unit direction of travel of the arriving light, or None for
        light from every direction alike (reflected as by a matte patch).
        """
        g = self.scene.geometry
        K, R, lu = self._system
        src, dst = self._pairs
        n_all = len(g.area)
        v = g.visible
        up = np.broadcast_to(CAMERA_DIRECTION, (n_all, 2))
        patches = np.arange(n_all)
        if incoming is None:
            to_camera = g.albedo
            to_pair = g.albedo[src][:, None]
        else:
            to_camera = self._reflect(patches, incoming, up)
            to_pair = self._reflect(src, incoming[src], _unit(g.centre[dst] - g.centre[src]))[:, None]
        first = (to_camera / g.area)[v, None] * power[v]
        emitted = g.form_factors[src, dst][:, None] * to_pair * power[src]
        if bounces is None:
            return first + R @ lu.solve(emitted)
        out = np.empty((bounces, len(v), power.shape[1]))
        out[0] = first
        x = emitted
        for n in range(1, bounces):
            out[n] = R @ x
            x = K @ x
        return out

    def isf(self) -> tuple[np.ndarray, np.ndarray]:
        """T (m, m) float64 with unit 2-norm columns (column j: a unit-power laser beam on point j) and the scales."""
        g = self.scene.geometry
        power = np.zeros((len(g.area), self.m))
        power[g.visible, np.arange(self.m)] = 1.0
        incoming = np.broadcast_to(-LASER_DIRECTION, (len(g.area), 2))
        raw = self._respond(power, incoming)
        scale = np.linalg.norm(raw, axis=0)
        return raw / scale, scale

    def photo(self, kind: str, n_bounces: int = 8, **params) -> tuple[np.ndarray, np.ndarray]:
        """A photo (m,) and its true bounces (n_bounces, m) under ``kind`` (as :meth:`Scene.photo`).

        The flashlight's and projector's light arrives from their positions, the room's
        lamp from its position and its sky from every direction.
        """
        _check_count("n_bounces", n_bounces)
        if kind not in ILLUMINATIONS:
            raise ValueError(f"unknown illumination {kind!r}; choose one of {ILLUMINATIONS}")
        g = self.scene.geometry
        settings = DEFAULTS[2][kind] | params
        parts = []
        if kind == "room":
            lamp = direct_light(g, "room", **(settings | {"ambient": 0.0}))
            parts.append((lamp, settings["lamp"]))
            parts.append((direct_light(g, "room", **(settings | {"lamp_power": 0.0})), None))
        else:
            parts.append((direct_light(g, kind, **params), settings["position"]))
        photo, total = np.zeros(self.m), np.zeros((n_bounces, self.m))
        for radiosity, position in parts:
            power = (radiosity / g.albedo * g.area)[:, None]      # rho E -> the power arriving
            incoming = None if position is None else _unit(g.centre - np.asarray(position, dtype=float))
            photo += self._respond(power, incoming)[:, 0]
            total += self._respond(power, incoming, n_bounces)[..., 0]
        return photo, total


def glossy_scene(scene: Scene, gloss, lobe_deg: float = 12.0) -> GlossyScene:
    """``scene`` (flatland) with a glossy share ``gloss`` (scalar or (N,) per patch, in [0, 1]) of its reflection."""
    if scene.geometry.dim != 2:
        raise ValueError(f"glossy scenes are flatland only; scene {scene.name!r} is 3D")
    share = np.broadcast_to(np.asarray(gloss, dtype=float), scene.geometry.area.shape).copy()
    if np.any(share < 0) or np.any(share > 1):
        raise ValueError(f"gloss must be in [0, 1], got {gloss!r}")
    if not lobe_deg > 0:
        raise ValueError(f"lobe_deg must be > 0, got {lobe_deg}")
    return GlossyScene(scene=scene, gloss=share, lobe_deg=float(lobe_deg))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]
