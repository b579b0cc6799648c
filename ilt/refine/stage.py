"""``ilt refine``: an ISF directory in, the next beams out (docs/refine.md).

Writes ``OUT/refine.csv`` (``x,y`` full-resolution sensor pixels where each new beam
should land, ``pan,tilt`` in the plan's units when the capture is known, ``gain`` the
indicator's share it removes; best first), ``OUT/refine.json`` (the indicator before and
after, the counts), ``OUT/refine.png`` (the cells shaded by their beams' prediction residual,
the spots and the targets), a copy of the ISF's ``cells.exr`` (the coverage a build with the
new beams keeps: ``ilt build-isf --keep-covered``, which ``ilt run``'s passes give it) and
the manifest. Works on an ISF built from bare beam
frames: without a capture there are no angles, only pixels.
"""

from __future__ import annotations

import csv
import logging
import os
import shutil
from pathlib import Path

import numpy as np

from ilt.io.manifest import (
    MANIFEST,
    StageError,
    fingerprint_file,
    read_manifest,
    write_json,
    write_manifest,
)
from ilt.io.staged import staged_directory
from ilt.isf.directory import CELLS_FILE, SAMPLES_FILE, T_FILE, ISFError, load_isf
from ilt.isf.fold_transfer import recorded_lines
from ilt.isf.noise import T_VAR_FILE, read_entry_variance

from .indicator import Placement, RefineError, place_beams
from .pointing import aim, check_reach

log = logging.getLogger(__name__)

CSV_FILE = "refine.csv"
JSON_FILE = "refine.json"
PNG_FILE = "refine.png"


def refine(isf_dir: str | os.PathLike, out: str | os.PathLike, beams: int, capture: str | os.PathLike | None = None,
           min_spacing: float | None = None, force: bool = False) -> dict:
    """Decide up to ``beams`` new beams for the scan of ``isf_dir`` and write ``out``.

    capture: the capture directory the ISF was built from (its manifest's plan and
    pan-tilt limits give the angles and the reach); None: pixels only.
    Raises RefineError (bad value, no spots, a target out of reach) or ISFError before
    anything is written.
    """
    if beams < 1:
        raise RefineError(f"--beams must be at least 1, got {beams}")
    isf_dir = Path(isf_dir)
    isf = load_isf(isf_dir, mmap=True)
    if isf.samples is None:
        raise ISFError(f"{isf_dir / SAMPLES_FILE}: no such file; refine needs the spots of the ISF's beams "
                       "(build it with 'ilt build-isf')")
    plan = _plan_angles(Path(capture), isf) if capture is not None else None
    covered = _covered(isf)
    folds = _folds(isf_dir, isf)
    variance = read_entry_variance(isf_dir, isf.m)
    placement = place_beams(isf.T, isf.samples, beams, min_spacing=min_spacing, covered=covered, folds=folds,
                            variance=variance)
    angles = None
    if plan is not None:
        units, kept_angles, ptu = plan
        angles = aim(placement.targets, isf.samples, kept_angles)
        check_reach(angles, placement.targets, units, ptu, str(Path(capture) / MANIFEST))
    if len(placement.targets) < beams:
        log.info("%d of the %d beams asked for have room and gain (no edge left wider than 2 x --min-spacing "
                 "inside the cells, 3 x on a line of spots)", len(placement.targets), beams)
    summary = {"m": isf.m, "asked": beams, "beams": len(placement.targets), "fold_pairs": placement.fold_pairs,
               "folds": len(folds), "noise": variance is not None,
               "indicator": {"before": placement.before, "after": placement.after},
               "units": plan[0] if plan is not None else None}
    with staged_directory(out, force=force) as tmp:
        _write_csv(tmp / CSV_FILE, placement, angles)
        write_json(tmp / JSON_FILE, {**summary, "residual_median": float(np.median(placement.residual)),
                                     "residual_max": float(placement.residual.max())})
        _write_png(tmp / PNG_FILE, isf, placement)
        if (isf_dir / CELLS_FILE).is_file():
            shutil.copyfile(isf_dir / CELLS_FILE, tmp / CELLS_FILE)
        # what the decision read: T, the spots, and T_var.npy and the build's manifest (its folds) when used
        inputs = _input_hashes(isf_dir, (T_FILE, SAMPLES_FILE, *((T_VAR_FILE,) if variance is not None else ())))
        if folds:
            inputs[str(isf_dir / MANIFEST)] = fingerprint_file(isf_dir / MANIFEST)
        if capture is not None:
            inputs[str(Path(capture) / MANIFEST)] = fingerprint_file(Path(capture) / MANIFEST)
        write_manifest(tmp, "refine", {"beams": beams, "min_spacing": min_spacing}, inputs=inputs,
                       extra=summary)
    return {"output": str(out), **summary}


def _input_hashes(directory: Path, names) -> dict[str, str]:
    """Path -> hash of each file, as the stage's manifest recorded it (read when it has none)."""
    try:
        recorded = read_manifest(directory).get("outputs", {})
    except StageError:
        recorded = {}
    return {str(directory / n): recorded.get(n) or fingerprint_file(directory / n) for n in names}


def _plan_angles(capture: Path, isf) -> tuple[str, np.ndarray, dict | None]:
    """(units, (m, 2) angles of the ISF's beams, the unit's facts) from the capture manifest."""
    try:
        manifest = read_manifest(capture)
    except StageError as exc:
        raise RefineError(str(exc)) from None
    plan = manifest.get("plan")
    if manifest.get("stage") != "capture" or not isinstance(plan, dict) or "targets" not in plan:
        raise RefineError(f"{capture / MANIFEST}: not a capture's manifest with a plan")
    targets = np.asarray(plan["targets"], dtype=np.float64)
    rows = np.arange(isf.m) if isf.beams is None else isf.beams
    if targets.ndim != 2 or targets.shape[1] != 2 or rows.max() >= len(targets):
        raise RefineError(f"{capture / MANIFEST}: its plan has {len(targets)} beams; the ISF uses beam "
                          f"{int(rows.max())}: not the capture this ISF was built from")
    return str(plan.get("units", "degrees")), targets[rows], manifest.get("ptu")


def _folds(isf_dir: Path, isf) -> list[tuple[np.ndarray, np.ndarray]]:
    """The build's fold lines (:func:`ilt.isf.fold_transfer.recorded_lines`) as full-resolution
    (start, end) pairs; none when the build had no fold transfer. Every line, whether or not
    the light across it was corrected: on the 4x box lattice the 48-beam builds of two draws
    in three find the vertical crease alone, and leave it uncorrected; read, refine +48 went
    0.0867 / 0.0854 -> 0.0798 / 0.0808 (docs/refine.md, "The 4x box lattice")."""
    return [(isf.mapping.to_full(start), isf.mapping.to_full(end)) for start, end, _ in recorded_lines(isf_dir)]


def _covered(isf):
    """``covered(points)``: inside some cell (cell sampling) or inside the frame (point)."""
    if isf.frame_shape is None:
        return None
    height, width = isf.frame_shape

    def covered(points: np.ndarray) -> np.ndarray:
        px = np.floor(isf.mapping.to_grid(np.asarray(points, dtype=np.float64)) + 0.5).astype(np.int64)
        inside = (px[:, 0] >= 0) & (px[:, 1] >= 0) & (px[:, 0] < width) & (px[:, 1] < height)
        if isf.cells is None:
            return inside
        out = np.zeros(len(px), dtype=bool)
        out[inside] = isf.cells[px[inside, 1], px[inside, 0]] >= 0
        return out

    return covered


def _write_csv(path: Path, placement: Placement, angles: np.ndarray | None) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["x", "y", *(["pan", "tilt"] if angles is not None else []), "gain"])
        for n, ((x, y), gain) in enumerate(zip(placement.targets, placement.gain)):
            w.writerow([repr(float(x)), repr(float(y)),
                        *([repr(float(a)) for a in angles[n]] if angles is not None else []), repr(float(gain))])


def _write_png(path: Path, isf, placement: Placement) -> None:
    """The frame grid: each cell shaded by its beam's prediction residual, the spots
    (white), the targets (green rings, the best larger)."""
    import cv2

    if isf.frame_shape is None:
        return
    height, width = isf.frame_shape
    worst = placement.residual
    shade = np.zeros((height, width))
    if isf.cells is not None:
        inside = isf.cells >= 0
        shade[inside] = worst[isf.cells[inside]] / max(float(worst.max()), 1e-300)
    image = cv2.applyColorMap(np.uint8(np.clip(shade, 0, 1) * 255), cv2.COLORMAP_MAGMA)
    scale = max(1, int(np.ceil(480 / max(height, 1))), int(np.ceil(240 / max(width, 1))))
    scale = min(scale, 8)
    image = cv2.resize(image, (width * scale, height * scale), interpolation=cv2.INTER_NEAREST)
    for x, y in isf.mapping.to_grid(isf.samples):
        cv2.circle(image, (round(float(x) * scale), round(float(y) * scale)), max(1, scale // 2), (255, 255, 255), -1)
    for n, (x, y) in enumerate(isf.mapping.to_grid(placement.targets) if len(placement.targets) else []):
        cv2.circle(image, (round(float(x) * scale), round(float(y) * scale)), 2 * scale if n < 3 else scale + 1,
                   (80, 220, 80), 1)
    if not cv2.imwrite(str(path), image):
        raise RefineError(f"{path}: cannot write the PNG")
