"""Laser spot centroids with quality flags (paper Sec. 4: "the centroid of the laser
spot in the shortest exposure gives pixel i for beam i").

Per frame (:func:`find_spot`): subtract a dark frame when one was captured, estimate a
robust local background map (a large median), threshold relative to the peak above it,
label connected components (OpenCV), keep the component holding the peak, fit a plane to the ring
around it as the local background level, and take the intensity-weighted centroid of
the background-subtracted values in a window of about +-4 spot sigmas (sub-pixel).
Optionally refine with a least-squares 2D Gaussian. Pixel convention of DESIGN.md:
x right, y down, the centre of the top-left pixel at (0, 0); :func:`find_spot` works in
the frame's own pixels, the stage maps them to full-frame sensor pixels.

QA flags (name=figure): ``none`` (peak over noise below ``min_snr``), ``multiple``
(flux of the second spot / the first), ``large`` (area / median area of the scan, or
the area when over ``max_area``), ``elongated`` (ratio of the principal axes),
``saturated`` (pixels on the flat top), ``outside`` (spot on the frame border or
outside the region of interest; figure: distance to it in pixels).
"""

from __future__ import annotations

import functools
import logging
import math
import threading
from dataclasses import dataclass

import cv2
import numpy as np

from ilt.spots.table import Spot

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SpotParameters:
    """What counts as a clean spot.

    threshold: component threshold, fraction of (peak - background).
    min_snr: peak over robust noise below this is ``none``.
    max_second: ``multiple`` when another component's flux / the spot's >= this.
    max_elongation: ``elongated`` when sqrt(lambda1 / lambda2) of the spot's second moments > this.
    large_factor: ``large`` when the area > this x the median area of the scan's clean spots.
    max_area: ``large`` when the area (pixels over threshold) exceeds it (None: no limit).
    saturation: pixel level at which the sensor clips (None: detect a flat top).
    roi: (x0, y0, x1, y1) pixels a spot must lie in (None: the frame).
    refine: refine the centroid with a 2D Gaussian fit.
    """

    threshold: float = 0.2
    min_snr: float = 10.0
    max_second: float = 0.05
    max_elongation: float = 2.0
    large_factor: float = 4.0
    max_area: float | None = None
    saturation: float | None = None
    roi: tuple[float, float, float, float] | None = None
    refine: bool = False


#: a pixel whose 8 neighbours all hold less than this share of its light above the
#: background is no light through a lens (the next pixel of a pixel-integrated Gaussian spot
#: centred on its pixel holds 5% of the peak at sigma 0.3 px, 23% at 0.5, 50% at 0.8): a
#: firefly, hot pixel or cosmic-ray hit, neither taken for the spot nor counted as a second
#: one. (A spot sharper still, sigma 0.25 px, would read so: it is kept when the frame holds
#: no other light the spot test passes.)
ISOLATED_SHARE = 0.03
#: at most this many such pixels brighter than the spot are passed over in one frame
_MAX_ISOLATED = 1000

#: pixels of a flat top (within this relative distance of the max) that mean clipping
_PLATEAU_REL = 1e-3
_PLATEAU_MIN = 5
#: centroid aperture radius in spot sigmas, and its re-centring passes
_APERTURE = 3.5
_APERTURE_ITERATIONS = 20


def find_spot(image: np.ndarray, params: SpotParameters = SpotParameters(),
              dark: np.ndarray | None = None) -> Spot:
    """The laser spot in one frame.

    image: (H, W) float linear frame; dark: (H, W) dark frame to subtract, or None.
    Returns a :class:`Spot` in the frame's own pixels (x, y NaN when flagged ``none``).

    The whole frame is touched only by a few vectorised passes (peak, background map,
    threshold); components are labelled in a window around the peak, and over the whole
    frame only when pixels over threshold lie outside the spot (a second spot or noise).
    """
    img = np.asarray(image)
    if dark is not None:
        img = img - dark
    height, width = img.shape
    # full-frame passes in float32 into this thread's buffers; the window in float64
    full = np.ascontiguousarray(img, dtype=np.float32)
    level, mask = _frame_buffers(img.shape)
    grid, noise = _background_grid(full)
    iy, ix = np.unravel_index(int(np.argmax(full)), img.shape)
    first, originals = (iy, ix), (full, img)
    for _ in range(_MAX_ISOLATED):
        if not _isolated(full, _background_at(grid, img.shape, iy, ix), iy, ix):
            break
        # an isolated pixel brighter than the spot: set to its neighbours' median, in copies
        # (never in the caller's frame), and the peak sought again
        if np.shares_memory(full, image):
            full = full.copy()
        if img is image or np.shares_memory(img, image):
            img = img.copy()
        full[iy, ix] = img[iy, ix] = _neighbour_median(full, iy, ix)
        iy, ix = np.unravel_index(int(np.argmax(full)), img.shape)
    if (iy, ix) != first:
        left = float(img[iy, ix]) - _background_at(grid, img.shape, iy, ix)
        if not left > params.min_snr * noise:     # nothing else there: the sharp pixel was the spot
            (iy, ix), (full, img) = first, originals
    top = float(img[iy, ix])
    amplitude = top - _background_at(grid, img.shape, iy, ix)
    if not amplitude > max(params.min_snr * noise, 1e-30 * max(1.0, abs(top))):
        snr = amplitude / noise if noise > 0 else 0.0
        return Spot(math.nan, math.nan, 0.0, max(amplitude, 0.0), 0, {"none": round(snr, 3)})
    # the spot's component, thresholded in windows around the peak; the whole frame is
    # compared with one level under every pixel's threshold (one pass), and thresholded
    # exactly, and labelled, only when pixels over that level lie outside the spot
    cut = float(params.threshold * amplitude)

    def over_threshold(rows: slice, cols: slice) -> np.ndarray:
        return (full[rows, cols] > _background_window(grid, img.shape, rows, cols) + cut).view(np.uint8)

    (x0, y0, w, h, area), core = _peak_component(over_threshold, img.shape, iy, ix)
    box = (slice(y0, y0 + h), slice(x0, x0 + w))
    floor = float(grid.min()) + cut
    floor -= 1e-6 * (abs(floor) + cut)  # below every level, after rounding to float32
    others = np.empty(0)
    if cv2.countNonZero(cv2.compare(full, floor, cv2.CMP_GT, dst=mask)) > area:
        level = _background_map(grid + np.float32(cut), img.shape, out=level)
        mask = cv2.compare(full, level, cv2.CMP_GT, dst=mask)
        if cv2.countNonZero(mask) > area:
            others = _other_fluxes(mask, full, level, cut, iy, ix)
    flags: dict = {}
    if others.size:
        own_flux = float((full[box][core] - _background_window(grid, img.shape, *box)[core]).sum())
        if others.max() >= params.max_second * own_flux:
            flags["multiple"] = round(float(others.max() / own_flux), 4)
    sigma = math.sqrt(area / math.pi) / math.sqrt(2 * math.log(1 / params.threshold))
    pad = int(math.ceil(2.5 * sigma)) + 2
    ys, xs = slice(max(0, y0 - pad), min(height, y0 + h + pad)), slice(max(0, x0 - pad), min(width, x0 + w + pad))
    window = img[ys, xs].astype(np.float64)
    # pixel coordinates as a row and a column: every use broadcasts them over the window
    gx = np.arange(xs.start, xs.stop, dtype=np.float64)[None, :]
    gy = np.arange(ys.start, ys.stop, dtype=np.float64)[:, None]
    plane = _background_plane(window)
    values = window - plane
    flux = float(values.sum())
    if not flux > 0:
        return Spot(math.nan, math.nan, 0.0, amplitude, area, {"none": 0.0})
    cx, cy = _aperture_centroid(values, gx, gy, float((values * gx).sum() / flux),
                                float((values * gy).sum() / flux), _APERTURE * sigma)
    if params.refine:
        cx, cy = _gaussian_refine(values, gx, gy, cx, cy, sigma)
    in_window = np.zeros(window.shape, dtype=bool)
    in_window[y0 - ys.start:y0 - ys.start + h, x0 - xs.start:x0 - xs.start + w] = core
    flags.update(_shape_flags(values, gx, gy, in_window, cx, cy, params))
    plateau = int((window[in_window] >= top - _PLATEAU_REL * abs(top)).sum())
    if params.saturation is not None:
        clipped = int((window >= params.saturation).sum())
        if clipped:
            flags["saturated"] = clipped
    elif plateau >= _PLATEAU_MIN:
        flags["saturated"] = plateau
    outside = _outside(x0, y0, w, h, cx, cy, (height, width), params.roi)
    if outside is not None:
        flags["outside"] = outside
    if params.max_area is not None and area > params.max_area:
        flags["large"] = area
    return Spot(cx, cy, flux, float(values.max()), area, flags)


#: the background map: medians of blocks of ``_BLOCK_SAMPLES``^2 samples on a grid of
#: about ``_BLOCKS`` blocks along the frame's long side, then a median over
#: ``_BLOCK_FILTER``^2 blocks, so spots up to a few blocks wide do not raise it
_BLOCKS = 16
_BLOCK_SAMPLES = 4
_BLOCK_FILTER = 7


_BUFFERS = threading.local()


def _frame_buffers(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """This thread's full-frame scratch arrays (threshold level, mask), kept between
    frames of one shape: a fresh frame-sized array per pass costs page faults that
    took more time than the arithmetic (find_spot 3.4 -> 1.5 ms at 640 x 480 from
    the buffers alone)."""
    held = getattr(_BUFFERS, "arrays", None)
    if held is None or held[0].shape != shape:
        held = (np.empty(shape, np.float32), np.empty(shape, np.uint8))
        _BUFFERS.arrays = held
    return held


def _background_grid(img: np.ndarray) -> tuple[np.ndarray, float]:
    """A robust local background level on a coarse grid, (by, bx) float32 (each cell
    ``block`` = ``_background_block(shape)`` pixels square), and the pixel noise sigma.

    A large median: block medians of a subsampled frame, median-filtered over
    ``_BLOCK_FILTER`` blocks; interpolated back (:func:`_background_map`) it follows
    smooth backgrounds (interreflections, gradients of half the peak across the frame)
    that a single level would let over the threshold as false spots. The noise comes
    from differences of neighbouring samples, so a smooth background is not counted as
    noise. A frame too small for blocks gets a (1, 1) grid: one level.
    """
    step = _background_block(img.shape) // _BLOCK_SAMPLES
    # a side shorter than half a step (a wide flatland frame of 32 rows) is sampled from its middle
    y0, x0 = (min(step // 2, (n - 1) // 2) for n in img.shape)
    samples = img[y0::step, x0::step].astype(np.float32)
    if samples.size < 2:   # too few samples for differences: neighbouring pixels give the noise
        samples = img.astype(np.float32)
    diff = np.diff(samples, axis=1) if samples.shape[1] > 1 else np.diff(samples, axis=0)
    diff = diff.ravel()
    noise = 1.4826 * float(_median(np.abs(diff - _median(diff)))) / math.sqrt(2)
    if samples.shape[0] < _BLOCK_SAMPLES or samples.shape[1] < _BLOCK_SAMPLES:
        return np.full((1, 1), np.median(samples), np.float32), noise
    by, bx = samples.shape[0] // _BLOCK_SAMPLES, samples.shape[1] // _BLOCK_SAMPLES
    cells = samples[:by * _BLOCK_SAMPLES, :bx * _BLOCK_SAMPLES].reshape(by, _BLOCK_SAMPLES, bx, _BLOCK_SAMPLES)
    coarse = _median(cells.transpose(0, 2, 1, 3).reshape(by, bx, -1)).astype(np.float32)
    return _median_filter(coarse, min(_BLOCK_FILTER, by), min(_BLOCK_FILTER, bx)), noise


def _median(a: np.ndarray) -> np.ndarray:
    """np.median over the last axis (all of a 1-D array), by partition: the same
    values (the mean of the two middle ones for an even count) at half the cost on the
    few thousand samples of a frame's background."""
    n = a.shape[-1]
    k = n // 2
    if n % 2:
        return np.partition(a, k, axis=-1)[..., k]
    part = np.partition(a, (k - 1, k), axis=-1)
    return 0.5 * (part[..., k - 1] + part[..., k])


def _median_filter(grid: np.ndarray, ky: int, kx: int) -> np.ndarray:
    """scipy.ndimage.median_filter(grid, (ky, kx), mode="nearest") on a small grid, by
    partition over the windows gathered with one index (the same values: rank
    (ky kx) // 2; 0.04 against 0.21 ms on the 12 x 16 grid of a 640 x 480 frame)."""
    windows = grid.ravel()[_window_index(grid.shape, ky, kx)]
    k = ky * kx // 2
    return np.partition(windows, k, axis=-1)[..., k]


@functools.lru_cache(maxsize=8)
def _window_index(shape: tuple[int, int], ky: int, kx: int) -> np.ndarray:
    """(H, W, ky kx) flat indices of each pixel's ky x kx window, edges replicated
    (scipy's mode "nearest", its window origin for even sizes)."""
    height, width = shape
    rows = np.clip(np.arange(height)[:, None] + np.arange(ky) - ky // 2, 0, height - 1)
    cols = np.clip(np.arange(width)[:, None] + np.arange(kx) - kx // 2, 0, width - 1)
    index = rows[:, None, :, None] * width + cols[None, :, None, :]
    return index.reshape(height, width, ky * kx)


def _background_block(shape: tuple[int, int]) -> int:
    """Pixels per side of a background grid cell."""
    return max(1, max(shape) // (_BLOCKS * _BLOCK_SAMPLES)) * _BLOCK_SAMPLES


def _background_map(grid: np.ndarray, shape: tuple[int, int], out: np.ndarray | None = None) -> np.ndarray:
    """The grid interpolated to the frame (bilinear, cell centres at the cells' centres,
    edges replicated), (H, W) float32 into ``out``."""
    height, width = shape
    out = np.empty(shape, np.float32) if out is None else out
    if grid.size == 1:
        out[...] = grid.flat[0]
        return out
    block = _background_block(shape)
    by, bx = grid.shape
    if (by * block, bx * block) == (height, width):  # the common case: blocks tile the frame
        return cv2.resize(grid, (width, height), dst=out, interpolation=cv2.INTER_LINEAR)
    fine = cv2.resize(grid, (bx * block, by * block), interpolation=cv2.INTER_LINEAR)[:height, :width]
    cv2.copyMakeBorder(fine, 0, height - fine.shape[0], 0, width - fine.shape[1], cv2.BORDER_REPLICATE, dst=out)
    return out


def _background_at(grid: np.ndarray, shape: tuple[int, int], y: int, x: int) -> float:
    """:func:`_background_map` at one pixel, without drawing the map."""
    return float(_background_window(grid, shape, slice(y, y + 1), slice(x, x + 1))[0, 0])


def _background_window(grid: np.ndarray, shape: tuple[int, int], rows: slice, cols: slice) -> np.ndarray:
    """:func:`_background_map` over the window [rows, cols] of a frame of ``shape``,
    (h, w) float64, without drawing the map (the same bilinear weights)."""
    if grid.size == 1:
        return np.full((rows.stop - rows.start, cols.stop - cols.start), float(grid.flat[0]))
    (y0, y1, fy), (x0, x1, fx) = _axis_weights(shape, grid.shape)
    y0, y1, fy, x0, x1, fx = y0[rows], y1[rows], fy[rows, None], x0[cols], x1[cols], fx[cols]
    g = grid.astype(np.float64)
    upper, lower = g[y0], g[y1]
    upper = (1 - fx) * upper[:, x0] + fx * upper[:, x1]
    lower = (1 - fx) * lower[:, x0] + fx * lower[:, x1]
    return (1 - fy) * upper + fy * lower


@functools.lru_cache(maxsize=8)
def _axis_weights(shape: tuple[int, int], grid_shape: tuple[int, int]):
    """Per frame axis, the bilinear interpolation of :func:`_background_map`: for every
    pixel the two grid cells it lies between (edges replicated) and its weight on the
    second."""
    block = _background_block(shape)
    out = []
    for pixels, cells in zip(shape, grid_shape):
        at = (np.arange(pixels) + 0.5) / block - 0.5
        low = np.floor(at)
        out.append((np.clip(low, 0, cells - 1).astype(np.intp), np.clip(low + 1, 0, cells - 1).astype(np.intp),
                    at - low))
    return tuple(out)


#: half-size of the first window in which the spot's component is labelled
_COMPONENT_WINDOW = 24


def _peak_component(over_threshold, shape: tuple[int, int], iy: int, ix: int):
    """The connected component (8-connectivity) of the pixels over threshold holding
    pixel (iy, ix), labelled in a window around it, grown until the component fits.

    over_threshold(rows, cols): (h, w) uint8, 1 where a window's pixels are over threshold.
    Returns ((x0, y0, w, h, area) of the component in frame pixels, its (h, w) bool footprint).
    """
    height, width = shape
    half = _COMPONENT_WINDOW
    while True:
        wy0, wy1 = max(0, iy - half), min(height, iy + half + 1)
        wx0, wx1 = max(0, ix - half), min(width, ix + half + 1)
        _, labels, stats, _ = cv2.connectedComponentsWithStats(over_threshold(slice(wy0, wy1), slice(wx0, wx1)),
                                                               connectivity=8)
        own = labels[iy - wy0, ix - wx0]
        x0, y0, w, h, area = (int(v) for v in stats[own])
        fits = ((x0 > 0 or wx0 == 0) and (y0 > 0 or wy0 == 0) and (x0 + w < wx1 - wx0 or wx1 == width)
                and (y0 + h < wy1 - wy0 or wy1 == height))
        if fits:
            return (x0 + wx0, y0 + wy0, w, h, area), labels[y0:y0 + h, x0:x0 + w] == own
        half *= 2


def _other_fluxes(mask: np.ndarray, image: np.ndarray, level: np.ndarray, cut: float, iy: int, ix: int):
    """Fluxes over threshold (image - level + cut summed) of the components of ``mask``
    ((H, W) uint8, 8-connectivity) other than the one holding pixel (iy, ix), and other
    than single isolated pixels (:data:`ISOLATED_SHARE`: fireflies, hot pixels)."""
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    own = labels[iy, ix]
    on = np.flatnonzero(mask)
    above = image.ravel()[on].astype(np.float64) - level.ravel()[on] + cut
    fluxes = np.bincount(labels.ravel()[on], weights=above, minlength=count)
    skip = [0, own]
    for k in np.flatnonzero(stats[:, cv2.CC_STAT_AREA] == 1):
        y, x = int(stats[k, cv2.CC_STAT_TOP]), int(stats[k, cv2.CC_STAT_LEFT])
        if k != own and _isolated(image, float(level[y, x]) - cut, y, x):
            skip.append(int(k))
    return np.delete(fluxes, skip)


def _isolated(image: np.ndarray, background: float, y: int, x: int) -> bool:
    """Whether pixel (y, x) stands alone: each of its (up to 8) neighbours holds less than
    :data:`ISOLATED_SHARE` of its light above ``background``."""
    light = float(image[y, x]) - background
    if not light > 0:
        return False
    window = image[max(0, y - 1):y + 2, max(0, x - 1):x + 2].astype(np.float64) - background
    window[y - max(0, y - 1), x - max(0, x - 1)] = -np.inf
    return bool(window.max() < ISOLATED_SHARE * light)


def _neighbour_median(image: np.ndarray, y: int, x: int) -> float:
    window = image[max(0, y - 1):y + 2, max(0, x - 1):x + 2].astype(np.float64)
    values = np.delete(window.ravel(), (y - max(0, y - 1)) * window.shape[1] + (x - max(0, x - 1)))
    return float(np.median(values))


def _aperture_centroid(values, gx, gy, cx, cy, radius) -> tuple[float, float]:
    """Centroid in a soft-edged disc of ``radius`` px re-centred on the estimate until it
    settles: symmetric about the spot, so unbiased, and it leaves out most background
    noise of the window (noise in the centroid grows with the aperture's second moment)."""
    for _ in range(_APERTURE_ITERATIONS):
        r = np.hypot(gx - cx, gy - cy)
        weight = np.clip(radius + 0.5 - r, 0.0, 1.0)
        w = weight * values
        total = w.sum()
        if not total > 0:
            break
        nx, ny = float((w * gx).sum() / total), float((w * gy).sum() / total)
        done = abs(nx - cx) + abs(ny - cy) < 1e-6
        cx, cy = nx, ny
        if done:
            break
    return cx, cy


def _background_plane(window: np.ndarray) -> np.ndarray:
    """Least-squares plane a + b x + c y through the window's 2-pixel border ring, one
    pass of 3-MAD rejection; (h, w) float64."""
    index, design, normal, solve = _ring_design(window.shape)
    target = window.ravel()[index]
    coef = solve @ target
    resid = target - design @ coef
    mad = 1.4826 * _median(np.abs(resid))
    out = np.abs(resid) > 3 * mad if mad > 0 else None
    if out is not None and out.any():  # the fit without the rejected ring pixels
        d = design[out]
        coef = np.linalg.solve(normal - d.T @ d, design.T @ target - d.T @ target[out])
    h, w = window.shape
    return coef[0] + coef[1] * (np.arange(w) - (w - 1) / 2)[None, :] + coef[2] * (np.arange(h) - (h - 1) / 2)[:, None]


@functools.lru_cache(maxsize=64)
def _ring_design(shape: tuple[int, int]):
    """For a window of ``shape``: the flat indices of its 2-pixel border ring, the plane's
    design matrix there (1, x, y about the window's centre), its normal matrix and the
    least-squares solution operator (normal^-1 design^T)."""
    h, w = shape
    ring = np.zeros(shape, dtype=bool)
    ring[:2], ring[-2:], ring[:, :2], ring[:, -2:] = True, True, True, True
    yy, xx = np.nonzero(ring)
    design = np.stack([np.ones(yy.size), xx - (w - 1) / 2, yy - (h - 1) / 2], axis=1)
    normal = design.T @ design
    return np.flatnonzero(ring), design, normal, np.linalg.solve(normal, design.T)


#: a pixel's own second moment about its centre (a unit square's), added to the spot's
PIXEL_MOMENT = 1.0 / 12.0


def _shape_flags(values, gx, gy, core, cx, cy, params) -> dict:
    """``elongated`` from the second moments of the spot's light: its component grown by
    one pixel (the threshold alone cuts a spot of 2-3 px on whichever side its noise puts a
    flank pixel under the level: a round 0.6 px spot with 25% noise a pixel read as a line
    of 2-3 px, elongation 15-1300), each pixel taken as its square, not its centre
    (:data:`PIXEL_MOMENT`: two equal pixels are a 1 x 2 px patch, elongation 2, not a line)."""
    grown = cv2.dilate(core.view(np.uint8), np.ones((3, 3), np.uint8)).view(bool)
    w = np.where(grown, values, 0.0)
    total = w.sum()
    dx, dy = gx - cx, gy - cy
    cov = (np.array([[(w * dx * dx).sum(), (w * dx * dy).sum()], [(w * dx * dy).sum(), (w * dy * dy).sum()]]) / total
           + PIXEL_MOMENT * np.eye(2))
    lo, hi = np.linalg.eigvalsh(cov)
    elongation = math.sqrt(hi / lo) if lo > 0 else math.inf
    return {"elongated": round(elongation, 3)} if elongation > params.max_elongation else {}


def _outside(x0, y0, w, h, cx, cy, shape, roi) -> float | None:
    height, width = shape
    if x0 == 0 or y0 == 0 or x0 + w == width or y0 + h == height:
        return 0.0
    if roi is None:
        return None
    rx0, ry0, rx1, ry1 = roi
    d = max(rx0 - cx, cx - rx1, ry0 - cy, cy - ry1)
    return round(float(d), 3) if d > 0 else None


def _gaussian_refine(values, gx, gy, cx, cy, sigma) -> tuple[float, float]:
    """Least-squares elliptical 2D Gaussian + constant on the window; returns its centre."""
    from scipy.optimize import least_squares

    x, y = (np.broadcast_to(g, values.shape).ravel().astype(float) for g in (gx, gy))
    v = values.ravel()

    def residual(p):
        a, mx, my, sx, sy, b = p
        return a * np.exp(-0.5 * (((x - mx) / sx) ** 2 + ((y - my) / sy) ** 2)) + b - v

    start = [v.max(), cx, cy, max(sigma, 0.5), max(sigma, 0.5), 0.0]
    fit = least_squares(residual, start, method="lm")
    mx, my = fit.x[1], fit.x[2]
    if fit.success and abs(mx - cx) < 2 * sigma + 1 and abs(my - cy) < 2 * sigma + 1:
        return float(mx), float(my)
    return cx, cy


# ---------------------------------------------------------------------- the stage
