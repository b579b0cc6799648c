"""File-level HDR stages: calibrate a bracket's response, merge brackets to EXR.

The algorithms (ilt.hdr.mitsunaga_nayar, ilt.hdr.merge) take arrays; this module reads
frames, checks that a bracket is one camera at one size, writes outputs atomically and
spreads beams over a ``concurrent.futures`` executor. Layout: docs/hdr.md.
"""

from __future__ import annotations

import concurrent.futures as cf
import hashlib
import io
import json
import logging
import math
import os
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import numpy as np

from ilt.hdr.bracket import Bracket, list_beams, logged_fingerprints, read_beam
from ilt.hdr.merge import MergeError, NoiseModel, merge_bracket
from ilt.hdr.mitsunaga_nayar import (
    RATIO_WARN_STOPS,
    CalibrationError,
    ResponseFit,
    fit_response,
    usable_samples,
)
from ilt.io.atomic import atomic_path
from ilt.io.beams import FrameRecord
from ilt.io.exr import write_exr, write_png
from ilt.io.manifest import MANIFEST, fingerprint_file, write_json, write_manifest
from ilt.io.raw import SATURATION_MARGIN, GreenInfo, RawError, read_color, read_green
from ilt.io.staged import staged_directory

log = logging.getLogger(__name__)

RAW_SUFFIXES = {".dng", ".cr2", ".cr3", ".nef", ".arw", ".orf", ".rw2", ".raf", ".pef", ".srw", ".raw"}


# ---------------------------------------------------------------- response files

@dataclass(frozen=True)
class Response:
    """A calibrated response as stored in response.json: the inverse response f on
    normalised values and measured relative exposures keyed by nominal (time, f-number)."""

    coefficients: np.ndarray
    exposures: dict[tuple[str, str], float] = field(default_factory=dict)
    exponent: float = 1.0  # f(M) = sum c_n u^n with u = M^exponent

    def __call__(self, m):
        u = np.asarray(m, dtype=np.float64) ** self.exponent
        return np.polynomial.polynomial.polyval(u, self.coefficients)

    def slope(self, m):
        """f'(M), same shape (chain rule through u = M^exponent)."""
        m = np.maximum(np.asarray(m, dtype=np.float64), 1e-12)
        du = self.exponent * m ** (self.exponent - 1)
        return np.polynomial.polynomial.polyval(m**self.exponent,
                                                np.polynomial.polynomial.polyder(self.coefficients)) * du

    def is_identity(self) -> bool:
        c = self.coefficients
        return len(c) == 2 and c[0] == 0 and c[1] == 1 and self.exponent == 1


def load_response(path: str | os.PathLike) -> Response:
    """Read response.json written by `calibrate`; CalibrationError naming the file."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
        c = np.asarray(data["coefficients"], dtype=np.float64)
        exponent = float(data.get("exponent", 1.0))
        table = {(x["exposure_time"], x["f_number"]): float(x["relative_exposure"])
                 for x in data.get("exposures", [])}
    except FileNotFoundError:
        raise
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise CalibrationError(f"{path}: not a response file written by ilt calibrate ({exc})") from None
    if c.ndim != 1 or c.size < 2 or not np.isfinite(c).all():
        raise CalibrationError(f"{path}: coefficients must be a list of at least two numbers")
    if not (math.isfinite(exponent) and exponent > 0):
        raise CalibrationError(f"{path}: exponent {exponent!r} must be a positive number")
    return Response(c, table, exponent)


# ---------------------------------------------------------------- reading brackets

@dataclass
class Frame:
    """One decoded frame: green (h, w) black-subtracted DN (or (h, w, 3) with colour),
    its info, and the fingerprint of the file's bytes."""

    image: np.ndarray
    info: GreenInfo
    fingerprint: str


def read_frame(path: Path, record: FrameRecord | None = None, hand_time=None, *,
               margin: float = SATURATION_MARGIN, color: bool = False,
               expected: str | None = None) -> Frame:
    """Read a RAW frame once, hash those bytes and decode them from memory.

    ``expected``: the fingerprint ("sha256:<hex>") the capture logged for the file;
    a frame whose bytes differ is refused (RawError naming it) before it is decoded.
    """
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise RawError(f"{path}: no such file") from None
    fingerprint = "sha256:" + hashlib.sha256(data).hexdigest()
    if expected is not None and fingerprint != expected:
        raise RawError(f"{path}: its sha256 is not the one capture.jsonl logged when it was shot "
                       "(a file copied over it?); restore the captured file, or capture the beam again")
    green, info = read_green(path, record.exposure_time if record else None,
                             record.f_number if record else None, hand_time, margin, data=data,
                             dtype=np.float32)
    image = green
    if color:
        image, saturated = read_color(path, margin, data=data)
        info = GreenInfo(**{**info.__dict__, "saturated": saturated})
    return Frame(image, info, fingerprint)


def read_ldr_frame(path: Path, record: FrameRecord | None = None, hand_time=None, *,
                   margin: float = SATURATION_MARGIN, color: bool = False,
                   expected: str | None = None) -> Frame:
    """Read an 8/16-bit TIFF, PNG or JPEG frame (OpenCV) as a :class:`Frame`: green (or
    RGB) codes, black 0, white the code's maximum, every pixel its own sample
    (origin (0, 0), scale 1). A code at the maximum counts as saturated."""
    from ilt.io.exposure import read_exif, resolve_facts

    if not path.is_file():
        raise MergeError(f"{path}: no such file")
    data = path.read_bytes()  # read once: hashed, decoded and its EXIF parsed from memory
    fingerprint = "sha256:" + hashlib.sha256(data).hexdigest()
    if expected is not None and fingerprint != expected:
        raise RawError(f"{path}: its sha256 is not the one capture.jsonl logged when it was shot")
    image, top = _read_codes(path, MergeError, data)
    tags = read_exif(io.BytesIO(data))
    facts = resolve_facts(path, record.exposure_time if record else None,
                          record.f_number if record else None, tags, None, hand_time)
    saturated = (image >= top - 0.5).any(axis=2) if image.ndim == 3 else image >= top - 0.5
    if image.ndim == 3:
        image = image[:, :, ::-1] if color else image[:, :, 1]  # OpenCV's BGR
    elif color:
        image = np.repeat(image[:, :, None], 3, axis=2)
    info = GreenInfo(path, facts, str(tags.get("Image Make", "")).strip(), str(tags.get("Image Model", "")).strip(),
                     saturated.shape, "", (0.0, 0.0, 0.0, 0.0), top, top, top - 0.5, saturated,
                     origin=(0.0, 0.0), scale=1.0)
    return Frame(np.ascontiguousarray(image, dtype=np.float32), info, fingerprint)


def _read_codes(path: Path, error, data: bytes | None = None) -> tuple[np.ndarray, float]:
    """(codes as read by OpenCV, their maximum) of an 8/16-bit image (``data``: its
    bytes, when already read), OpenCV's own warnings silenced (its TIFF reader logs every
    EXIF tag it does not know)."""
    import cv2

    if data is None and not path.is_file():
        raise error(f"{path}: no such file")
    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    flags = cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH
    try:
        image = cv2.imread(str(path), flags) if data is None else \
            cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    finally:
        cv2.utils.logging.setLogLevel(level)
    if image is None:
        raise error(f"{path}: not an image OpenCV can read (nor a RAW file by its suffix)")
    if image.dtype not in (np.uint8, np.uint16):
        raise error(f"{path}: {image.dtype} pixels; 8- or 16-bit images are needed")
    if image.ndim == 3 and image.shape[2] == 4:
        image = image[:, :, :3]
    return image, float(np.iinfo(image.dtype).max)


def check_same_camera(frames: list[Frame]) -> None:
    """Every frame of a bracket from one camera at one size; RawError naming the odd file."""
    first = frames[0].info
    for fr in frames[1:]:
        i = fr.info
        if i.full_shape != first.full_shape:
            raise RawError(f"{i.path}: size {i.full_shape[1]} x {i.full_shape[0]} differs from "
                           f"{first.path.name} ({first.full_shape[1]} x {first.full_shape[0]})")
        if i.camera != first.camera or i.cfa != first.cfa:
            raise RawError(f"{i.path}: camera {i.camera!r} ({i.cfa}) differs from "
                           f"{first.path.name} ({first.camera!r}, {first.cfa})")


def relative_exposures(frames: list[Frame], response: Response | None) -> np.ndarray:
    """(K,) e_k = t / N^2, or the calibration's measured value for the same nominal facts."""
    out = []
    for fr in frames:
        x = fr.info.exposure
        key = (x.time_text, x.f_number_text)
        if response is not None and key in response.exposures:
            out.append(response.exposures[key])
        else:
            out.append(x.relative_exposure())
    return np.asarray(out)


# ---------------------------------------------------------------- merging

@dataclass(frozen=True)
class MergeOptions:
    """noise: NoiseModel (gain e-/DN, read noise DN); response: calibrated Response or
    None (linear); margin: saturation headroom; color: merge RGB (``--color``);
    compression: EXR compression, lossless only (zip at deflate level 1 by default)."""

    noise: NoiseModel = NoiseModel()
    response: Response | None = None
    margin: float = SATURATION_MARGIN
    color: bool = False
    compression: str = "zip:1"


def merge_frames(frames: list[Frame], dark: Frame | None, options: MergeOptions):
    """Merge decoded frames; returns (radiance, count, saturated, exposures, attributes)."""
    check_same_camera(frames + ([dark] if dark else []))
    exposures = relative_exposures(frames, options.response)
    response = options.response
    full_scale = frames[0].info.white_level - float(np.mean(frames[0].info.black_levels))
    if response is not None and response.is_identity():
        response = None
    sat = [fr.info.saturated for fr in frames]
    images = [fr.image for fr in frames]
    if options.color:
        sat = [np.repeat(s[..., None], 3, axis=2) for s in sat]
    ldr = frames[0].info.cfa == ""  # an 8/16-bit image: every pixel a sample, no CFA
    noise = NoiseModel(options.noise.gain, options.noise.read_noise, sites=1) if ldr else options.noise
    try:
        radiance, count, saturated = merge_bracket(
            images, exposures, sat, noise=noise, response=response,
            full_scale=full_scale, dark=dark.image if dark else None,
            slope=response.slope if (ldr and response is not None) else None)
    except MergeError as exc:
        names = ", ".join(fr.info.path.name for fr in frames)
        raise MergeError(f"{frames[0].info.path.parent}: {exc} ({names})") from None
    if options.color:
        count, saturated = count.min(axis=2), saturated.any(axis=2)
    first = frames[0].info
    attributes = {
        "units": ("codes per second at f/1 through the inverse response, per pixel" if ldr else
                  "DN per second at f/1 per photosite, black-subtracted")
                 + (" (camera RGB)" if options.color else " (green)"),
        "frames": len(frames),
        "exposure_times": [fr.info.exposure.exposure_time for fr in frames],
        "f_numbers": [fr.info.exposure.f_number for fr in frames],
        "relative_exposures": exposures.tolist(),
        "camera": first.camera,
        "full_shape": list(first.full_shape),
        "pixel_origin": list(first.origin),
        "pixel_scale": float(first.scale),
        "gain": float(options.noise.gain),
        "read_noise": float(options.noise.read_noise),
        "dark_frame": dark.info.path.name if dark else "",
        "saturated_pixels": int(saturated.sum()),
    }
    return radiance, count, saturated, exposures, attributes


def merge_beam(beam_dir: str | os.PathLike, out_dir: str | os.PathLike, options: MergeOptions,
               fingerprints: dict[str, str] | None = None) -> dict:
    """Merge one beam directory into ``out_dir/<beam>.exr``, ``.valid.png``, ``.saturated.png``.

    Every frame is hashed as it is read (the bytes decoded are the bytes hashed) and
    its EXIF exposure checked against the beam manifest. ``fingerprints``: frame file
    name -> "sha256:<hex>" the capture logged; a frame that differs is refused.
    Memory: one bracket. Returns a summary (beam, files, inputs with the fingerprints
    hashed here, how many were checked against the log).
    Raises RawError/MergeError/ExposureError naming the file at fault; writes nothing then.
    """
    bracket = read_beam(beam_dir)
    known = fingerprints or {}

    def read(record: FrameRecord) -> Frame:
        return read_frame(bracket.path(record), record, margin=options.margin, color=options.color,
                          expected=known.get(record.file))

    frames = [read(r) for r in bracket.frames]
    dark = read(bracket.dark) if bracket.dark else None
    radiance, count, saturated, exposures, attributes = merge_frames(frames, dark, options)
    name = Path(beam_dir).name
    out_dir = Path(out_dir)
    channels = ["R", "G", "B"] if options.color else ["Y"]
    image = radiance if options.color else radiance[..., None]
    write_exr(out_dir / f"{name}.exr", image, channels, attributes, options.compression)
    write_png(out_dir / f"{name}.valid.png", count)
    write_png(out_dir / f"{name}.saturated.png", saturated.astype(np.uint8) * 255)
    inputs = {f"{name}/{fr.info.path.name}": fr.fingerprint for fr in frames + ([dark] if dark else [])}
    return {"beam": name, "frames": len(frames), "saturated_pixels": int(saturated.sum()),
            "min_valid": int(count.min()), "inputs": inputs,
            "logged": sum(Path(f).name in known for f in inputs),
            "exposures": [fr.info.exposure.as_dict() for fr in frames]}


def merge_capture(
    capture_dir: str | os.PathLike,
    output: str | os.PathLike,
    options: MergeOptions = MergeOptions(),
    *,
    executor: cf.Executor | None = None,
    workers: int = 1,
    force: bool = False,
    parameters: dict | None = None,
    progress=None,
) -> tuple[Path, dict]:
    """Merge every beam of a capture directory into an HDR directory (docs/hdr.md).
    ``progress(n)`` is called as beams finish.

    Beams run through ``executor`` (any concurrent.futures.Executor, e.g. a cluster's),
    else a process pool of ``workers`` (1: in this process). The directory is staged and
    renamed into place only when every beam succeeded: on any error an existing
    ``output`` is untouched and nothing half-written remains.

    Input fingerprints are the hashes of the bytes merged (each frame is read once);
    a frame whose hash is not the one the capture's log (``capture.jsonl``) recorded,
    or whose EXIF exposure is not its manifest's, is refused. The capture's own
    manifest.json is recorded among the inputs by its hash, which is how ``ilt run``
    knows that a merge made by hand was made from this capture.
    """
    beams = list_beams(capture_dir)
    logged = logged_fingerprints(capture_dir)
    top = Path(capture_dir) / MANIFEST
    with staged_directory(output, force=force) as tmp:
        summaries = _run_beams(beams, tmp, options, executor, workers, logged, progress)
        clipped = [s for s in summaries if s["saturated_pixels"]]
        for s in clipped:
            log.warning("%s: %d pixels saturated in every exposure: their values are lower bounds "
                        "(add a shorter exposure or a smaller aperture to the bracket)", s["beam"],
                        s["saturated_pixels"])
        inputs = {k: v for s in summaries for k, v in s.pop("inputs").items()}
        checked = sum(s.pop("logged") for s in summaries)
        frames = len(inputs)
        if top.exists():
            inputs[MANIFEST] = fingerprint_file(top)
        first = summaries[0]
        write_manifest(tmp, "merge", parameters or {}, inputs, extra={
            "fingerprints": {"hashed": frames, "checked_against_capture_log": checked},
            "beams": [s["beam"] for s in summaries],
            "channels": ["R", "G", "B"] if options.color else ["Y"],
            "pixel_mapping": {"origin": [0.5, 0.5], "scale": 2.0,
                              "note": "pixel (i, j) is at full-frame x = 0.5 + 2 j, y = 0.5 + 2 i"},
            "beam_summaries": summaries,
            "frames_per_beam": first["frames"],
            "beams_with_clipped_pixels": [s["beam"] for s in clipped],
        })
    return Path(output), {"output": str(output), "beams": len(summaries),
                          "saturated_pixels": sum(s["saturated_pixels"] for s in summaries)}


def _run_beams(beams, out_dir, options, executor, workers, logged, progress=None) -> list[dict]:
    """Every beam through :func:`ilt.parallel.chunks.run_chunks` (a bounded number in flight, a
    dead worker named by its beam) on the caller's executor or a pool of ``workers``
    that is stopped at once on an error or a signal (:func:`ilt.parallel.chunks.beam_executor`)."""
    from ilt.parallel.chunks import beam_executor, run_chunks

    tasks = [([i], b, out_dir, options, logged.get(b.name)) for i, b in enumerate(beams)]
    with beam_executor(executor, workers) as pool:
        return list(run_chunks(_merge_one, tasks, pool, progress=progress))


def _merge_one(index, beam_dir, out_dir, options, logged):
    """Worker: :func:`merge_beam` of one beam (``index``: its place, for messages)."""
    return merge_beam(beam_dir, out_dir, options, logged)


def merge_files(paths: list[str | os.PathLike], output: str | os.PathLike,
                options: MergeOptions = MergeOptions(), times: list[Fraction] | None = None,
                dark: str | os.PathLike | None = None, force: bool = False) -> tuple[Path, dict]:
    """Merge one hand-shot bracket into ``output`` (.exr) plus ``<stem>.valid.png`` and
    ``<stem>.saturated.png`` beside it, making ``output``'s directory if needed.

    RAW files: the green of each 2x2 cell (or camera RGB). 8/16-bit TIFF, PNG or JPEG
    files: every pixel (green, or RGB with ``color``), through the response from
    ``ilt calibrate`` (required for 8-bit files, whose codes are not linear), with the
    noise of a code carried through f (:func:`ilt.hdr.merge.merge_bracket`'s ``slope``).
    """
    output = Path(output)
    if output.suffix.lower() != ".exr":
        raise MergeError(f"{output}: the output of --bracket must be an .exr file")
    if times is not None and len(times) != len(paths):
        raise MergeError(f"--times gives {len(times)} exposure times for {len(paths)} files")
    siblings = [output, output.with_suffix(".valid.png"), output.with_suffix(".saturated.png")]
    for p in siblings:
        if p.exists() and not force:
            raise MergeError(f"{p} exists; use --force to replace it")
    _check_writable_parent(output, MergeError)
    raw = [Path(p).suffix.lower() in RAW_SUFFIXES for p in paths]
    if any(raw) and not all(raw):
        raise MergeError(f"{paths[raw.index(False)]}: a bracket mixes RAW and 8/16-bit files")
    read = read_frame if all(raw) else read_ldr_frame
    frames = [read(Path(p), None, times[k] if times else None, margin=options.margin,
                   color=options.color) for k, p in enumerate(paths)]
    dark_frame = read(Path(dark), None, max(times) if times else None, margin=options.margin,
                      color=options.color) if dark else None
    if not all(raw):
        bits = {fr.info.white_level for fr in frames}
        if options.response is None and 255 in bits:
            raise MergeError(f"{paths[0]}: 8-bit codes are not linear; give --response from "
                             "'ilt calibrate' of this camera")
    radiance, count, saturated, _, attributes = merge_frames(frames, dark_frame, options)
    output.parent.mkdir(parents=True, exist_ok=True)
    image = radiance if options.color else radiance[..., None]
    write_exr(output, image, ["R", "G", "B"] if options.color else ["Y"], attributes, options.compression)
    write_png(siblings[1], count)
    write_png(siblings[2], saturated.astype(np.uint8) * 255)
    return output, {"output": str(output), "frames": len(frames), "saturated_pixels": int(saturated.sum())}


# ---------------------------------------------------------------- calibration

@dataclass
class CalibrationInput:
    """A bracket (or several of the same exposures) as normalised images for fitting."""

    images: list[list[np.ndarray]]  # per scene, Q images (h, w) of M in [0, 1], shortest first
    valid: list[list[np.ndarray]]
    facts: list  # Q ExposureFacts, shortest first
    raw: bool
    files: list[Path]


def collect_calibration_input(inputs: list[str | os.PathLike], times: list[Fraction] | None,
                              max_beams: int = 8) -> CalibrationInput:
    """Files (a bracket), a beam directory, or a capture directory (up to ``max_beams``
    beams pooled) -> normalised images. RAW: green / (white - black); others: value / max code."""
    paths = [Path(p) for p in inputs]
    brackets: list[list[tuple[Path, FrameRecord | None]]]
    if len(paths) == 1 and paths[0].is_dir():
        d = paths[0]
        if (d / "manifest.json").exists() and not any(d.glob("beam-[0-9]*")):
            beam_dirs = [d]
        else:
            beam_dirs = list_beams(d)[:max_beams]
        brackets = []
        for b in beam_dirs:
            br: Bracket = read_beam(b)
            brackets.append([(br.path(r), r) for r in br.frames])
    else:
        brackets = [[(p, None) for p in paths]]
    if times is not None and any(len(b) != len(times) for b in brackets):
        raise CalibrationError(f"--times gives {len(times)} times for a bracket of {len(brackets[0])} files")
    scenes, valid, facts_ref, raw_kind, files = [], [], None, None, []
    for bracket in brackets:
        loaded = [_load_normalised(p, r, times[k] if times else None) for k, (p, r) in enumerate(bracket)]
        kinds = {x[2] for x in loaded}
        if len(kinds) > 1:
            raise CalibrationError(f"{bracket[0][0]}: mixes RAW and non-RAW files in one bracket")
        raw_kind = kinds.pop() if raw_kind is None else raw_kind
        shapes = {x[0].shape for x in loaded}
        if len(shapes) > 1:
            odd, shape = next((p, x[0].shape) for (p, _), x in zip(bracket, loaded)
                              if x[0].shape != loaded[0][0].shape)
            raise CalibrationError(f"{odd}: size {shape} differs from {bracket[0][0].name}")
        order = sorted(range(len(loaded)), key=lambda k: loaded[k][1].relative_exposure())
        facts = [loaded[k][1] for k in order]
        if facts_ref is not None and [f.relative_exposure() for f in facts] != \
                [f.relative_exposure() for f in facts_ref]:
            raise CalibrationError(f"{bracket[0][0].parent}: exposures differ from the first bracket's")
        facts_ref = facts
        images = [loaded[k][0] for k in order]
        clip = [loaded[k][3] for k in order]
        # 8/16-bit: three codes above black, and the neighbours a code below the top (a
        # sample a code from clipping is there because its noise was negative)
        low, high = (0.003, 1.0) if raw_kind else (3 / 255, 254 / 255)
        masks = usable_samples(images, low, high, 1.0)
        valid.append([m & ~c for m, c in zip(masks, clip)])
        scenes.append(images)
        files += [p for p, _ in bracket]
    return CalibrationInput(scenes, valid, facts_ref, bool(raw_kind), files)


def _load_normalised(path: Path, record: FrameRecord | None, hand_time):
    """(M image, facts, is_raw, clipped mask) of one file."""
    from ilt.io.exposure import resolve_facts

    if path.suffix.lower() in RAW_SUFFIXES:
        frame = read_frame(path, record, hand_time)
        i = frame.info
        full = i.white_level - float(np.mean(i.black_levels))
        return frame.image / full, i.exposure, True, i.saturated
    image, top = _read_codes(path, CalibrationError)
    if image.ndim == 3:
        image = image[:, :, 1]  # green of BGR
    facts = resolve_facts(path, record.exposure_time if record else None,
                          record.f_number if record else None, hand_time=hand_time)
    return image / top, facts, False, image >= top - 0.5


def calibrate(inputs, output: str | os.PathLike, *, times=None, order=None, max_order=None,
              pin_span=None, estimate_ratios=None, tolerance=1e-6, plot=True,
              force=False) -> tuple[Path, dict]:
    """Mitsunaga-Nayar calibration of a bracket; writes ``output`` (JSON) and a PNG plot
    beside it (same stem), creating ``output``'s directory if needed. RAW input: order
    <= 3 and the exposure ratios estimated; other images: order <= 12, the nominal
    ratios trusted unless ``estimate_ratios`` (see ilt.hdr.mitsunaga_nayar)."""
    output = Path(output)
    plot_path = output.with_suffix(".png")
    for p in (output, plot_path) if plot else (output,):
        if p.exists() and not force:
            raise CalibrationError(f"{p} exists; use --force to replace it")
    _check_writable_parent(output)
    data = collect_calibration_input(inputs, times)
    e = np.array([f.relative_exposure() for f in data.facts])
    if np.any(np.diff(e) <= 0):
        raise CalibrationError(f"{data.files[0].parent}: two frames have the same exposure; "
                               "calibration needs distinct exposures")
    images = [np.concatenate([s[q].ravel() for s in data.images]) for q in range(len(e))]
    valid = [np.concatenate([v[q].ravel() for v in data.valid]) for q in range(len(e))]
    estimate = data.raw if estimate_ratios is None else estimate_ratios
    fit = fit_response(images, e, valid, order=order,
                       max_order=max_order or (3 if data.raw else 12),
                       zero_intercept=data.raw, estimate_ratios=estimate,
                       pin_span=(not data.raw) if pin_span is None else pin_span,
                       noise=1e-3 if data.raw else 1 / 255, tolerance=tolerance)
    warnings = []
    if not fit.converged:
        warnings.append(f"the fit did not converge to tolerance {tolerance:g} in {fit.iterations} steps; "
                        "the response may be off (try --order or a longer bracket)")
    names = [f"{f.time_text} s at f/{f.f_number_text}" for f in data.facts]
    for q, stops in enumerate(fit.ratio_stops()):
        if abs(stops) > RATIO_WARN_STOPS:
            warnings.append(f"the measured ratio of {names[q + 1]} to {names[q]} is {fit.ratios[q]:.3g}, "
                            f"{stops:+.2f} stops from the nominal {fit.nominal_ratios[q]:.3g}: check the "
                            "exposure facts (EXIF, --times) or whether the scene moved")
    for w in warnings:
        log.warning("%s: %s", data.files[0].parent if len(data.files) else output, w)
    measured = fit.relative_exposures()
    # measured exposures keep the nominal scale: their geometric mean equals the nominal one
    measured = measured * np.exp(np.mean(np.log(e)) - np.mean(np.log(measured)))
    table_m, table_f = fit.table(256)
    result = {
        "method": "Mitsunaga & Nayar 1999, monotone (Bernstein form), robust log-residual fit",
        "kind": "raw" if data.raw else "ldr",
        "coefficients": fit.coefficients.tolist(),
        "exponent": fit.exponent,
        "bernstein": fit.bernstein.tolist(),
        "table": {"note": "f sampled at 256 evenly spaced M in [0, 1]; interpolate linearly",
                  "m": table_m.tolist(), "f": table_f.tolist()},
        "order": fit.order,
        "ratios_estimated": bool(estimate),
        "warnings": warnings,
        "ratios": fit.ratios.tolist(),
        "nominal_ratios": fit.nominal_ratios.tolist(),
        "exposures": [{"exposure_time": f.time_text, "f_number": f.f_number_text,
                       "nominal": f.relative_exposure(), "relative_exposure": float(m)}
                      for f, m in zip(data.facts, measured)],
        "residual": fit.residual,
        "held_out": {str(k): v for k, v in fit.held_out.items()},
        "linearity_error": fit.linearity_error(),
        "iterations": fit.iterations,
        "converged": fit.converged,
        "pairs": fit.pairs,
        "inputs": [str(p) for p in data.files],
    }
    output.parent.mkdir(parents=True, exist_ok=True)
    write_json(output, result)
    if plot:
        _plot_response(fit, plot_path)
    return output, result


def _check_writable_parent(path: Path, error=CalibrationError) -> None:
    """Refuse, before any work, an output whose directory cannot be made or written."""
    parent = path.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise error(f"{path}: {parent} is a file, so the directory cannot be made")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise error(f"{path}: {parent} is not writable")


def _plot_response(fit: ResponseFit, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    m = np.linspace(0, 1, 501)
    fig, ax = plt.subplots(figsize=(5, 4), dpi=100)
    ax.plot(m, fit(m), label=f"f(M), order {fit.order}")
    ax.plot(m, m, "k:", lw=0.8, label="linear")
    ax.set_xlabel("normalised measurement M")
    ax.set_ylabel("normalised irradiance I = f(M)")
    ax.set_title(f"max |f(M) - M| = {fit.linearity_error():.2e}")
    ax.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
