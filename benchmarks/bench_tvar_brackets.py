"""Is T_var.npy right on merged RAW brackets? Two captures of one scene, on the same cells.

    python benchmarks/bench_tvar_brackets.py --scratch DIR [--config configs/sim.toml] [--seeds 0,1]

The emulated rig (``ilt run CONFIG``: the simulated camera writes real DNG brackets, ``ilt
merge`` fuses them, ``ilt build-isf`` fits the frames' noise and writes ``T_var.npy``) is run
twice with the camera's noise seeded differently: the same scene, the same beams, two draws
of photon and read noise through the whole bracket and merge. Each capture's merged frames
are summed over the FIRST capture's cells (build-isf's own cells move with the noise, which
would confound the comparison), and the two raw matrices' difference is held against the
first build's ``T_var`` (relative to its unit columns): for a calibrated variance
``z^2 = (R1 - R0)^2 / (2 Var)`` is a chi-square of one degree of freedom, median 0.455.
Printed separately for the spots' own cells (the diagonal, whose pixels are far above the
frames' fitted knots and merged from the bracket's shortest exposures) and the rest.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
CHI2_MEDIAN = 0.4549


def capture(config: Path, seed: int, scratch: Path) -> Path:
    """The workspace of ``ilt run`` on ``config`` with the camera's seed ``seed`` (kept: reused)."""
    ws = scratch / f"seed{seed}"
    if not (ws / "isf" / "T_var.npy").exists():
        text = re.sub(r"(?m)^seed\s*=.*$", f"seed = {seed}", config.read_text())
        if f"seed = {seed}" not in text:
            raise SystemExit(f"{config}: no 'seed =' line in [camera] to change")
        scratch.mkdir(parents=True, exist_ok=True)
        rig = scratch / f"rig-seed{seed}.toml"
        rig.write_text(text)
        subprocess.run([sys.executable, "-m", "ilt", "-q", "run", str(rig), "-w", str(ws)], check=True,
                       stdout=subprocess.DEVNULL)
    return ws


def raw_sums(ws: Path, cells: np.ndarray, m: int) -> np.ndarray:
    """(m, beams) each merged beam frame's light summed over ``cells``."""
    from ilt.io.exr import read_exr
    from ilt.isf.cells import integrate

    frames = sorted((ws / "hdr").glob("beam-*.exr"))
    return np.stack([integrate(read_exr(f)[0][..., 0].astype(np.float64), cells, m) for f in frames], axis=1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scratch", type=Path, required=True)
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "sim.toml")
    ap.add_argument("--seeds", default="0,1")
    args = ap.parse_args()
    from ilt.io.exr import read_exr

    a, b = (int(s) for s in args.seeds.split(","))
    first, second = capture(args.config, a, args.scratch), capture(args.config, b, args.scratch)
    T = np.load(first / "isf" / "T.npy")
    variance = np.load(first / "isf" / "T_var.npy")
    m = T.shape[0]
    cells = read_exr(first / "isf" / "cells.exr")[0][..., 0].astype(np.int64)
    R0, R1 = raw_sums(first, cells, m), raw_sums(second, cells, m)
    if R0.shape != (m, m) or R1.shape != (m, m):
        raise SystemExit(f"expected {m} x {m} sums, got {R0.shape} and {R1.shape} (beams dropped by build-isf?)")
    norms = np.linalg.norm(R0, axis=0)                   # T_var is relative to T's unit columns
    z2 = (R1 - R0) ** 2 / (2 * variance * norms[None, :] ** 2)
    own = np.eye(m, dtype=bool)
    diag_sigma = np.sqrt(np.mean((np.diag(R1) / np.diag(R0) - 1) ** 2) / 2)
    said = np.median(np.sqrt(np.diag(variance)) / np.diag(T))
    print(f"{args.config.name}: {m} beams, seeds {a} and {b}, on the first capture's cells")
    print(f"  other cells: median z^2 {np.median(z2[~own]):.3f} (calibrated: {CHI2_MEDIAN}), "
          f"{int((~own).sum())} entries")
    print(f"  spots' own cells: median z^2 {np.median(z2[own]):.3f}; relative sigma measured {diag_sigma:.4%}, "
          f"T_var says {said:.4%} ({diag_sigma / said:.2f}x)")


if __name__ == "__main__":
    sys.exit(main())
