"""The light cells send across a fold, spread over the cell, against each spot's alone (issue 21).

    python benchmarks/bench_fold_transfer.py [--scenes m,box] [--electrons 2e4] --scratch DIR
                                             [--fold-transfer flatland|all] [--timing-beams 432]

On bench_refine.py's pre-rendered 2x lattices (the M's 96 beams, the box's 3 x 12 x 12) the
uniform scans from the base to the whole lattice, the in-between ones the lattice beams
nearest a uniform scan (uneven: on the M their spots fall 4 px from a fold on one side and
12 on the other), are run through ``ilt centroids``, ``ilt build-isf`` (which writes
``fold_transfer.npz``, :mod:`ilt.isf.fold_transfer`) and ``ilt decompose`` twice: as built,
and with ``--no-fold-transfer`` (each cell's light sent from its spot, as before). It prints
the mean of the full-resolution bounces 1-3 of the three photos against the renderer's over
the base's pixels, the fold lines found and their entries, and flags every figure that
rises from one scan to the next. ``--timing-beams``: build-isf of that scan with and without
the fold transfer, median of 3 (the share it adds to the build).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import bench_refine as refine_bench  # noqa: E402  (the lattices, scans and errors of the refine benchmark)


def sweep(root: Path, scene: str, electrons: float, mode: str) -> None:
    base_m = {"m": 48, "box": 108}[scene]
    lattice_m, px, spot = refine_bench.lattice_parameters(scene, base_m)
    case = root / f"{scene}-{lattice_m}"
    if not (case / "hdr").exists():
        refine_bench.run("simulate", scene, "--frames", "--beams", lattice_m, "--px-per-beam", px, "--spot", spot,
                         "-o", case, "--force")
    hdr = refine_bench.coverage_bench.noisy_frames(case, np.random.default_rng(0), electrons)
    uniform = refine_bench.uniform_sets(scene, lattice_m)
    mask = None
    rows = []
    for count, beams in sorted(uniform.items()):
        where = refine_bench.scan(case, hdr, f"uniform-{count}-{mode}", beams, ("--fold-transfer", mode))
        if not (where / "dec-off").exists():
            refine_bench.run("decompose", "--isf", where / "isf",
                             *[case / "photos" / f"{p}.exr" for p in refine_bench.PHOTOS], "-o", where / "dec-off",
                             "--no-cache", "--no-fold-transfer")
        if mask is None:
            mask = refine_bench.covered(where, cells_only=True)
        on, off = refine_bench.errors(case, where, mask), refine_bench.errors(case, where, mask, "dec-off")
        record = json.loads((where / "isf" / "manifest.json").read_text()).get("fold_transfer", {})
        rows.append((count, off, on, record))
    noise = f"{electrons:g} e-" if electrons > 0 else "noise-free"
    print(f"\n### {scene}: lattice {lattice_m}, {noise}, --fold-transfer {mode}, over the {int(mask.sum())} pixels "
          "of the base scan\n")
    print("| m | spot's light alone | spread over the cell | ratio | fold lines (entries) |")
    print("|---|---|---|---|---|")
    for count, off, on, record in rows:
        lines = ", ".join(f"{line['entries']}" for line in record.get("lines", []))
        print(f"| {count} | {off.mean():.4f} | {on.mean():.4f} | {on.mean() / off.mean():.2f} | {lines} |")
    for label, k in (("spot's light alone", 1), ("spread over the cell", 2)):
        rises = [f"{refine_bench.PHOTOS[p]} b{b + 1} {a[0]} -> {c[0]}: {a[k][p, b]:.4f} -> {c[k][p, b]:.4f}"
                 for a, c in zip(rows, rows[1:]) for p in range(3) for b in range(3) if c[k][p, b] > a[k][p, b]]
        means = [r[k].mean() for r in rows]
        print(f"\n{label}: means rise {sum(b > a for a, b in zip(means, means[1:]))} times; "
              f"{len(rises)} photo-bounce rises" + (f" ({'; '.join(rises[:6])}{' ...' if len(rises) > 6 else ''})"
                                                   if rises else ""))


def timing(root: Path, beams: int, electrons: float, mode: str) -> None:
    case = next(root.glob("box-*"), None) or next(root.glob("m-*"))
    where = case / f"scans-hdr{'-noisy' if electrons > 0 else ''}" / f"uniform-{beams}-{mode}"
    if not (where / "spots").exists():
        print(f"\nno scan of {beams} beams under {case}: run the sweep first")
        return
    seconds = {}
    for label, extra in (("with", ("--fold-transfer", mode)), ("without", ("--fold-transfer", "off"))):
        runs = []
        for _ in range(3):
            started = time.perf_counter()
            subprocess.run([sys.executable, "-m", "ilt", "-q", "build-isf", str(where / "hdr"), str(where / "spots"),
                            "-o", str(root / "timing-isf"), "--force", *extra], check=True)
            runs.append(time.perf_counter() - started)
        seconds[label] = statistics.median(runs)
    print(f"\nbuild-isf of {where.name} ({case.name}): {seconds['with']:.2f} s with the fold transfer, "
          f"{seconds['without']:.2f} s without (median of 3): {seconds['with'] / seconds['without']:.2f}x")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="m,box")
    ap.add_argument("--electrons", type=float, default=2e4, help="0: noise-free frames")
    ap.add_argument("--scratch", type=Path, required=True)
    ap.add_argument("--fold-transfer", default="all", choices=["flatland", "all"],
                    help="build-isf's --fold-transfer (the box's folds are 3D: 'all' corrects them)")
    ap.add_argument("--timing-beams", type=int, default=0)
    args = ap.parse_args()
    args.scratch.mkdir(parents=True, exist_ok=True)
    for scene in filter(None, args.scenes.split(",")):
        sweep(args.scratch, scene, args.electrons, args.fold_transfer)
    if args.timing_beams:
        timing(args.scratch, args.timing_beams, args.electrons, args.fold_transfer)


if __name__ == "__main__":
    main()
