"""ilt's full-resolution bounces against the per-pixel kernel method K = (F - D) T^-1 (issue 21).

    python benchmarks/bench_kernel.py --scratch DIR [--scenes m,occluded,textured,box]
                                      [--electrons 2e4] [--frames hdr-noisy] [--block 8] [--json PATH]

Reads the scans ``benchmarks/noisy_sweep.py --scratch DIR`` made (run it first, with the
same ``--electrons``): for each scan, its beam frames, cells and decomposed photos.

The reference keeps every pixel of every beam frame: ``G = F - D`` (P pixels x m beams),
with ``D_j`` beam j's frame on its own cell (all of a beam's light in its own cell is
taken as direct, as ilt's ``T1`` is the diagonal of T), ``T`` the frames' cell integrals,
and the photo's bounces by the paper's recursion on them: ``x_n = T^-1 r_n``,
``r_(n+1) = r_n - T1 x_n``, ``Phi_n = G x_n``, bounce 1 = photo - Phi_0, bounce n =
Phi_(n-2) - Phi_(n-1). It is what ilt's fine operator approximates with a plane per
cell, at the cost of storing the whole scan (P x m); no regularisation (the T's of these
scenes are diagonally dominant).

Errors: relative L2 of ``--block`` x ``--block`` block sums of each bounce (1-3) of every
photo against the renderer's, over the pixels the sparsest scan covers, for ilt's images
and the reference's; the ratio ilt / reference per photo and bounce.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))   # the sibling benchmarks
import noisy_sweep   # noqa: E402
import bench_refine as refine_bench   # noqa: E402

PHOTOS = refine_bench.PHOTOS


def block_error(estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray, block: int) -> float:
    """Relative L2 of the ``block`` x ``block`` sums of ``estimate - truth`` over ``mask``."""
    h, w = truth.shape
    hb, wb = -(-h // block) * block, -(-w // block) * block

    def sums(image):
        padded = np.zeros((hb, wb))
        padded[:h, :w] = np.where(mask, image, 0.0)
        return padded.reshape(hb // block, block, wb // block, block).sum(axis=(1, 3))

    return float(np.linalg.norm(sums(estimate - truth)) / np.linalg.norm(sums(truth)))


def reference_bounces(frames: np.ndarray, labels: np.ndarray, photo: np.ndarray, bounces: int = 3) -> np.ndarray:
    """(bounces, H, W) the kernel method's bounces of ``photo`` (module docstring);
    frames (m, H, W), labels (H, W) the cells (-1 outside)."""
    m = frames.shape[0]
    inside = labels.ravel() >= 0
    label = labels.ravel()[inside]
    F = frames.reshape(m, -1)[:, inside].T.astype(np.float64)            # (n, m)
    T = np.stack([np.bincount(label, F[:, j], m) for j in range(m)], axis=1)
    F[np.arange(label.size), label] = 0.0                                # D: each beam's own cell
    t1 = np.diag(T).copy()
    r = np.bincount(label, photo.ravel()[inside].astype(np.float64), m)
    phis = []
    for _ in range(bounces):
        x = np.linalg.solve(T, r)
        phis.append(F @ x)
        r = r - t1 * x
    out = np.zeros((bounces,) + photo.shape)
    flat = out.reshape(bounces, -1)
    flat[0, inside] = photo.ravel()[inside] - phis[0]
    for n in range(1, bounces):
        flat[n, inside] = phis[n - 1] - phis[n]
    return out


def measure(case: Path, frames_name: str, block: int, photos: str = "photos") -> dict:
    from ilt.io.exr import read_exr

    scans = sorted((case / f"scans-{frames_name}").glob("sweep-*"), key=lambda p: int(p.name.split("-")[1]))
    scans = [s for s in scans if s.name.split("-")[1].isdigit() and len(s.name.split("-")) == 2]
    mask = refine_bench.covered(scans[0], cells_only=True)
    dec = noisy_sweep.dec_name(photos)      # noisy_sweep.py --photo-samples / --photo-snr
    rows = {}
    for scan in scans:
        manifest = json.loads((scan / "isf" / "manifest.json").read_text())
        files = sorted((scan / "hdr").glob("beam-*.exr"))
        frames = np.stack([read_exr(files[b])[0][..., 0] for b in manifest["beams"]])
        labels = read_exr(scan / "isf" / "cells.exr")[0][..., 0].astype(np.int64)
        ours, ref = np.empty((len(PHOTOS), 3)), np.empty((len(PHOTOS), 3))
        for p, photo in enumerate(PHOTOS):
            image = read_exr(case / photos / f"{photo}.exr")[0][..., 0].astype(np.float64)
            truth = refine_bench.truth_bounces(case, photo)
            reference = reference_bounces(frames, labels, image)
            for n in range(3):
                ours[p, n] = block_error(refine_bench.bounce_image(scan, photo, n + 1, dec), truth[n], mask, block)
                ref[p, n] = block_error(reference[n], truth[n], mask, block)
        rows[len(manifest["beams"])] = {"ilt": ours.tolist(), "reference": ref.tolist()}
        print(f"  {case.name} m = {len(manifest['beams'])}: worst ratio {np.max(ours / ref):.2f}", flush=True)
    return rows


def table(scene: str, rows: dict) -> str:
    head = "| m | " + " | ".join(f"{p} b{n}" for p in PHOTOS for n in (1, 2, 3)) + " | worst ratio |"
    lines = [f"### {scene}: ilt / reference (8 x 8 blocks)", "", head, "|" + "---|" * 11]
    for m, r in sorted(rows.items(), key=lambda kv: int(kv[0])):
        ours, ref = np.array(r["ilt"]), np.array(r["reference"])
        cells = [f"{a:.3f} / {b:.3f}" for a, b in zip(ours.ravel(), ref.ravel())]
        lines.append(f"| {m} | " + " | ".join(cells) + f" | {np.max(ours / ref):.2f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    noisy_sweep.scan_arguments(ap, "m,occluded,textured,box")
    ap.add_argument("--block", type=int, default=8)
    ap.add_argument("--photos", default="photos",
                    help="the photos' directory in each scene's case: photos-mcS or photos-snrX, the noisy photos "
                         "noisy_sweep.py --photo-samples / --photo-snr decomposed (into each scan's dec-NAME); "
                         "the truth stays exact")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    frames = noisy_sweep.frames_name(args)
    root = args.scratch / f"e{args.electrons:g}"
    results = {}
    for scene in args.scenes.split(","):
        m = noisy_sweep.lattice(scene)[0]
        results[scene] = measure(root / f"{scene}-{m}", frames, args.block, args.photos)
        print(table(scene, results[scene]) + "\n", flush=True)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
