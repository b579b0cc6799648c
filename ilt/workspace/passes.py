"""Refine passes of ``ilt run``: scan, decide the next beams, scan them, again (docs/refine.md).

With ``[refine] passes = N`` in the rig TOML, ``ilt run`` loops N times after the first
scan: build-isf -> ``ilt refine`` into ``WORKSPACE/passes/pass-P/`` -> capture the new
beams, appended to the same ``capture/`` (journaled as an ``extend`` event, resumable
like any capture) -> merge -> centroids -> build-isf; photos and decompose run once, on
the last pass's ISF. Each pass directory is written whole or not at all (its manifest
last) and is never rewritten: it records what was decided from the scan as it was. The
capture's run record names every pass's ``refine.csv`` by its hash, so an edited or
missing pass makes the capture stale, never silently re-aimed.

``passes/landing.csv`` (rewritten after each pass's centroids): for every beam a pass
added, the pixel refine asked for, the spot it gave and the distance between them
(the pointing map's error, :mod:`ilt.refine.pointing`); ``landing.json`` its medians.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ilt.capture.config import ConfigError
from ilt.io.atomic import atomic_path
from ilt.io.manifest import MANIFEST, StageError, fingerprint_file, write_json
from ilt.io.workspace_dirs import LANDING_CSV, Workspace

log = logging.getLogger(__name__)

LANDING_JSON = "landing.json"
#: most refine passes a config may ask (each re-runs merge, centroids and build-isf)
MAX_PASSES = 100


@dataclass(frozen=True)
class RefineConfig:
    """[refine]: ``passes`` after the first scan, each adding at most ``beams`` beams, or
    as many as ``hours`` of rig time allow over all passes (the capture estimate's time
    a beam, from this workspace's capture log once it has one); ``min_spacing`` as
    ``ilt refine --min-spacing``."""

    passes: int = 0
    beams: int | None = None
    hours: float | None = None
    min_spacing: float | None = None

    def as_dict(self) -> dict:
        return {"passes": self.passes, "beams": self.beams, "hours": self.hours, "min_spacing": self.min_spacing}


def parse_refine(section, where: str) -> RefineConfig:
    """The [refine] table; ConfigError naming ``where`` and the key."""
    if not isinstance(section, dict):
        raise ConfigError(f"{where}: must be a table")
    known = ("passes", "beams", "hours", "min-spacing")
    values = {k.replace("_", "-"): v for k, v in section.items()}
    if unknown := set(values) - set(known):
        raise ConfigError(f"{where}: unknown key {min(unknown)!r} (known: {', '.join(known)})")

    def number(key, kind, low):
        value = values.get(key)
        if value is None:
            return None
        ok = isinstance(value, int) if kind is int else isinstance(value, (int, float))
        if isinstance(value, bool) or not ok or not math.isfinite(value) or value < low or \
                (kind is not int and value == 0):
            what = "a whole number" if kind is int else "a number"
            raise ConfigError(f"{where}: {key} = {value!r}: must be {what} >= {low}" +
                              (" and > 0" if kind is not int else ""))
        return kind(value)

    passes = number("passes", int, 0) or 0
    if passes > MAX_PASSES:
        raise ConfigError(f"{where}: passes = {passes}: at most {MAX_PASSES}")
    beams, hours = number("beams", int, 2), number("hours", float, 0)   # refine's beams come in pairs
    if beams is not None and hours is not None:
        raise ConfigError(f"{where}: beams and hours both given; keep one")
    if passes and beams is None and hours is None:
        raise ConfigError(f"{where}: passes = {passes} needs beams = K (new beams a pass) or hours = H "
                          "(rig time for all passes)")
    return RefineConfig(passes, beams, hours, number("min-spacing", float, 0))


@dataclass(frozen=True)
class Pass:
    """A refine pass done: its number (from 1), directory, the beams it added (angles in
    the plan's units and the pixels they were aimed at) and its refine.csv's hash."""

    number: int
    directory: Path
    angles: np.ndarray
    pixels: np.ndarray
    fingerprint: str

    @property
    def beams(self) -> int:
        return len(self.angles)


def pass_dir(ws: Workspace, number: int) -> Path:
    return ws.passes / f"pass-{number}"


def completed_passes(ws: Workspace) -> list[Pass]:
    """The passes with a manifest, 1, 2, ... up to the first missing one (:func:`read_pass`)."""
    out = []
    while (d := pass_dir(ws, len(out) + 1)).is_dir() and (d / MANIFEST).is_file():
        out.append(read_pass(d, len(out) + 1))
    return out


def read_pass(directory: Path, number: int) -> Pass:
    """Pass ``number`` from its directory's refine.csv. StageError naming the file when it
    has no pan/tilt or cannot be read."""
    from ilt.refine.stage import CSV_FILE

    path = directory / CSV_FILE
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
        angles = np.array([[float(r["pan"]), float(r["tilt"])] for r in rows]).reshape(-1, 2)
        pixels = np.array([[float(r["x"]), float(r["y"])] for r in rows]).reshape(-1, 2)
    except (OSError, KeyError, ValueError, TypeError) as exc:
        raise StageError(f"{path}: not a refine pass's beams with pan and tilt ({exc})") from None
    return Pass(number, directory, angles, pixels, fingerprint_file(path))


def kept_coverage(passes: list[Pass]) -> Path | None:
    """The cells of the ISF the latest refine pass read (its copy of ``cells.exr``), which
    the build with its beams keeps covered (``ilt build-isf --keep-covered``): a scan grown
    by passes never covers less than before. None before the first pass."""
    from ilt.isf.directory import CELLS_FILE

    for p in reversed(passes):
        if (p.directory / CELLS_FILE).is_file():
            return p.directory / CELLS_FILE
    return None


def passes_parameter(passes: list[Pass]) -> list[dict]:
    """What a capture extended by ``passes`` depends on (its run record's ``passes``)."""
    return [{"beams": p.beams, "refine": p.fingerprint} for p in passes]


def finished(cfg: RefineConfig, passes: list[Pass]) -> bool:
    """No pass left to run: all asked for are done, or the last one found no beam to add."""
    return len(passes) >= cfg.passes or bool(passes and passes[-1].beams == 0)


def beams_for_pass(cfg: RefineConfig, rig, passes: list[Pass], capture_dir: Path) -> int:
    """The beams the next pass may add: ``beams``, or what is left of ``hours`` shared
    over the passes left, at the estimate's time a beam (the workspace's capture log
    refines it, :func:`ilt.capture.estimate.estimate`)."""
    if cfg.beams is not None:
        return cfg.beams
    from ilt.capture.estimate import estimate

    logs = [capture_dir / "capture.jsonl"] if (capture_dir / "capture.jsonl").is_file() else []
    est = estimate(rig, logs)
    per_beam = est.seconds / max(est.beams, 1)
    left = cfg.hours * 3600 - per_beam * sum(p.beams for p in passes)
    beams = max(0, int(left / per_beam / (cfg.passes - len(passes))))
    return beams if beams >= 2 else 0     # refine places pairs: one beam is none


def run_refine_pass(ws: Workspace, cfg: RefineConfig, rig, passes: list[Pass]) -> Pass:
    """Decide the next pass's beams from the workspace's ISF and capture into
    ``passes/pass-P/`` (written whole: :func:`ilt.refine.stage.refine`)."""
    from ilt.refine.stage import refine

    number = len(passes) + 1
    capture_dir = ws.stage_dir("capture")
    beams = beams_for_pass(cfg, rig, passes, capture_dir)
    out = pass_dir(ws, number)
    if beams == 0:
        log.info("refine pass %d: [refine] hours leave no beam; stopping", number)
        _write_empty_pass(out, number)
    else:
        summary = refine(ws.stage_dir("build-isf"), out, beams, capture=capture_dir,
                         min_spacing=cfg.min_spacing, force=True)
        log.info("refine pass %d: %d new beams (indicator %.3g -> %.3g) -> %s", number, summary["beams"],
                 summary["indicator"]["before"], summary["indicator"]["after"], out / "refine.csv")
    return read_pass(out, number)


def _write_empty_pass(out: Path, number: int) -> None:
    from ilt.io.manifest import write_manifest
    from ilt.io.staged import staged_directory
    from ilt.refine.stage import CSV_FILE

    with staged_directory(out, force=True) as tmp:
        (tmp / CSV_FILE).write_text("x,y,pan,tilt,gain\n")
        write_manifest(tmp, "refine", {"beams": 0}, extra={"pass": number, "beams": 0})


def write_landing(ws: Workspace, passes: list[Pass], base_m: int) -> dict | None:
    """``passes/landing.csv`` and ``landing.json`` from the workspace's ISF spots
    (``samples.csv``: where each kept beam's spot is): for each
    beam a pass added (capture beams ``base_m`` on, in pass order), the target pixel,
    the spot found and their distance (full-resolution pixels); "dropped" when the ISF
    has no spot for it. Returns the summary (None without passes)."""
    from ilt.isf.directory import SAMPLES_FILE, read_samples_with_beams

    if not passes:
        return None
    samples, beams = read_samples_with_beams(ws.stage_dir("build-isf") / SAMPLES_FILE)
    spot_of = dict(zip(beams.tolist(), samples))
    lines, per_pass = [], []
    beam = base_m
    for p in passes:
        errors = []
        for target in p.pixels:
            spot = spot_of.get(beam)
            error = None if spot is None else float(np.hypot(*(spot - target)))
            if error is not None:
                errors.append(error)
            lines.append([p.number, beam, *target.tolist(), *(spot.tolist() if spot is not None else ["", ""]),
                          "" if error is None else round(error, 4), "" if spot is not None else "dropped"])
            beam += 1
        per_pass.append({"pass": p.number, "beams": p.beams, "found": len(errors),
                         "median_px": float(np.median(errors)) if errors else None,
                         "max_px": float(np.max(errors)) if errors else None})
    directory = ws.passes
    with atomic_path(directory / LANDING_CSV) as tmp, open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["pass", "beam", "target_x", "target_y", "spot_x", "spot_y", "error_px", "flags"])
        w.writerows(lines)
    summary = {"passes": per_pass}
    write_json(directory / LANDING_JSON, summary)
    for s in per_pass[-1:]:
        if s["found"]:
            log.info("refine pass %d: %d of %d new beams found, landing %.2f px from their targets (median; "
                     "max %.2f) -> %s", s["pass"], s["found"], s["beams"], s["median_px"], s["max_px"],
                     directory / LANDING_CSV)
    return summary


def read_landing(ws: Workspace) -> dict | None:
    path = ws.passes / LANDING_JSON
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def set_aside(ws: Workspace) -> Path | None:
    """Move ``passes/`` to ``passes.previous-N`` (a scan started again keeps the old decisions)."""
    d = ws.passes
    if not d.exists():
        return None
    k = 1
    while (aside := d.with_name(f"{d.name}.previous-{k}")).exists():
        k += 1
    os.replace(d, aside)
    return aside
