"""What cells that end at the scene's folds would be worth: an oracle (issue 21).

    python benchmarks/bench_fold_cells.py --scratch DIR [--scenes m,textured,occluded]
                                          [--electrons 2e4] [--frames hdr-noisy]

Reads the scans ``benchmarks/noisy_sweep.py --scratch DIR`` made (run it first, with the
same ``--electrons``). Cells are the spots' Voronoi regions, which know nothing of the
surface: where a spot lands near a fold its cell holds pixels of both facets, whose light
differs (on the M the flashlight lights one facet and not the next), and a cell's plane
cannot follow it. This rebuilds each scan's ISF with the renderer's own facets (the
*oracle*: ``ilt simulate``'s scene, rendered again, says which facet each frame column
shows): every pixel whose spot is on another facet than the pixel goes to the nearest spot
on its own facet, the rest of the cells as ilt makes them. Then it decomposes the photos
as ``ilt decompose`` does by default and prints the mean error of bounces 1-3 of the three
photos over the sparsest scan's pixels, ilt's cells against the oracle's: the ceiling of
any fold test on the frames. Flatland scenes only (the frame's columns are the surface's).

And a fold test on the frames (not in ilt; a measured design, :func:`valley_columns`): at a
concave fold, the light of the beams farther than one spot spacing from a column has a
V-shaped minimum (a facet lights the facet it faces the less, the nearer the fold: the
light leaves it at grazing angles). Columns where that far light is ``VALLEY_Z`` sigma
below the mean of the ``VALLEY_PX`` columns either side (the frames' noise model) cut the
facets, and the cells end there as the oracle's do.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))   # the sibling benchmarks
import noisy_sweep   # noqa: E402
import bench_refine as refine_bench   # noqa: E402


def column_facets(scene: str, m: int, px: float, spot: float) -> np.ndarray:
    """(W,) int: the facet each frame column shows most (-1: none), from the renderer."""
    from ilt.sim.render import render_scene

    rendered = render_scene(scene, beams=m, px_per_beam=px, spot=spot)
    patch = rendered.sub_patch                       # (W, S) fine patch of each sub-pixel ray
    facets = np.where(patch >= 0, rendered.geometry.facet[np.maximum(patch, 0)], -1)
    out = np.full(patch.shape[0], -1)
    for c in range(patch.shape[0]):
        seen = facets[c][facets[c] >= 0]
        if seen.size:
            out[c] = np.bincount(seen).argmax()
    return out


def facet_cells(facet: np.ndarray):
    """A drop-in for :func:`ilt.isf.cells.voronoi_cells` whose cells end at the facets' edges."""
    from ilt.isf.cells import voronoi_cells

    def cells(centroids, frame_shape, lit=None, max_radius=None, threads=1):
        labels = voronoi_cells(centroids, frame_shape, lit, max_radius, threads)
        columns = np.clip(np.floor(centroids[:, 0] + 0.5).astype(int), 0, facet.size - 1)
        spot_facet = facet[columns]
        rows, cols = np.nonzero(labels >= 0)
        wrong = np.flatnonzero((spot_facet[labels[rows, cols]] != facet[cols]) & (facet[cols] >= 0))
        for k in wrong:
            r, c = rows[k], cols[k]
            mine = np.flatnonzero(spot_facet == facet[c])
            if mine.size:
                labels[r, c] = mine[np.argmin(np.hypot(centroids[mine, 0] - c, centroids[mine, 1] - r))]
        return labels
    return cells


#: the fold test's half window (px) and its threshold (sigma): the two concave folds of the
#: noisy M stand at 4.9-8.7 sigma at 96-192 beams, the largest of the rest at 3.3-4.0
VALLEY_PX, VALLEY_Z = 32, 4.5


def valley_columns(scan: Path, half: int = VALLEY_PX, z_min: float = VALLEY_Z) -> list[int]:
    """The columns where the light of the beams more than a spot spacing away has a
    significant V-shaped minimum (the module docstring), from the scan's frames, spots and
    the frames' noise model (its ISF's noise.json); none without one."""
    import csv

    from ilt.io.exr import read_exr
    from ilt.isf.noise import FrameNoise, read_noise

    record = read_noise(scan / "isf")
    if record is None:
        return []
    noise = FrameNoise.from_record(record)
    with open(scan / "spots" / "spots.csv") as f:
        rows = list(csv.DictReader(f))
    xs = np.array([float(r["x"]) for r in rows])
    frames = [read_exr(scan / "hdr" / f"beam-{int(r['beam']):05d}.exr")[0][..., 0].astype(np.float64) for r in rows]
    height = frames[0].shape[0]
    columns = np.stack([f.mean(axis=0) for f in frames])                  # (m, W): a column is one surface point
    spacing = float(np.median(np.diff(np.sort(xs))))
    far = np.abs(xs[:, None] - np.arange(columns.shape[1])[None, :]) > spacing
    light = (columns * far).sum(axis=0)
    sigma = np.sqrt((noise.pixel_variance(np.maximum(columns, 0.0)) * far).sum(axis=0) / height)
    total = np.cumsum(np.pad(light, (1, 0)))
    x = np.arange(half, light.size - half)
    sides = ((total[x] - total[x - half]) + (total[x + half + 1] - total[x + 1])) / (2 * half)
    z = (sides - light[x]) / (sigma[x] * np.sqrt(1 + 0.5 / half))
    cuts: list[int] = []
    for i in np.argsort(-z):
        if z[i] < z_min:
            break
        if all(abs(x[i] - c) > 2 * half for c in cuts):
            cuts.append(int(x[i]))
    return sorted(cuts)


def oracle_scan(case: Path, scan: Path, facet: np.ndarray, name: str = "facets") -> Path:
    """The scan rebuilt with facet cells (its own spots), decomposed: the directory holding dec/."""
    import ilt.isf.build as build

    out = scan.parent / f"{scan.name}-{name}"
    if (out / "dec").exists():
        return out
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    plain = build.voronoi_cells
    build.voronoi_cells = facet_cells(facet)
    try:
        build.build_isf(scan / "hdr", scan / "spots", out / "isf", workers=1)
    finally:
        build.voronoi_cells = plain
    refine_bench.run("decompose", "--isf", out / "isf", *[case / "photos" / f"{p}.exr" for p in refine_bench.PHOTOS],
                     "-o", out / "dec", "--no-cache")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    noisy_sweep.scan_arguments(ap, "m,textured,occluded")
    args = ap.parse_args()
    frames = noisy_sweep.frames_name(args)
    root = args.scratch / f"e{args.electrons:g}"
    print("| scene | beams | ilt's cells | cells ending at the facets (oracle) | change | the fold test's cuts | "
          "cells ending at them | change |")
    print("|---|---|---|---|---|---|---|---|")
    for scene in args.scenes.split(","):
        m, px, spot = noisy_sweep.lattice(scene)
        case = root / f"{scene}-{m}"
        facet = column_facets(scene, m, px, spot)
        scans = sorted((case / f"scans-{frames}").glob("sweep-*"), key=lambda p: int(p.name.split("-")[1]))
        scans = [s for s in scans if len(s.name.split("-")) == 2]
        mask = refine_bench.covered(scans[0], cells_only=True)
        for scan in scans:
            ours = refine_bench.errors(case, scan, mask).mean()
            theirs = refine_bench.errors(case, oracle_scan(case, scan, facet), mask).mean()
            cuts = valley_columns(scan)
            tested = ours
            if cuts:
                found = np.searchsorted(np.array(cuts) + 0.5, np.arange(facet.size))
                tested = refine_bench.errors(case, oracle_scan(case, scan, found, "valleys"), mask).mean()
            print(f"| {scene} | {scan.name.split('-')[1]} | {ours:.4f} | {theirs:.4f} | {theirs / ours - 1:+.0%} | "
                  f"{', '.join(map(str, cuts)) or 'none'} | {tested:.4f} | {tested / ours - 1:+.0%} |", flush=True)


if __name__ == "__main__":
    main()
