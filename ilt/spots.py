"""Laser spot centroids with quality flags (paper Sec. 4: "the centroid of the laser
spot in the shortest exposure gives pixel i for beam i").

Per frame (:func:`find_spot`): subtract a background (a dark frame when one was
captured, else the frame's median), threshold relative to the peak, label connected
components (OpenCV), keep the component holding the peak, fit a plane to the ring
around it as the local background level, and take the intensity-weighted centroid of
the background-subtracted values in a window of about +-4 spot sigmas (sub-pixel).
Optionally refine with a least-squares 2D Gaussian. Pixel convention of DESIGN.md:
x right, y down, the centre of the top-left pixel at (0, 0).

QA flags (name=figure): ``none`` (peak over noise below ``min_snr``), ``multiple``
(flux of the second spot / the first), ``large`` (area / median area of the scan, or
the area when over ``max_area``), ``elongated`` (ratio of the principal axes),
``saturated`` (pixels on the flat top), ``outside`` (spot on the frame border or
outside the region of interest; figure: distance to it in pixels).
"""

from __future__ import annotations

import csv
import logging
import math
import os
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
    Returns a :class:`Spot` (x, y NaN when flagged ``none``).
    """
    img = np.asarray(image)
    if dark is not None:
        img = img - dark
    height, width = img.shape
    # robust statistics from every 4th row and column (the spot is a small part of the
    # frame either way); the window around the spot is then handled in float64
    rows = img[::4, ::4].astype(np.float64)
    level = float(np.median(rows))
    # pixel-to-pixel differences: a smooth background (interreflections) is not noise
    step = np.diff(rows, axis=1)
    noise = 1.4826 * float(np.median(np.abs(step - np.median(step)))) / math.sqrt(2)
    iy, ix = np.unravel_index(int(np.argmax(img)), img.shape)
    top = float(img[iy, ix])
    amplitude = top - level
    if not amplitude > max(params.min_snr * noise, 1e-30 * max(1.0, abs(top))):
        snr = amplitude / noise if noise > 0 else 0.0
        return Spot(math.nan, math.nan, 0.0, max(amplitude, 0.0), 0, {"none": round(snr, 3)})
    mask = (img > level + params.threshold * amplitude).astype(np.uint8)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    own = labels[iy, ix]
    on = np.flatnonzero(mask)
    fluxes = np.bincount(labels.ravel()[on], weights=img.ravel()[on] - level, minlength=count)
    fluxes[0] = 0.0
    flags: dict = {}
    others = np.delete(fluxes, [0, own])
    if others.size and others.max() >= params.max_second * fluxes[own]:
        flags["multiple"] = round(float(others.max() / fluxes[own]), 4)
    x0, y0, w, h, area = (int(v) for v in stats[own])
    sigma = math.sqrt(area / math.pi) / math.sqrt(2 * math.log(1 / params.threshold))
    pad = int(math.ceil(2.5 * sigma)) + 2
    ys, xs = slice(max(0, y0 - pad), min(height, y0 + h + pad)), slice(max(0, x0 - pad), min(width, x0 + w + pad))
    window = img[ys, xs].astype(np.float64)
    gy, gx = np.mgrid[ys, xs]
    ring = np.zeros(window.shape, dtype=bool)
    ring[:2], ring[-2:], ring[:, :2], ring[:, -2:] = True, True, True, True
    plane = _background_plane(window, gx, gy, ring)
    values = window - plane
    flux = float(values.sum())
    if not flux > 0:
        return Spot(math.nan, math.nan, 0.0, amplitude, area, {"none": 0.0})
    cx, cy = _aperture_centroid(values, gx, gy, float((values * gx).sum() / flux),
                                float((values * gy).sum() / flux), _APERTURE * sigma)
    if params.refine:
        cx, cy = _gaussian_refine(values, gx, gy, cx, cy, sigma)
    core = labels[ys, xs] == own
    flags.update(_shape_flags(values, gx, gy, core, cx, cy, params))
    plateau = int((window[core] >= top - _PLATEAU_REL * abs(top)).sum())
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


def _background_plane(window, gx, gy, ring) -> np.ndarray:
    """Least-squares plane a + b x + c y through the ring pixels, one pass of 3-MAD rejection."""
    design = np.stack([np.ones(ring.sum()), gx[ring] - gx.mean(), gy[ring] - gy.mean()], axis=1)
    target = window[ring]
    keep = np.ones(len(target), dtype=bool)
    for _ in range(2):
        coef, *_ = np.linalg.lstsq(design[keep], target[keep], rcond=None)
        resid = target - design @ coef
        mad = 1.4826 * np.median(np.abs(resid[keep]))
        keep = np.abs(resid) <= 3 * mad if mad > 0 else keep
    return coef[0] + coef[1] * (gx - gx.mean()) + coef[2] * (gy - gy.mean())


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

    x, y, v = gx.ravel().astype(float), gy.ravel().astype(float), values.ravel()

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


def _centroid_chunk(beams, files, shape, params, dark):
    """Worker: spots of a chunk of frames, with their pixelwise sum and max (H, W) float64."""
    from ilt.frames import read_frame

    spots, total, peak = [], np.zeros(shape), np.full(shape, -np.inf)
    for path in files:
        frame = read_frame(path, shape)
        spots.append(find_spot(frame, params, dark))
        total += frame
        np.maximum(peak, frame, out=peak)
    return spots, total, peak


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
                  chunk: int = 16, progress=None, force: bool = False) -> dict:
    """The centroids stage: one spot per beam frame of ``hdr_dir`` into ``out`` (atomically).

    Writes ``spots.csv``, ``sum.exr`` (the sum of all beam frames, (H, W) float32: which
    pixels the scan lights), ``overlay.png`` (all spots on the scene, paper Fig. 4) and
    ``manifest.json`` (plan layout, frame shape, parameters, flag counts). Frames are read
    one at a time per worker through ``executor`` (default: a process pool of ``workers``).
    Returns the manifest's summary fields.
    """
    from ilt.frames import beam_executor, chunks, open_hdr_directory, read_frame, run_chunks
    from ilt.imageio import write_exr
    from ilt.manifest import staged_directory, write_manifest

    path = Path(hdr_dir)
    if path.is_dir() and is_capture_directory(path):
        import importlib.util

        if importlib.util.find_spec("ilt.hdr.raw") is None:
            raise SpotsError(f"{path}: capture directories need ilt.hdr (issue 3); merge to an HDR directory first")
        raise SpotsError(f"{path}: reading capture directories is not wired in yet; run 'ilt merge' first")
    hdr = open_hdr_directory(path)
    dark_frame = read_frame(dark, hdr.frame_shape) if dark else None
    beams = list(range(hdr.m))
    tasks = [(c, [hdr.files[b] for b in c], hdr.frame_shape, params, dark_frame) for c in chunks(beams, chunk)]
    spots: list[Spot] = []
    total, peak = np.zeros(hdr.frame_shape), np.full(hdr.frame_shape, -np.inf)
    with beam_executor(executor, workers) as ex:
        for chunk_spots, chunk_total, chunk_peak in run_chunks(_centroid_chunk, tasks, ex, progress=progress):
            spots.extend(chunk_spots)
            total += chunk_total
            np.maximum(peak, chunk_peak, out=peak)
    flag_large(spots, params.large_factor)
    counts = {name: sum(name in s.flags for s in spots) for name in FLAGS}
    for b, s in zip(beams, spots):
        if s.flags:
            log.warning("beam %d (%s): %s", b, hdr.files[b].name, format_flags(s.flags))
    fields = {"m": hdr.m, "layout": list(hdr.layout), "frame_shape": list(hdr.frame_shape),
              "flag_counts": counts, "clean": sum(not s.flags for s in spots)}
    with staged_directory(out, force=force) as tmp:
        write_spots(tmp / SPOTS_FILE, beams, spots)
        write_exr(tmp / SUM_FILE, total, attributes={"ilt:quantity": "sum of beam frames"})
        draw_overlay(tmp / OVERLAY_FILE, peak, spots)
        parameters = {k: v for k, v in asdict(params).items()}
        parameters["dark"] = str(dark) if dark else None
        write_manifest(tmp, "centroids", parameters, inputs=_listing_fingerprint(hdr), extra=fields)
    return {**fields, "output": str(out)}


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


def draw_overlay(path: Path, background: np.ndarray, spots: list[Spot]) -> Path:
    """PNG of the scan's brightest values (log scale) with every spot marked (paper Fig. 4,
    top left): clean spots as green circles, flagged ones as red crosses."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from ilt.imageio import atomic_output
    from ilt.preview import log_scale

    height, width = background.shape
    scale = min(12.0 / width, 9.0 / height, 0.05)
    fig = Figure(figsize=(max(width * scale, 3), max(height * scale, 1.5) + 0.4), dpi=100, layout="constrained")
    ax = fig.add_subplot()
    ax.imshow(log_scale(np.where(np.isfinite(background), background, 0.0), 5.0), cmap="gray",
              interpolation="nearest")
    xy = np.array([[s.x, s.y] for s in spots])
    bad = np.array([bool(s.flags) for s in spots])
    ok = ~bad & np.isfinite(xy[:, 0])
    ax.scatter(xy[ok, 0], xy[ok, 1], s=30, facecolors="none", edgecolors="lime", linewidths=0.8)
    shown = bad & np.isfinite(xy[:, 0])
    ax.scatter(xy[shown, 0], xy[shown, 1], s=40, marker="x", c="red", linewidths=1.0)
    ax.set_title(f"{ok.sum()} clean spots, {bad.sum()} flagged")
    ax.set_axis_off()
    FigureCanvasAgg(fig)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png")
    return path
