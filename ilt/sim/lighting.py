"""Direct light on the patches of a :class:`~ilt.sim.geometry.Geometry`: the
"photos" of paper Sec. 3.1.1 (Fig. 6 and 9), lit by light the method never sees.

Every function returns the direct (1-bounce) radiosity of all N patches,
rho_i E_i, where the irradiance E_i of a point source of angular intensity I is
``I(omega) cos(theta_i) / r^(d-1)`` (d = 2 in flatland, 3 in the box) when the
patch centre sees the source, with hard shadows cast by the scene's occluders.
"""

import inspect
from collections.abc import Callable

import numpy as np

from .geometry import Geometry

_EPS = 1e-12

ILLUMINATIONS = ("flashlight", "room", "projector")

#: Default light positions and aims, by scene dimension.  Flatland: a flashlight low
#: on the left so that the middle peak shades the bottom of facet 3 and facet 2
#: faces away; box: lights in the open octant, which every face sees whole.
DEFAULTS = {
    2: {
        "flashlight": {"position": (-0.3, 3.0), "target": (2.5, 0.8), "half_angle_deg": 30.0},
        "room": {"lamp": (3.5, 3.5)},
        "projector": {"position": (2.0, 4.0), "target": (2.0, 0.0), "half_angle_deg": 40.0},
    },
    3: {
        "flashlight": {"position": (1.3, 0.9, 1.2), "target": (0.1, 0.2, 0.0), "half_angle_deg": 30.0},
        "room": {"lamp": (0.8, 0.3, 1.6)},
        "projector": {"position": (1.8, 1.6, 1.5), "target": (0.2, 0.2, 0.2), "half_angle_deg": 40.0},
    },
}


def point_source(geometry: Geometry, position, intensity: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """(N,) float64 direct radiosity rho_i I(omega_i) cos(theta_i) / r_i^(d-1) from a point source.

    Parameters: position (d,) scene units; intensity maps unit directions (N, d) from
    the source to the patch centres to (N,) radiant intensity >= 0.
    """
    position = np.asarray(position, dtype=float)
    if position.shape != (geometry.dim,):
        raise ValueError(f"light position must have {geometry.dim} coordinates, got {position.tolist()}")
    to_patch = geometry.centre - position
    r = np.linalg.norm(to_patch, axis=1)
    omega = to_patch / r[:, None]
    cos = np.maximum(-np.einsum("ik,ik->i", omega, geometry.normal), 0.0)
    lit = ~geometry.blocked(np.broadcast_to(position, geometry.centre.shape), geometry.centre)
    return geometry.albedo * np.where(lit, intensity(omega) * cos / r ** (geometry.dim - 1), 0.0)


def _beam_angles(omega: np.ndarray, position, target) -> np.ndarray:
    """(N, d-1) angles (radians) of directions ``omega`` about the axis position -> target.

    Flatland: the signed angle; 3D: (horizontal, vertical) angles in a frame with z up.
    """
    axis = np.asarray(target, dtype=float) - np.asarray(position, dtype=float)
    axis /= np.linalg.norm(axis)
    if len(axis) == 2:
        return np.arctan2(omega[:, 1] * axis[0] - omega[:, 0] * axis[1], omega @ axis)[:, None]
    side = np.cross(axis, [0.0, 0.0, 1.0])
    side = side / np.linalg.norm(side) if np.linalg.norm(side) > _EPS else np.array([1.0, 0.0, 0.0])
    up = np.cross(side, axis)
    depth = omega @ axis
    return np.stack([np.arctan2(omega @ side, depth), np.arctan2(omega @ up, depth)], axis=1)


def _cone(omega, position, target, half_angle_deg) -> np.ndarray:
    axis = np.asarray(target, dtype=float) - np.asarray(position, dtype=float)
    return omega @ (axis / np.linalg.norm(axis)) >= np.cos(np.radians(half_angle_deg))


def flashlight(geometry: Geometry, position, target, half_angle_deg: float, power: float = 1.0) -> np.ndarray:
    """Point source of intensity ``power`` inside a hard-edged cone aimed at ``target``; (N,) float64."""
    return point_source(geometry, position,
                        lambda omega: power * _cone(omega, position, target, half_angle_deg))


def room(geometry: Geometry, lamp, ambient: float = 1.0, lamp_power: float = 1.0) -> np.ndarray:
    """Uniform sky of radiosity ``ambient`` plus an isotropic lamp; (N,) float64.

    The sky's irradiance on patch i is ``ambient (1 - sum_j F[i, j])``, the part of
    its view that no patch (hidden ones included) fills.
    """
    sky = ambient * np.clip(1.0 - geometry.form_factors.sum(axis=1), 0.0, None)
    return geometry.albedo * sky + point_source(geometry, lamp, lambda omega: np.full(len(omega), float(lamp_power)))


#: the projector's default stripe width (degrees): a cycle is twice it
PROJECTOR_PERIOD_DEG = 6.0


def projector(geometry: Geometry, position, target, half_angle_deg: float, period_deg: float = PROJECTOR_PERIOD_DEG,
              pattern: str = "stripes", power: float = 1.0, phase_deg: float = 0.0) -> np.ndarray:
    """Point source modulated over angle by a binary pattern, with shadows; (N,) float64.

    ``pattern``: "stripes" (bright where floor((horizontal angle - phase) / period) is
    even), "checker" (also alternating in the vertical angle; same as stripes in
    flatland) or "full" (every projector pixel on). ``phase_deg`` shifts the pattern
    (Nayar et al. 2006's shifted patterns: :mod:`ilt.separate`).
    """
    if pattern not in ("stripes", "checker", "full"):
        raise ValueError(f"projector pattern must be 'stripes', 'checker' or 'full', got {pattern!r}")
    if period_deg <= 0:
        raise ValueError(f"projector period_deg must be > 0, got {period_deg}")

    def intensity(omega):
        shifted = np.degrees(_beam_angles(omega, position, target))
        shifted[:, 0] -= phase_deg
        cells = np.floor(shifted / period_deg).astype(int)
        parity = cells[:, 0] if pattern == "stripes" else cells.sum(axis=1)
        lit = np.ones(len(omega), dtype=bool) if pattern == "full" else parity % 2 == 0
        return power * (lit & _cone(omega, position, target, half_angle_deg))

    return point_source(geometry, position, intensity)


_KINDS = {"flashlight": flashlight, "room": room, "projector": projector}


def direct_light(geometry: Geometry, kind: str, **params) -> np.ndarray:
    """(N,) float64 direct radiosity of all patches under illumination ``kind`` (one of :data:`ILLUMINATIONS`).

    ``params`` override the scene's :data:`DEFAULTS` and the function's own.
    """
    if kind not in _KINDS:
        raise ValueError(f"unknown illumination {kind!r}; choose one of {ILLUMINATIONS}")
    function = _KINDS[kind]
    allowed = set(inspect.signature(function).parameters) - {"geometry"}
    if unknown := set(params) - allowed:
        raise ValueError(f"illumination {kind!r} has no parameter(s) {sorted(unknown)}; it takes {sorted(allowed)}")
    return function(geometry, **(DEFAULTS[geometry.dim][kind] | params))
