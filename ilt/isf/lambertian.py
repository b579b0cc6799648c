"""``isf/lambertian.json`` and ``isf/lambertian.png``: is this T a Lambertian scene's?

build-isf (and ``ilt simulate``) run the reciprocity test of
:mod:`ilt.transport.reciprocity` on T, its entries' noise (``T_var.npy``) and its
samples (pairs of neighbouring samples left out) and write the verdict here; ``ilt
decompose`` reads it and refuses a "not lambertian" T unless told to accept it.

``lambertian.json``: ``verdict`` ("lambertian", "not lambertian", "undecided"),
``reason`` (one sentence with the figures), ``reciprocity_residual``, ``noise_floor``,
``excess``, ``tolerance`` (log units), ``pairs``, ``beams``, ``worst_beams`` ([{beam
(row of T), plan_beam, rms}], worst first). ``lambertian.png``: each beam's rms
asymmetry, shaded over its cell (or on the plan's layout without cells).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ilt.io.manifest import write_json
from ilt.io.preview import save_png
from ilt.transport.reciprocity import Reciprocity, near_pairs, reciprocity_check

from .layout import vector_to_image

LAMBERTIAN_FILE = "lambertian.json"
LAMBERTIAN_PNG = "lambertian.png"

log = logging.getLogger(__name__)


def check_lambertian(directory: str | Path, T: np.ndarray, samples: np.ndarray | None, T_var: np.ndarray | None,
                     beams: np.ndarray | None, layout: tuple[int, int], cells: np.ndarray | None = None) -> dict:
    """Run the reciprocity test and write ``lambertian.json`` and ``lambertian.png`` into ``directory``.

    T (m, m), T_var (m, m) or None, samples (m, 2) full-frame pixels or None (no pair
    left out), beams (m,) plan beam of each row or None, layout the plan's (rows, cols),
    cells (H, W) row of T per pixel or None. Returns the JSON-ready dict (also for the manifest).
    """
    directory = Path(directory)
    exclude = None if samples is None else near_pairs(samples)
    result = reciprocity_check(T, T_var, exclude=exclude)
    fields = result.as_dict()
    plan = np.arange(len(T)) if beams is None else np.asarray(beams)
    for row in fields["worst_beams"]:
        row["plan_beam"] = int(plan[row["beam"]])
    write_json(directory / LAMBERTIAN_FILE, fields)
    _write_png(directory / LAMBERTIAN_PNG, result, plan, layout, cells)
    if result.verdict == "not lambertian":
        log.warning("reciprocity: not lambertian: %s", result.reason)
    else:
        log.info("reciprocity: %s (%s)", result.verdict, result.reason)
    return fields


def read_lambertian(directory: str | Path) -> dict | None:
    """The ``lambertian.json`` of an ISF directory, or None when it has none (an older ISF)."""
    path = Path(directory) / LAMBERTIAN_FILE
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise ValueError(f"{path}: not a readable reciprocity verdict ({error})") from error


def _write_png(path: Path, result: Reciprocity, plan: np.ndarray, layout, cells) -> None:
    per_beam = np.nan_to_num(result.per_beam, nan=0.0)
    if cells is not None:
        image = np.where(cells >= 0, per_beam[np.maximum(cells, 0)], 0.0)
    else:
        image = vector_to_image(per_beam, layout, positions=plan.astype(np.int64))
    save_png(path, image, log=False,
             title=f"reciprocity: rms asymmetry per beam (log units), {result.verdict}")
