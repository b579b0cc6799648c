"""A spot's direct light in its neighbours' cells: the spill matrix ``Q`` (docs/spots-and-isf.md).

The cancellation theorem takes ``T1`` diagonal: beam j's direct light falls in its own
cell. A real spot has a size of its own, fixed by the laser, not by the scan: when the
beams are denser than about 3 spot sigmas apart, its flank lights the next cells, and
that direct light, read as indirect, is what the recursion then amplifies (on the
emulated M, 32 beams of the 16-beam scan's spot: bounce errors 0.099 against 0.051 at 16
beams, noise-free; 2.7% of the direct light in other cells).

With the flank measured, ``T1 = (I + Q) D``: ``Q[i, j]`` is beam j's direct light in
cell i over its direct light in its own cell (i != j), ``D`` diagonal. Then
``T = (I - A)^-1 (I + Q) D`` and ``T'' = (I + Q)^-1 T = (I - A'')^-1 D`` with
``A'' = (I + Q)^-1 A (I + Q)``: the paper's form again, whose ``C1'' = D T''^-1`` splits
``p'' = (I + Q)^-1 p``; the bounces are ``(I + Q) L''_n`` (:mod:`ilt.decompose.stage`).
(``A''`` has a diagonal of order Q A, not 0: the one approximation.)

The flank is measured on each beam frame, around its spot: the background is a plane
fitted to a ring of pixels around the spot, the spot is the connected part of what
rises above it by more than the frame's noise (``SPILL_SIGMAS`` of the noise model's
sigma at the pixel's level, :mod:`ilt.isf.noise`) and more than ``SPILL_FLOOR`` of the
spot's peak, and ``Q[:, j]`` is its sum over each cell over its sum over cell j. Entries
under ``SPILL_MIN`` are left out (``spill.npz`` is sparse).
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage
import scipy.sparse

#: the spot must rise this many noise sigmas above the background ring
SPILL_SIGMAS = 3.0
#: and this share of its own peak (keeps out the indirect light near the spot)
SPILL_FLOOR = 1e-3
#: spill entries below this share of the own cell's direct light are dropped
SPILL_MIN = 1e-4
#: how far from its centre a spot is followed, in its own sigmas (measured on its core)
SPOT_SIGMAS = 4.0
#: the window around a spot, in nearest-spot distances (capped by MAX_RADIUS px)
WINDOW = 1.5
MAX_RADIUS = 32
#: the spot's core, which its Gaussian is fitted to: the pixels above the first of these shares
#: of its peak that holds CORE_PIXELS of them. A spot under a pixel's sigma across its short axis
#: (a floor's, seen at a grazing angle) has 3-5 pixels above a quarter of its peak, all on one
#: row; taken round from their area, its flank along the row was lost: on the 4x box lattice's 768
#: beams (noise-free) 238 spots' spill short of the renderer's by 0.005 of their own cell's light
#: or more (0.004 against 0.070 at worst), the scan's 83% of it, and its bounces worse than the
#: 432 beams'. Above a tenth: 99.5% of it (docs/spots-and-isf.md, "A spot on one row").
CORE_SHARES = (0.25, 0.1)
CORE_PIXELS = 6
SPILL_FILE = "spill.npz"


def spot_windows(on_grid: np.ndarray) -> np.ndarray:
    """(m,) window radius (grid px) around each spot: WINDOW x its nearest-spot distance,
    between 3 and MAX_RADIUS px."""
    from scipy.spatial import cKDTree

    if len(on_grid) < 2:
        return np.full(len(on_grid), 3.0)
    nn = cKDTree(on_grid).query(on_grid, k=2)[0][:, 1]
    return np.clip(WINDOW * nn, 3.0, MAX_RADIUS)


def spot_spill(frame: np.ndarray, labels: np.ndarray, own: int, centre: np.ndarray, radius: float,
               noise=None) -> dict[int, float]:
    """Cell -> the share of the spot's direct light in that cell over its share in its
    own cell ``own`` (module docstring), for the cells other than ``own`` holding more
    than SPILL_MIN of it. ``centre`` (x, y) and ``radius`` in grid pixels; ``noise``: a
    :class:`~ilt.isf.noise.FrameNoise` (None: noise-free frames, no noise test)."""
    height, width = frame.shape
    ring = radius + 2.0
    x0, x1 = max(0, int(centre[0] - ring)), min(width, int(centre[0] + ring) + 2)
    y0, y1 = max(0, int(centre[1] - ring)), min(height, int(centre[1] + ring) + 2)
    window = np.asarray(frame[y0:y1, x0:x1], dtype=np.float64)
    cells = labels[y0:y1, x0:x1]
    yy, xx = np.mgrid[y0:y1, x0:x1]
    dx, dy = xx - centre[0], yy - centre[1]
    d = np.hypot(dx, dy)
    edge = (d >= radius) & (d < ring)
    if edge.sum() < 3:
        return {}
    design = np.column_stack([np.ones(int(edge.sum())), dx[edge], dy[edge]])
    coef = np.linalg.lstsq(design, window[edge], rcond=None)[0]
    rise = window - (coef[0] + coef[1] * dx + coef[2] * dy)
    inside = d < radius
    peak = float(rise[inside].max()) if inside.any() else 0.0
    if not peak > 0:
        return {}
    model = _spot_model(rise, inside, peak, dx, dy, centre - (x0, y0))
    if model is None:
        return {}
    # the direct light: the spot's own shape, where the frame has it (a spot cut by a
    # fold has no flank beyond it; the light that rises there is indirect)
    direct = np.minimum(model, np.maximum(rise, 0.0))
    keep = inside & (model > SPILL_FLOOR * peak) & (cells >= 0)
    if noise is not None:   # a flank lost in the noise is not measured
        keep &= model > SPILL_SIGMAS * np.sqrt(noise.pixel_variance(np.maximum(window, 0.0)))
    sums = np.bincount(cells[keep], weights=direct[keep])
    if own >= len(sums) or not sums[own] > 0:
        return {}
    shares = sums / sums[own]
    return {int(i): float(s) for i, s in enumerate(shares) if i != own and s > SPILL_MIN}


def _spot_model(rise, inside, peak, dx, dy, at) -> np.ndarray | None:
    """The spot as a 2D Gaussian fitted to its core (the connected pixels above
    :data:`CORE_SHARES` of its peak around the centre, the first share that gives 6 or more
    of them): log-quadratic least squares (6 terms), else round with the sigma of the first
    core's area (2 pi sigma^2 ln 4). None when there is no core."""
    cy = int(np.clip(round(at[1]), 0, rise.shape[0] - 1))
    cx = int(np.clip(round(at[0]), 0, rise.shape[1] - 1))
    first = None
    for share in CORE_SHARES:
        core = inside & (rise > share * peak)
        parts, _ = scipy.ndimage.label(core)
        part = parts[cy, cx] or (parts[np.unravel_index(np.argmax(np.where(core, rise, -np.inf)), rise.shape)])
        if part == 0:
            return None
        core = parts == part
        first = core if first is None else first
        if core.sum() < CORE_PIXELS:
            continue
        x, y = dx[core], dy[core]
        design = np.column_stack([np.ones(x.size), x, y, x * x, x * y, y * y])
        c = np.linalg.lstsq(design, np.log(rise[core]), rcond=None)[0]
        curvature = np.array([[c[3], c[4] / 2], [c[4] / 2, c[5]]])
        if np.all(np.linalg.eigvalsh(curvature) < 0):
            value = c[0] + c[1] * dx + c[2] * dy + c[3] * dx * dx + c[4] * dx * dy + c[5] * dy * dy
            return np.exp(np.minimum(value, np.log(peak) + 1.0))
    sigma = max(np.sqrt(first.sum() / (2 * np.pi * np.log(4.0))), 0.3)
    return peak * np.exp(-(dx * dx + dy * dy) / (2 * sigma * sigma))


def spill_matrix(columns: list[dict[int, float]], m: int) -> scipy.sparse.csr_matrix:
    """``Q`` (m, m) from each beam's :func:`spot_spill` (column j: beam j's)."""
    rows = [i for c in columns for i in c]
    cols = [j for j, c in enumerate(columns) for _ in c]
    vals = [v for c in columns for v in c.values()]
    return scipy.sparse.csr_matrix((vals, (rows, cols)), shape=(m, m))


class Unmixing:
    """``I + Q`` factorised once (sparse LU: Q holds a few entries a column): ``unmix``
    solves with it, ``mix`` multiplies by it; values of shape (m, ...)."""

    def __init__(self, Q: scipy.sparse.spmatrix):
        import scipy.sparse.linalg

        self.Q = Q.tocsr()
        self.m = Q.shape[0]
        self._lu = scipy.sparse.linalg.splu((scipy.sparse.identity(self.m, format="csc") + Q.tocsc()).tocsc())

    def unmix(self, values: np.ndarray, out: np.ndarray | None = None, block: int = 1024) -> np.ndarray:
        """``(I + Q)^-1 values``; with ``out`` (e.g. a memory map), written there a block of
        ``block`` columns at a time, so nothing the size of ``values`` is held in memory."""
        if out is not None:
            for c0 in range(0, values.shape[1], block):
                out[:, c0:c0 + block] = self._lu.solve(np.ascontiguousarray(values[:, c0:c0 + block],
                                                                            dtype=np.float64))
            return out
        values = np.asarray(values, dtype=np.float64)
        flat = values.reshape(self.m, -1)
        return (self._lu.solve(np.ascontiguousarray(flat)) if flat.shape[1] else flat.copy()).reshape(values.shape)

    def mix(self, values: np.ndarray) -> np.ndarray:
        """``(I + Q) values``."""
        values = np.asarray(values, dtype=np.float64)
        flat = values.reshape(self.m, -1)
        return (flat + self.Q @ flat).reshape(values.shape)
