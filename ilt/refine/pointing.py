"""Pixel targets to pan/tilt: the map from the plan's angles to the spots it gave, inverted locally.

A beam aimed at (pan, tilt) lands at a spot pixel (x, y) through the unit's geometry, the
scene's depth and the lens: unknown in closed form, smooth between neighbouring beams.
Around a target pixel the map is taken as affine, fitted by least squares over the
``neighbours`` nearest spots of the scan (pixel -> angle, so the inverse is what is
fitted), and evaluated at the target. On a line of spots the fit is rank-deficient
across the line; the least-norm solution keeps the line's other angle.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ilt.capture.plan import Plan, out_of_limits, to_steps

from .indicator import RefineError

#: spots in each local fit (an affine map has 3 unknowns per angle)
NEIGHBOURS = 6


def aim(targets: np.ndarray, spots: np.ndarray, angles: np.ndarray, neighbours: int = NEIGHBOURS) -> np.ndarray:
    """(K, 2) (pan, tilt) for (K, 2) pixel targets, from the scan's (m, 2) spot pixels
    and the (m, 2) angles that gave them (any units: the result is in the same)."""
    targets, spots, angles = (np.asarray(a, dtype=np.float64) for a in (targets, spots, angles))
    k = min(neighbours, len(spots))
    if len(targets) == 0:
        return np.empty((0, 2))
    _, near = cKDTree(spots).query(targets, k=k)
    near = near.reshape(len(targets), k)
    out = np.empty((len(targets), 2))
    for n, (target, idx) in enumerate(zip(targets, near)):
        centre = spots[idx].mean(axis=0)
        design = np.column_stack([np.ones(k), spots[idx] - centre])
        coef = np.linalg.lstsq(design, angles[idx], rcond=1e-9)[0]
        out[n] = coef[0] + (target - centre) @ coef[1:]
    return out


def check_reach(angles: np.ndarray, targets: np.ndarray, units: str, ptu: dict | None, source: str) -> None:
    """Every (pan, tilt) within the unit's limits, when the capture recorded them
    (``ptu``: the capture manifest's ``ptu``, with ``limits`` and ``resolution_arcsec``).
    Raises RefineError naming ``source``, the first target out of reach and its pixel."""
    if not ptu or "limits" not in ptu:
        return
    resolution = (ptu["resolution_arcsec"]["pan"], ptu["resolution_arcsec"]["tilt"])
    steps = to_steps(Plan("list", units, np.rint(angles) if units == "steps" else angles, (1, len(angles))),
                     resolution)
    outside = out_of_limits(steps, ptu["limits"])
    if outside:
        axis, col, bad, lo, hi = outside
        n = int(bad[0])
        raise RefineError(
            f"{source}: new beam {n} at pixel ({targets[n, 0]:.1f}, {targets[n, 1]:.1f}) needs {axis} "
            f"{int(steps[n, col])} steps, outside the unit's limits [{lo}, {hi}] ({bad.size} target(s) out of "
            "reach); lower --beams or widen the unit's limits")
