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

import csv
import functools
import logging
import math
import os
import threading
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

log = logging.getLogger(__name__)

SPOTS_FILE = "spots.csv"
SPOTS_HEADER = ["beam", "x", "y", "flux", "peak", "area", "flags"]
FLAGS = ("none", "multiple", "large", "elongated", "saturated", "outside")


class SpotsError(ValueError):
    """A spots table that cannot be read; the message names the file and line."""


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


@dataclass
class Spot:
    """One beam's spot: centroid (x, y) px, flux (background-subtracted sum), peak (above
    background), area (pixels over threshold) and flags {name: figure}."""

    x: float
    y: float
    flux: float
    peak: float
    area: int
    flags: dict = field(default_factory=dict)


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
    ((H, W) uint8, 8-connectivity) other than the one holding pixel (iy, ix)."""
    count, labels, _, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    own = labels[iy, ix]
    on = np.flatnonzero(mask)
    above = image.ravel()[on].astype(np.float64) - level.ravel()[on] + cut
    fluxes = np.bincount(labels.ravel()[on], weights=above, minlength=count)
    return np.delete(fluxes, [0, own])


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


def _shape_flags(values, gx, gy, core, cx, cy, params) -> dict:
    w = np.where(core, values, 0.0)
    total = w.sum()
    dx, dy = gx - cx, gy - cy
    cov = np.array([[(w * dx * dx).sum(), (w * dx * dy).sum()], [(w * dx * dy).sum(), (w * dy * dy).sum()]]) / total
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


def flag_large(spots: list[Spot], factor: float) -> None:
    """Flag spots whose area exceeds ``factor`` x the median area of the clean spots (in place)."""
    areas = [s.area for s in spots if not s.flags]
    if not areas:
        return
    median = float(np.median(areas))
    for s in spots:
        if "none" not in s.flags and s.area > factor * median and "large" not in s.flags:
            s.flags["large"] = round(s.area / median, 3)


def format_flags(flags: dict) -> str:
    return ";".join(f"{k}={v:g}" for k, v in flags.items())


def parse_flags(text: str) -> dict:
    out = {}
    for item in filter(None, text.split(";")):
        name, _, value = item.partition("=")
        out[name] = float(value) if value else 0.0
    return out


def write_spots(path: str | os.PathLike, beams: list[int], spots: list[Spot]) -> None:
    """Write ``spots.csv`` (header ``beam,x,y,flux,peak,area,flags``)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(SPOTS_HEADER)
        for b, s in zip(beams, spots):
            w.writerow([b, repr(s.x), repr(s.y), repr(s.flux), repr(s.peak), s.area, format_flags(s.flags)])


def read_spots(path: str | os.PathLike) -> tuple[list[int], list[Spot]]:
    """Read ``spots.csv``; returns plan beams (strictly increasing) and their spots."""
    path = Path(path)
    try:
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            if reader.fieldnames != SPOTS_HEADER:
                raise SpotsError(f"{path}: header {reader.fieldnames} is not {','.join(SPOTS_HEADER)}")
            rows = list(reader)
    except OSError as exc:
        raise SpotsError(f"{path}: cannot read ({exc.strerror})") from None
    beams, spots = [], []
    for i, row in enumerate(rows):
        try:
            beam = int(row["beam"])
            spot = Spot(float(row["x"]), float(row["y"]), float(row["flux"]), float(row["peak"]),
                        int(row["area"]), parse_flags(row["flags"] or ""))
        except (TypeError, ValueError):
            raise SpotsError(f"{path}: line {i + 2} is not beam,x,y,flux,peak,area,flags: {row}") from None
        if beams and beam <= beams[-1]:
            raise SpotsError(f"{path}: line {i + 2}: beam {beam} after beam {beams[-1]} (beams must increase)")
        beams.append(beam)
        spots.append(spot)
    if not beams:
        raise SpotsError(f"{path}: no spots")
    return beams, spots


def spot_dict(spot: Spot) -> dict:
    return asdict(spot)


# ---------------------------------------------------------------------- the stage

SUM_FILE = "sum.exr"
OVERLAY_FILE = "overlay.png"


def _centroid_chunk(beams, sources, reader, params, dark, default_mapping, scratch=None):
    """Worker: spots of a chunk of frames (full-frame pixels), the chunk's pixelwise sum
    (H, W) float32 on the frame grid, the frame grid's pixel mapping, and the beams whose
    frames were kept in ``scratch``.

    sources: what ``reader(source, dark)`` turns into ``(frame, mapping or None,
    saturation)`` (EXR paths, or beam directories of a capture; ``default_mapping``
    where the reader finds none); workers get paths, never arrays. ``scratch``: a
    :class:`ilt.frames.FrameScratch` where each frame is also written for a following
    build-isf, so that a combined run decodes every EXR once.
    """
    spots, total, mapping, kept = [], None, None, []
    fd = scratch.open(write=True) if scratch is not None else None
    try:
        for beam, source in zip(beams, sources):
            frame, own, saturation = reader(source, dark)
            own = own or default_mapping
            if total is None:
                # float32 within a chunk (16 frames: a few ulp), float64 across chunks
                total, mapping = np.zeros(frame.shape, np.float32), own
            elif frame.shape != total.shape or own != mapping:
                from ilt.frames import FrameError

                raise FrameError(f"{source}: beam {beam}: frame of {frame.shape[1]} x {frame.shape[0]} pixels "
                                 f"({own.as_dict()}) differs from beam {beams[0]}'s")
            grid_params = _grid_parameters(params, own, saturation)
            spots.append(_to_full_frame(find_spot(frame, grid_params), own))
            total += frame
            if fd is not None:
                if _keep_frame(scratch, fd, beam, frame):
                    kept.append(beam)
                else:  # the disk is full: the rest of the chunk is decoded again by build-isf
                    os.close(fd)
                    fd = None
    finally:
        if fd is not None:
            os.close(fd)
    return spots, total, mapping, kept  # float32: half the bytes back to the caller


def _keep_frame(scratch, fd: int, beam: int, frame: np.ndarray) -> bool:
    """Write a decoded frame for build-isf; False (with a warning) when it cannot be
    written: it is then left out of the scratch's record and build-isf decodes that
    beam's EXR again."""
    try:
        scratch.keep(fd, beam, frame)
        return True
    except OSError as exc:
        log.warning("%s: cannot keep beam %d's decoded frame (%s); build-isf will decode it again",
                    scratch.path, beam, exc.strerror or exc)
        return False


def read_exr_frame(path, dark):
    """Reader for HDR directories: (frame - dark, its pixel mapping or None, None)."""
    from ilt.frames import read_frame_with_mapping

    frame, mapping = read_frame_with_mapping(path)
    if dark is not None:
        frame = frame - _cached_dark(dark, frame.shape)
    return frame, mapping, None


def read_shortest_exposure(beam_dir, dark=None):
    """Reader for capture directories: the beam's shortest exposure (paper Sec. 4), its
    half-resolution green image (:func:`ilt.hdr.raw.read_green`) less the beam's dark
    frame when it has one, the green grid's mapping to full-frame pixels and the level
    (DN above black) at which a sample counts as saturated. ``dark`` is unused (the
    capture's own dark frames are)."""
    from ilt.frames import PixelMapping
    from ilt.hdr.bracket import read_beam
    from ilt.hdr.exposure import parse_positive
    from ilt.hdr.raw import read_green

    bracket = read_beam(beam_dir)

    def exposure(record):
        if record.exposure_time is not None and record.f_number is not None:
            where = bracket.path(record)
            return parse_positive(record.exposure_time, "exposure time", where) / \
                parse_positive(record.f_number, "f-number", where) ** 2
        return read_green(bracket.path(record), dtype=np.float32)[1].exposure.relative_exposure()

    shortest = min(bracket.frames, key=exposure)
    green, info = read_green(bracket.path(shortest), shortest.exposure_time, shortest.f_number, dtype=np.float32)
    if bracket.dark is not None:
        dark_green, _ = read_green(bracket.path(bracket.dark), bracket.dark.exposure_time, bracket.dark.f_number,
                                   dtype=np.float32)
        if dark_green.shape != green.shape:
            raise SpotsError(f"{bracket.path(bracket.dark)}: dark frame size differs from {shortest.file}")
        green -= dark_green
    return green, PixelMapping(tuple(info.origin), float(info.scale)), float(info.saturation)


_DARK_CACHE: dict = {}


def _cached_dark(path, shape) -> np.ndarray:
    """The dark frame, read once per worker process."""
    from ilt.frames import read_frame

    key = (str(path), tuple(shape))
    if key not in _DARK_CACHE:
        _DARK_CACHE.clear()
        _DARK_CACHE[key] = read_frame(path, shape)
    return _DARK_CACHE[key]


def _grid_parameters(params: SpotParameters, mapping, saturation) -> SpotParameters:
    """Parameters in the frame grid's pixels: the ROI mapped from full-frame pixels, and
    the sensor's saturation level when the reader knows it and the user gave none."""
    from dataclasses import replace

    roi = params.roi
    if roi is not None:
        (x0, y0), (x1, y1) = mapping.to_grid(np.array(roi[:2])), mapping.to_grid(np.array(roi[2:]))
        roi = (float(x0), float(y0), float(x1), float(y1))
    sat = params.saturation if params.saturation is not None else saturation
    return replace(params, roi=roi, saturation=sat) if (roi, sat) != (params.roi, params.saturation) else params


def _to_full_frame(spot: Spot, mapping) -> Spot:
    """A spot found on a frame grid, its centroid (and ``outside`` distance) in full-frame pixels."""
    x, y = mapping.to_full(np.array([spot.x, spot.y]))
    flags = dict(spot.flags)
    if "outside" in flags:
        flags["outside"] = round(flags["outside"] * mapping.scale, 3)
    return Spot(float(x), float(y), spot.flux, spot.peak, spot.area, flags)


def is_capture_directory(path: Path) -> bool:
    """A capture directory (raw brackets) rather than an HDR directory of EXR frames."""
    from ilt.manifest import MANIFEST

    if (path / MANIFEST).exists():
        import json

        try:
            if json.loads((path / MANIFEST).read_text()).get("stage") == "capture":
                return True
        except (OSError, ValueError):
            pass
    return not any(p.suffix.lower() == ".exr" for p in path.iterdir()) and any(
        p.suffix.lower() in (".dng", ".cr2", ".nef", ".arw") for p in path.rglob("*"))


def run_centroids(hdr_dir: str | os.PathLike, out: str | os.PathLike, params: SpotParameters = SpotParameters(),
                  dark: str | os.PathLike | None = None, executor=None, workers: int | None = None,
                  chunk: int = 16, progress=None, force: bool = False, frame_cache=None) -> dict:
    """The centroids stage: one spot per beam of ``hdr_dir`` into ``out`` (atomically).

    ``hdr_dir`` is an HDR directory (one EXR per beam), or a capture directory, whose
    beams are read at their shortest exposure with their dark frames subtracted (the
    paper's choice: the spot is least saturated there). ``dark``: a dark frame (EXR on
    the frame grid) to subtract from HDR frames.

    Writes ``spots.csv`` (centroids in full-frame sensor pixels, DESIGN.md sec. 3; area
    and flux on the frame grid), ``sum.exr`` (the sum of all beam frames, (H, W) float32
    on the frame grid, with its pixel mapping: which pixels the scan lights),
    ``overlay.png`` (all spots on the scene, paper Fig. 4) and ``manifest.json`` (plan
    layout, frame shape, pixel mapping, parameters, flag counts). Frames are read one at
    a time per worker through ``executor`` (default: a process pool of ``workers``);
    ``frame_cache`` (HDR directories only): a scratch directory in which every decoded
    frame is also kept for a following build-isf (:class:`ilt.frames.FrameScratch`).
    Returns the manifest's summary fields.
    """
    from ilt.frames import (
        FrameScratch,
        HDRDirectory,
        beam_executor,
        chunks,
        open_hdr_directory,
        read_frame,
        run_chunks,
    )
    from ilt.imageio import write_exr
    from ilt.manifest import staged_directory, write_manifest

    path = hdr_dir.path if isinstance(hdr_dir, HDRDirectory) else Path(hdr_dir)
    if not isinstance(hdr_dir, HDRDirectory) and path.is_dir() and is_capture_directory(path):
        if dark is not None:
            raise SpotsError(f"{path}: --dark applies to HDR directories; a capture's own dark frames are used")
        names, sources, layout, inputs = _capture_beams(path)
        reader, default_mapping, scratch = read_shortest_exposure, None, None
    else:
        hdr = open_hdr_directory(hdr_dir)
        if dark:
            read_frame(dark, hdr.frame_shape)
        names, sources, layout, inputs = [f.name for f in hdr.files], list(hdr.files), hdr.layout, \
            _listing_fingerprint(hdr)
        reader, default_mapping = read_exr_frame, hdr.mapping
        scratch = FrameScratch(Path(frame_cache), hdr.frame_shape) if frame_cache is not None else None
    beams = list(range(len(sources)))
    tasks = [(c, [sources[b] for b in c], reader, params, str(dark) if dark else None, default_mapping,
              scratch) for c in chunks(beams, chunk)]
    spots: list[Spot] = []
    total, mapping, kept = None, None, []
    with beam_executor(executor, workers) as ex:
        for c, (chunk_spots, chunk_total, chunk_mapping, chunk_kept) in zip(
                (t[0] for t in tasks), run_chunks(_centroid_chunk, tasks, ex, progress=progress)):
            if total is None:
                total, mapping = chunk_total.astype(np.float64), chunk_mapping
            elif chunk_total.shape != total.shape or chunk_mapping != mapping:
                raise SpotsError(f"{sources[c[0]]}: beam {c[0]}: frame of {chunk_total.shape[1]} x "
                                 f"{chunk_total.shape[0]} pixels differs from beam 0's")
            else:
                total += chunk_total
            spots.extend(chunk_spots)
            kept.extend(chunk_kept)
    if scratch is not None:
        scratch.record(kept)
    flag_large(spots, params.large_factor)
    counts = {name: sum(name in s.flags for s in spots) for name in FLAGS}
    for b, s in zip(beams, spots):
        if s.flags:
            log.warning("beam %d (%s): %s", b, names[b], format_flags(s.flags))
    fields = {"m": len(beams), "layout": list(layout), "frame_shape": list(total.shape),
              "pixel_mapping": mapping.as_dict(), "flag_counts": counts, "clean": sum(not s.flags for s in spots)}
    with staged_directory(out, force=force) as tmp:
        write_spots(tmp / SPOTS_FILE, beams, spots)
        write_exr(tmp / SUM_FILE, total, attributes={"ilt:quantity": "sum of beam frames", **mapping.attributes()})
        draw_overlay(tmp / OVERLAY_FILE, total, spots, mapping)
        parameters = {k: v for k, v in asdict(params).items()}
        parameters["dark"] = str(dark) if dark else None
        write_manifest(tmp, "centroids", parameters, inputs=inputs, extra=fields)
    return {**fields, "output": str(out)}


def _capture_beams(path: Path):
    """Beam names, beam directories, plan layout and manifest inputs of a capture directory."""
    import json

    from ilt.hdr.bracket import list_beams
    from ilt.manifest import MANIFEST, fingerprint_file

    dirs = list_beams(path)
    layout = (1, len(dirs))
    inputs = {}
    if (path / MANIFEST).exists():
        plan = json.loads((path / MANIFEST).read_text())
        if plan.get("layout"):
            layout = tuple(int(n) for n in plan["layout"])
            if layout[0] * layout[1] != len(dirs):
                raise SpotsError(f"{path / MANIFEST}: layout {list(layout)} for {len(dirs)} beams")
        inputs[str(path / MANIFEST)] = fingerprint_file(path / MANIFEST)
    return [d.name for d in dirs], dirs, layout, inputs


def _listing_fingerprint(hdr) -> dict:
    """Inputs for the manifest: the HDR directory's manifest fingerprint when it has one,
    and a fingerprint of the frame listing (names, sizes, modification times), so
    that recording the inputs does not read every frame a second time."""
    import hashlib

    from ilt.manifest import MANIFEST, fingerprint_file

    h = hashlib.sha256()
    for f in hdr.files:
        st = f.stat()
        h.update(f"{f.name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    out = {str(hdr.path): "listing-sha256:" + h.hexdigest()}
    if (hdr.path / MANIFEST).exists():
        out[str(hdr.path / MANIFEST)] = fingerprint_file(hdr.path / MANIFEST)
    return out


def draw_overlay(path: Path, background: np.ndarray, spots: list[Spot], mapping=None) -> Path:
    """PNG of the sum of the scan's frames (log scale, 5 decades) with every spot marked
    (paper Fig. 4, top left): clean spots as green circles, flagged ones as red crosses,
    a title bar with the counts. ``mapping``: of the frame grid (spots are in full-frame
    pixels). Drawn with OpenCV at an integer zoom (the long side at least 640 pixels:
    encoding the PNG is most of the time, 80 ms at 1280 x 960), sub-pixel positions
    kept: a matplotlib figure took longer than a thousand spots."""
    from ilt.imageio import write_png
    from ilt.preview import log_scale

    height, width = background.shape
    zoom = max(1, -(-640 // max(height, width)))
    grey = (255 * log_scale(np.where(np.isfinite(background), background, 0.0), 5.0)).astype(np.uint8)
    grey = cv2.resize(grey, (width * zoom, height * zoom), interpolation=cv2.INTER_NEAREST)
    bar = 28
    canvas = np.zeros((height * zoom + bar, width * zoom, 3), np.uint8)
    canvas[bar:] = grey[..., None]
    xy = np.array([[s.x, s.y] for s in spots], dtype=np.float64).reshape(-1, 2)
    if mapping is not None and len(xy):
        xy = mapping.to_grid(xy)
    bad = np.array([bool(s.flags) for s in spots], dtype=bool)
    finite = np.isfinite(xy).all(axis=1)
    shift = 4  # sub-pixel bits of cv2's drawing functions
    centres = np.round(((xy + 0.5) * zoom - 0.5 + [0, bar]) * (1 << shift)).astype(np.int64)
    radius = max(3, zoom * 2)
    for (cx, cy), flagged, ok in zip(centres, bad, finite):
        if not ok:
            continue
        if flagged:
            x, y, r = int(cx), int(cy), (radius + 1) << shift
            cv2.line(canvas, (x - r, y - r), (x + r, y + r), (0, 0, 255), 1, cv2.LINE_AA, shift)
            cv2.line(canvas, (x - r, y + r), (x + r, y - r), (0, 0, 255), 1, cv2.LINE_AA, shift)
        else:
            cv2.circle(canvas, (int(cx), int(cy)), radius << shift, (0, 255, 0), 1, cv2.LINE_AA, shift)
    clean = int((~bad & finite).sum())
    cv2.putText(canvas, f"{clean} clean spots, {int(bad.sum())} flagged", (8, bar - 9),
                cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    return write_png(path, canvas)
