"""Isolated outlier pixels in a beam frame: fireflies, hot pixels, cosmic rays.

A path tracer's Monte Carlo noise is not only Poisson-like: now and then one pixel of a
frame is far too bright (a firefly); a sensor has hot pixels and cosmic-ray hits. Light
that reaches a camera through a lens is never a single pixel far above all eight of its
neighbours, a laser spot included (its disc is left alone all the same). Such a pixel adds
a large wrong value to one cell's sum for one beam: one entry of T, which a denser scan's
smaller cells average less (docs/fullres.md, "Monte Carlo outliers"). :func:`clamp_isolated`
replaces each by the median of its neighbours, judged against the frames' own noise model
(:mod:`ilt.isf.noise`): without one (noise-free frames) nothing is touched.
"""

from __future__ import annotations

import numpy as np

#: a pixel this many sigmas above the brightest of its eight neighbours is an isolated
#: outlier (on the noise model's variance-stabilising scale: :func:`_stabiliser`)
OUTLIER_SIGMAS = 6.0

#: the laser spot's own disc is left alone (its peak pixel can stand far above its
#: neighbours): this many times the radius of the spot's area, and at least this many pixels
SPOT_RADII = 3.0


def spot_radius(area: float) -> float:
    """The radius (px) about a spot of ``area`` pixels over threshold left alone."""
    return max(SPOT_RADII, SPOT_RADII * float(np.sqrt(max(area, 0.0) / np.pi)))


#: the share of a noise model's knots, from the faintest, a screening model keeps
SCREEN_KNOTS = 0.75


def screening_model(noise):
    """A noise model for a first search for outliers in the frames it was fitted on: its
    fainter knots (:data:`SCREEN_KNOTS` of them) and, above, the slope of a line through
    them. Fireflies inflate the bright bins of a fit (a frame's brightest 5 x 5 means hold
    them: on the M with 1e-3 of the pixels at 20x, the top bin's variance was 68x and the
    slope 33x the clean fit's), and a model that noisy hides every one of them; the faint
    bins hold too many pixels to be moved."""
    from dataclasses import replace

    keep = max(2, int(np.ceil(SCREEN_KNOTS * len(noise.levels))))
    levels, variances = np.asarray(noise.levels[:keep]), np.asarray(noise.variances[:keep])
    spread = levels - levels.mean()
    width = float(np.dot(spread, spread))
    slope = float(np.dot(spread, variances - variances.mean())) / width if width > 0 else 0.0
    return replace(noise, levels=tuple(levels), variances=tuple(variances), slope=max(slope, 0.0))


_BUFFERS: dict = {}


def _buffers(shape) -> tuple[np.ndarray, np.ndarray]:
    """Two (H, W) float32 work arrays for the screens, kept per process for frames of one
    shape (96 MB at 12 Mpx; allocated afresh, each frame's page faults cost more than the
    test). The exact test reads the frame itself."""
    if shape not in _BUFFERS:
        _BUFFERS.clear()
        _BUFFERS[shape] = (np.empty(shape, np.float32), np.empty(shape, np.float32))
    return _BUFFERS[shape]


def _at(frame: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``frame[rows, cols]``, NaN outside the frame."""
    height, width = frame.shape
    inside = (rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)
    out = np.full(rows.shape, np.nan)
    out[inside] = frame[rows[inside], cols[inside]]
    return out


def _variance_line(noise) -> tuple[float, float]:
    """(a, b) with ``a + b x <= Var(x)`` for every level x >= 0 of the model: a line under
    its knots, and under its slope above them."""
    levels, variances = np.asarray(noise.levels), np.asarray(noise.variances)
    dark = max(float(noise.pixel_variance(np.zeros(1))[0]), 0.0)
    positive = levels > 0
    rises = (variances[positive] - dark) / levels[positive] if positive.any() else np.array([0.0])
    return dark, max(0.0, min(float(rises.min()), float(noise.slope)))


_STABILISERS: dict = {}


def _stabiliser(noise):
    """``f(x)``: the noise model's variance-stabilising transform, the integral of
    ``1 / sigma(t)`` from 0 (Anscombe's ``2 sqrt(x)`` for photon counts): a pixel's noise is
    1 on its scale at every level, so a difference of ``k`` there is ``k`` sigma whatever the
    light. The variance is taken at least ``slope x`` (the photon noise the model's slope
    says): a model fitted where most faint pixels count no photon gives 0 there, and one
    photon above none would be infinitely many sigma. Built once per model (a table on a
    grid uniform in sqrt(x), where the integrand is smooth)."""
    key = (noise.levels, noise.variances, noise.slope)
    if key not in _STABILISERS:
        top = max(float(noise.levels[-1]), 1e-12)
        u = np.concatenate([np.linspace(0.0, 4.0 * np.sqrt(top), 4097),
                            np.sqrt(top) * np.geomspace(4.0, 1e6, 1024)[1:]])
        x = u * u
        variance = np.maximum(noise.pixel_variance(x), noise.slope * x)
        floor = max(float(np.max(noise.variances)), 1.0) * 1e-12
        integrand = 2.0 * u / np.sqrt(np.maximum(variance, floor))     # dx = 2u du
        table = np.concatenate([[0.0], np.cumsum(0.5 * (integrand[1:] + integrand[:-1]) * np.diff(u))])
        below = 1.0 / np.sqrt(max(float(noise.pixel_variance(np.zeros(1))[0]), floor))   # x < 0: sigma at 0

        def scale(values):
            values = np.asarray(values, dtype=np.float64)
            root = np.sqrt(np.maximum(values, 0.0))
            return np.where(values < 0, values * below, np.interp(root, u, table))
        _STABILISERS[key] = scale
    return _STABILISERS[key]


_OFFSETS = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]


def clamp_isolated(frame: np.ndarray, noise, spot: np.ndarray | None = None, radius: float = 0.0,
                   sigmas: float = OUTLIER_SIGMAS, replaced: list | None = None) -> int:
    """Replace, in place, each pixel of ``frame`` (H, W) that stands more than ``sigmas``
    noise sigmas (of the difference) above the brightest of its 8 neighbours by the median
    of those 8; the pixels within ``radius`` of ``spot`` (x, y) are left alone. ``noise``:
    the frames' :class:`ilt.isf.noise.FrameNoise`, or None (then nothing is done). Returns
    how many pixels were replaced (and appends their flat indices to ``replaced``, if given).

    At the frame's edge a pixel is judged on the neighbours it has. Cost: screens on the two
    horizontal neighbours in work arrays kept per process (a 3 x 3 maximum filter took
    0.34 s at 12 Mpx), then the exact test on the few pixels they leave
    (benchmarks/bench_outliers.py)."""
    if noise is None or frame.ndim != 2 or frame.shape[1] < 2:
        return 0
    height, width = frame.shape
    sides, diff = _buffers(frame.shape)
    # a pixel above both horizontal neighbours (the one it has, at the frame's left and right
    # edges) by the least sigma there is, then by a line under the model's variance, then on
    # the stabilised scale: each screen keeps every pixel the exact test can flag
    np.maximum(frame[:, :-2], frame[:, 2:], out=sides[:, 1:-1])
    sides[:, 0], sides[:, -1] = frame[:, 1], frame[:, -2]
    np.subtract(frame, sides, out=diff)
    # on the stabilised scale a difference d from level s is at most d / sigma(s) <= d / the
    # least sigma, and with photon noise alone (no sigma at zero, no level below it) at most
    # 2 sqrt(d / slope): so no pixel the test flags is under this floor
    least = max(min(noise.variances), 0.0)
    floor = sigmas * np.sqrt(2.0 * least) if least > 0 else sigmas**2 * noise.slope / 2.0
    candidates = np.flatnonzero(diff > floor)
    if candidates.size:
        dark, per_level = _variance_line(noise)
        level = np.maximum(sides.flat[candidates], 0.0)
        candidates = candidates[np.square(diff.flat[candidates]) > 2.0 * sigmas**2 * (dark + per_level * level)]
    scale = _stabiliser(noise)
    if candidates.size:
        candidates = candidates[scale(frame.flat[candidates]) - scale(sides.flat[candidates]) > sigmas * np.sqrt(2.0)]
    if candidates.size == 0:
        return 0
    rows, cols = np.divmod(candidates, width)
    neighbours = np.stack([_at(frame, rows + dy, cols + dx) for dy, dx in _OFFSETS])    # (8, n), NaN outside
    brightest = np.nanmax(neighbours, axis=0)
    values = frame[rows, cols]
    # on the noise model's variance-stabilising scale, where the noise is 1 at every level:
    # the difference of two pixels has sigma sqrt(2)
    out = scale(values) - scale(brightest) > sigmas * np.sqrt(2.0)
    if spot is not None and radius > 0:
        out &= np.hypot(cols - spot[0], rows - spot[1]) > radius
    if not out.any():
        return 0
    frame[rows[out], cols[out]] = np.nanmedian(neighbours[:, out], axis=0)
    if replaced is not None:
        replaced.extend((rows[out] * width + cols[out]).tolist())
    return int(out.sum())


def fresh_outliers(replaced: list[list[int]], pixels: int) -> float:
    """The share of a frame's ``pixels`` that are outliers at pixels of their own (fireflies),
    from those :func:`clamp_isolated` replaced in each of a sample of frames (``replaced``:
    flat indices per frame): the distinct pixels less one frame's mean, over the frames but
    one (an outlier at the same pixel of every frame, a hot pixel, counts once)."""
    counts = [len(set(r)) for r in replaced]
    if not counts or not any(counts):
        return 0.0
    if len(counts) == 1:
        return counts[0] / pixels
    distinct = len(set().union(*map(set, replaced)))
    return max(0.0, (distinct - float(np.mean(counts))) / (len(counts) - 1)) / pixels


__all__ = ["OUTLIER_SIGMAS", "SPOT_RADII", "clamp_isolated", "fresh_outliers", "screening_model", "spot_radius"]
