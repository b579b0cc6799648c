"""Fold cells where the cells' boundaries already lie on the folds: the far light's own dips (issue 21).

    python benchmarks/bench_fold_depth.py [--beams 16,32] [--electrons 2e4] --scratch DIR

The M rendered exactly (ilt.sim.render, as tests/decompose/test_spill_density.py's sparse
scan: 32 rows, the laser's spot 0.1 of a 32 px spacing, 8 fine patches a spacing) at 16 and
32 beams, 512 px wide: its folds lie midway between two spots, on the Voronoi cells'
boundaries, so cells that end at the folds can only lose. Each scan is built three ways
from the same frames (noise-free, and with photon and read noise of ``--electrons`` at the
brightest pixel, benchmarks/bench_coverage.py's): Voronoi cells (``fold_cells=False``);
fold cells judged by the noise test alone (``FOLD_DEPTH`` off, as before the depth test);
and fold cells as built today (a barrier's valley ``FOLD_DEPTH`` deep or more). It prints
the mean of the full-resolution bounces 1-3 of the flashlight and room photos against the
renderer's over the pixels every build covers, the pixels the fold cells moved and the
lines the depth test dropped (ilt.isf.folds.valley_depth).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import shutil
import sys
from pathlib import Path

import numpy as np

KINDS = ("flashlight", "room")


def _coverage_bench():
    spec = importlib.util.spec_from_file_location("bench_coverage", Path(__file__).with_name("bench_coverage.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def render(root: Path, beams: int, electrons: float):
    """The scan's frames (``hdr``, and ``hdr-noisy``), photos and exact bounces."""
    from ilt.capture.camera import sim_sensor
    from ilt.evaluate.end_to_end import GREEN_GRID, green_grid
    from ilt.io.exr import write_exr
    from ilt.io.manifest import write_manifest
    from ilt.sim.render import render_scene

    px = 512 // beams
    scene = render_scene("m", beams=beams, px_per_beam=px, rows=32, spot=0.1 * 32 / px, fine=8)
    sensor = sim_sensor(scene)
    truth = {k: green_grid(scene.photo(k, n_bounces=3)[1], sensor) for k in KINDS}
    hdr = root / "hdr"
    if not hdr.exists():
        tmp = root / "hdr.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        for j in range(beams):
            write_exr(tmp / f"beam-{j:05d}.exr", green_grid(scene.beam_frame(j), sensor).astype(np.float32),
                      attributes=GREEN_GRID.attributes())
        write_manifest(tmp, "simulate", {"scene": "m"}, extra={"m": beams, "layout": [1, beams],
                                                              "pixel_mapping": GREEN_GRID.as_dict()})
        tmp.rename(hdr)
    photos = []
    for k in KINDS:
        photos.append(root / f"{k}.exr")
        if not photos[-1].exists():
            write_exr(photos[-1], green_grid(scene.photo(k, n_bounces=1)[0], sensor).astype(np.float32),
                      attributes=GREEN_GRID.attributes())
    frames = {"noise-free": hdr}
    if electrons > 0:
        noisy = root / "hdr-noisy"
        if not noisy.exists():
            cb = _coverage_bench()
            cb.noisy_copy(hdr, root / "hdr-noisy.tmp", electrons / cb.peak_of(hdr), np.random.default_rng(0))
            (root / "hdr-noisy.tmp").rename(noisy)
        frames[f"{electrons:g} e-"] = noisy
    return frames, photos, truth


def build(frames: Path, photos: list[Path], out: Path, fold_cells: bool, depth: bool) -> Path:
    import ilt.isf.folds as folds
    from ilt.decompose.stage import decompose
    from ilt.isf.build import build_isf
    from ilt.isf.directory import load_isf
    from ilt.spots.stage import run_centroids

    shutil.rmtree(out, ignore_errors=True)
    run_centroids(frames, out / "spots", workers=1)
    kept = folds.FOLD_DEPTH
    folds.FOLD_DEPTH = kept if depth else -np.inf
    try:
        build_isf(frames, out / "spots", out / "isf", workers=1, fold_cells=fold_cells)
    finally:
        folds.FOLD_DEPTH = kept
    decompose(load_isf(out / "isf"), photos, out / "dec", n_bounces=6)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--beams", default="16,32")
    ap.add_argument("--electrons", type=float, default=2e4, help="photon and read noise at the brightest pixel (0: none)")
    ap.add_argument("--scratch", type=Path, required=True)
    args = ap.parse_args()
    from ilt.io.exr import read_exr

    ways = {"Voronoi": (False, True), "noise test alone": (True, False), "with the depth test": (True, True)}
    print("| beams | frames | Voronoi cells | fold cells, noise test alone (moved px) | fold cells, depth test "
          "(moved px, lines dropped) |")
    print("|---|---|---|---|---|")
    for beams in [int(b) for b in args.beams.split(",")]:
        root = args.scratch / f"m-{beams}"
        frames, photos, truth = render(root, beams, args.electrons)
        for name, hdr in frames.items():
            where = {way: build(hdr, photos, root / f"{hdr.name}-{i}", *flags) for i, (way, flags) in enumerate(ways.items())}
            mask = np.logical_and.reduce([read_exr(w / "dec" / "room" / "coverage.exr")[0][..., 0] > 0
                                          for w in where.values()])
            cells = []
            for way, w in where.items():
                errors = [np.linalg.norm((read_exr(w / "dec" / k / f"bounce-{n + 1}.exr")[0][..., 0] - truth[k][n])[mask])
                          / np.linalg.norm(truth[k][n][mask]) for k in KINDS for n in range(3)]
                folds = json.loads((w / "isf" / "manifest.json").read_text()).get("folds", {})
                note = ""
                if folds.get("applied"):
                    note = f" ({folds['moved_pixels']}" + (f", {folds.get('shallow_lines', 0)})" if ways[way][1] else ")")
                cells.append(f"{np.mean(errors):.4f}{note}")
            print(f"| {beams} | {name} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    sys.exit(main())
