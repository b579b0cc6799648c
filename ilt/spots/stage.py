"""The centroids stage (``ilt centroids``): the spot of every beam of a merged or raw
capture, in chunks over the pool, with the spots table, the sum of all frames
(``sum.exr``), per pixel the largest local mean over the frames (``peak.exr``: what one
beam lights; both feed build-isf's lit test), the sum with each frame's own spot taken out
(``sum-indirect.exr``: the scan's indirect light, for the lit test's silhouettes) and an
overlay of the spots on it (``overlay.png``).
"""

from __future__ import annotations

import logging
import os
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np

from ilt.spots.find import SpotParameters, find_spot
from ilt.spots.table import FLAGS, SPOTS_FILE, Spot, SpotsError, flag_large, format_flags, write_spots

log = logging.getLogger(__name__)


SUM_FILE = "sum.exr"
#: per pixel, the largest over the beam frames of its PEAK_SMOOTH x PEAK_SMOOTH mean
PEAK_FILE = "peak.exr"
PEAK_SMOOTH = 5
#: the sum of the beam frames, each without the disc of its own spot (SPOT_SIGMAS x the
#: spot's sigma): the scan's indirect light, for build-isf's silhouette test
INDIRECT_SUM_FILE = "sum-indirect.exr"
SPOT_SIGMAS = 3.0

OVERLAY_FILE = "overlay.png"


def inside_mean(image: np.ndarray, size: int) -> np.ndarray:
    """(H, W) the mean of the ``size`` x ``size`` window about each pixel, the window moved
    inside the image whole where it would cross the edge (an edge pixel takes the mean of
    the window next to it). A padded window counts the edge pixels many times and their
    noise with it: with ``mode="nearest"`` a corner's 5 x 5 mean held the noise of 5 pixels,
    not 25, and the largest of a scan's frames' means (``peak.exr``) lit specks of pure
    noise at the frame's corners and edges in build-isf's lit test. An image smaller than
    the window: padded as before."""
    from scipy.ndimage import uniform_filter

    height, width = image.shape
    if height < size or width < size:
        return uniform_filter(image, size=size, mode="nearest")
    half = size // 2
    mean = uniform_filter(image, size=size, mode="constant")      # right where the window is inside
    if half:                                                      # the edge bands take the nearest inside one
        mean[:half] = mean[half]
        mean[height - half:] = mean[height - half - 1]
        mean[:, :half] = mean[:, half:half + 1]
        mean[:, width - half:] = mean[:, width - half - 1:width - half]
    return mean


def _centroid_chunk(beams, sources, reader, params, dark, default_mapping, scratch=None):
    """Worker: spots of a chunk of frames (full-frame pixels), the chunk's pixelwise sum
    (H, W) float32 on the frame grid and its pixelwise largest local mean (``peak.exr``),
    the frame grid's pixel mapping, and the beams whose frames were kept in ``scratch``.

    sources: what ``reader(source, dark)`` turns into ``(frame, mapping or None,
    saturation)`` (EXR paths, or beam directories of a capture; ``default_mapping``
    where the reader finds none); workers get paths, never arrays. ``scratch``: a
    :class:`ilt.io.frames.FrameScratch` where each frame is also written for a following
    build-isf, so that a combined run decodes every EXR once.
    """
    spots, total, peak, indirect, mapping, kept = [], None, None, None, None, []
    fd = scratch.open(write=True) if scratch is not None else None
    try:
        for beam, source in zip(beams, sources):
            frame, own, saturation = reader(source, dark)
            own = own or default_mapping
            if total is None:
                # float32 within a chunk (16 frames: a few ulp), float64 across chunks
                total, mapping = np.zeros(frame.shape, np.float32), own
                peak = np.full(frame.shape, -np.inf, np.float32)
                indirect = np.zeros(frame.shape, np.float32)
            elif frame.shape != total.shape or own != mapping:
                from ilt.io.frames import FrameError

                raise FrameError(f"{source}: beam {beam}: frame of {frame.shape[1]} x {frame.shape[0]} pixels "
                                 f"({own.as_dict()}) differs from beam {beams[0]}'s")
            grid_params = _grid_parameters(params, own, saturation)
            spot = find_spot(frame, grid_params)
            spots.append(_to_full_frame(spot, own))
            total += frame
            indirect += frame
            _take_spot(indirect, frame, spot, grid_params.threshold)
            np.maximum(peak, inside_mean(frame.astype(np.float32, copy=False), PEAK_SMOOTH), out=peak)
            if fd is not None:
                if _keep_frame(scratch, fd, beam, frame):
                    kept.append(beam)
                else:  # the disk is full: the rest of the chunk is decoded again by build-isf
                    os.close(fd)
                    fd = None
    finally:
        if fd is not None:
            os.close(fd)
    return spots, total, peak, indirect, mapping, kept  # float32: half the bytes back to the caller


def _take_spot(indirect: np.ndarray, frame: np.ndarray, spot: Spot, threshold: float) -> None:
    """Take ``frame``'s pixels within :data:`SPOT_SIGMAS` sigmas of its ``spot`` (frame grid;
    sigma from the spot's area over its threshold, as :func:`ilt.spots.find.find_spot`
    has it, and at least 0.5 px) back out of ``indirect``: what is left of the frame is its
    indirect light. No spot (NaN): nothing taken."""
    if not (np.isfinite(spot.x) and np.isfinite(spot.y)) or spot.area <= 0:
        return
    sigma = max(0.5, float(np.sqrt(spot.area / np.pi) / np.sqrt(2 * np.log(1 / threshold))))
    radius = SPOT_SIGMAS * sigma
    height, width = frame.shape[:2]
    x0, x1 = max(0, int(np.floor(spot.x - radius))), min(width, int(np.ceil(spot.x + radius)) + 1)
    y0, y1 = max(0, int(np.floor(spot.y - radius))), min(height, int(np.ceil(spot.y + radius)) + 1)
    if x0 >= x1 or y0 >= y1:
        return
    yy, xx = np.mgrid[y0:y1, x0:x1]
    disc = np.hypot(xx - spot.x, yy - spot.y) <= radius
    indirect[y0:y1, x0:x1][disc] -= frame[y0:y1, x0:x1][disc]


def _keep_frame(scratch, fd: int, beam: int, frame: np.ndarray) -> bool:
    """Write a decoded frame for build-isf; False (with a warning) when it cannot be
    written: it is then left out of the scratch's record and build-isf decodes that
    beam's EXR again."""
    try:
        scratch.keep(fd, beam, frame)
        return True
    except OSError as exc:
        log.info("%s: cannot keep beam %d's decoded frame (%s); build-isf will decode it again",
                    scratch.path, beam, exc.strerror or exc)
        return False


def read_exr_frame(path, dark):
    """Reader for HDR directories: (frame - dark, its pixel mapping or None, None)."""
    from ilt.io.frames import read_frame_with_mapping

    frame, mapping = read_frame_with_mapping(path)
    if dark is not None:
        frame = frame - _cached_dark(dark, frame.shape)
    return frame, mapping, None


def read_shortest_exposure(beam_dir, dark=None):
    """Reader for capture directories: the beam's shortest exposure (paper Sec. 4), its
    half-resolution green image (:func:`ilt.io.raw.read_green`) less the beam's dark
    frame when it has one, the green grid's mapping to full-frame pixels and the level
    (DN above black) at which a sample counts as saturated. ``dark`` is unused (the
    capture's own dark frames are)."""
    from ilt.hdr.bracket import read_beam
    from ilt.io.exposure import parse_positive
    from ilt.io.frames import PixelMapping
    from ilt.io.raw import read_green

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


def _cached_dark(path, shape) -> np.ndarray:
    """The dark frame, read once per worker process."""
    from ilt.io.frames import read_frame

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
    from ilt.io.manifest import MANIFEST

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
    frame is also kept for a following build-isf (:class:`ilt.io.frames.FrameScratch`).
    Returns the manifest's summary fields.
    """
    from ilt.io.exr import write_exr
    from ilt.io.frames import FrameScratch, HDRDirectory, open_hdr_directory, read_frame
    from ilt.io.manifest import write_manifest
    from ilt.io.staged import staged_directory
    from ilt.parallel.chunks import beam_executor, chunks, run_chunks

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
    total, peak, indirect, mapping, kept = None, None, None, None, []
    with beam_executor(executor, workers) as ex:
        for c, (chunk_spots, chunk_total, chunk_peak, chunk_indirect, chunk_mapping, chunk_kept) in zip(
                (t[0] for t in tasks), run_chunks(_centroid_chunk, tasks, ex, progress=progress)):
            if total is None:
                total, peak, mapping = chunk_total.astype(np.float64), chunk_peak, chunk_mapping
                indirect = chunk_indirect.astype(np.float64)
            elif chunk_total.shape != total.shape or chunk_mapping != mapping:
                raise SpotsError(f"{sources[c[0]]}: beam {c[0]}: frame of {chunk_total.shape[1]} x "
                                 f"{chunk_total.shape[0]} pixels differs from beam 0's")
            else:
                total += chunk_total
                indirect += chunk_indirect
                np.maximum(peak, chunk_peak, out=peak)
            spots.extend(chunk_spots)
            kept.extend(chunk_kept)
    if scratch is not None:
        scratch.record(kept)
    flag_large(spots, params.large_factor)
    counts = {name: sum(name in s.flags for s in spots) for name in FLAGS}
    report_flags(beams, spots, names, out)
    fields = {"m": len(beams), "layout": list(layout), "frame_shape": list(total.shape),
              "pixel_mapping": mapping.as_dict(), "flag_counts": counts, "clean": sum(not s.flags for s in spots)}
    with staged_directory(out, force=force) as tmp:
        write_spots(tmp / SPOTS_FILE, beams, spots)
        write_exr(tmp / SUM_FILE, total, attributes={"ilt:quantity": "sum of beam frames", **mapping.attributes()})
        write_exr(tmp / PEAK_FILE, peak, attributes={
            "ilt:quantity": f"largest over the beam frames of the {PEAK_SMOOTH} x {PEAK_SMOOTH} mean "
                             f"(windows moved inside at the frame's edge)",
            **mapping.attributes()})
        write_exr(tmp / INDIRECT_SUM_FILE, indirect, attributes={
            "ilt:quantity": f"sum of beam frames, each without its spot's disc ({SPOT_SIGMAS:g} sigma)",
            **mapping.attributes()})
        draw_overlay(tmp / OVERLAY_FILE, total, spots, mapping)
        parameters = {k: v for k, v in asdict(params).items()}
        parameters["dark"] = str(dark) if dark else None
        write_manifest(tmp, "centroids", parameters, inputs=inputs, extra=fields)
    return {**fields, "output": str(out)}


#: flags that say a beam's spot is not what the scan meant to measure (no spot, a second
#: light, clipped values): WARNING, each named; the others (shape: a fold or a grazing
#: surface stretches a spot; outside: the plan reaches past the view) are INFO unless
#: more than SHAPE_WARN of the beams carry them
FAULT_FLAGS = ("none", "multiple", "saturated")
SHAPE_WARN = 0.10


def report_flags(beams, spots, names, out: Path) -> None:
    """Log each flagged beam (INFO) and what the user should look at (WARNING): the
    beams with a fault flag, or shape flags on more than :data:`SHAPE_WARN` of the scan."""
    flagged = [(b, s) for b, s in zip(beams, spots) if s.flags]
    for b, s in flagged:
        log.info("beam %d (%s): %s", b, names[b], format_flags(s.flags))
    overlay = Path(out) / OVERLAY_FILE
    for name in FAULT_FLAGS:
        hit = [b for b, s in flagged if name in s.flags]
        if hit:
            log.warning("%s: spot flagged %s (%s): build-isf drops %s; look at %s", _beam_list(hit), name,
                        _FAULT_MEANS[name], "it" if len(hit) == 1 else "them", overlay)
    shape = [b for b, s in flagged if not set(s.flags) & set(FAULT_FLAGS)]
    if len(shape) > SHAPE_WARN * len(beams):
        log.warning("%d of %d beams have flagged spots (%s): build-isf drops them; the focus, the spot size or "
                    "the region of interest may be off: look at %s", len(shape), len(beams),
                    ", ".join(sorted({k for b, s in flagged if b in shape for k in s.flags})), overlay)


_FAULT_MEANS = {"none": "no spot above the noise: laser off, blocked or aimed outside the view",
                "multiple": "a second spot: a reflection, flare or another light",
                "saturated": "the spot is clipped in every exposure: add a shorter one to the bracket"}


def _beam_list(beams: list[int]) -> str:
    shown = ", ".join(map(str, beams[:8])) + (f" and {len(beams) - 8} more" if len(beams) > 8 else "")
    return f"beam {shown}" if len(beams) == 1 else f"beams {shown}"


def _capture_beams(path: Path):
    """Beam names, beam directories, plan layout and manifest inputs of a capture directory."""
    import json

    from ilt.hdr.bracket import list_beams
    from ilt.io.manifest import MANIFEST, fingerprint_file

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

    from ilt.io.manifest import MANIFEST, fingerprint_file

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
    from ilt.io.exr import write_png
    from ilt.io.preview import log_scale

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


_DARK_CACHE: dict = {}
