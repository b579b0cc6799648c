"""Does a denser scan do better over many draws of a path tracer's noise? (issue 21)

    python benchmarks/noisy_sweep.py --samples 4 --scratch DIR [--dense]   # first: renders and scans
    python benchmarks/bench_diagonal_draws.py --scratch DIR --samples 4 [--scenes m,textured] [--draws 20] [--dense]
                                              [--json PATH] [--plot PNG]

With a path tracer's Monte Carlo noise of few samples, T's diagonal (each spot's own cell,
a few bright pixels) is by far its noisiest part: 20% a beam at 4 samples, while the
off-diagonal cells are 2-3%. On the noisy sweep's frames, replacing the diagonal with its
noise-free value takes the sample-level errors of the textured M's 384-beam scan from
0.0095/0.0283/0.0344 to 0.0037/0.0134/0.0085 (the room's bounces 1-3), replacing the
off-diagonal entries changes nothing that matters. That noise is the same share of the
light at every density, and one draw of it decides whether a given scan comes out above
or below its sparser one: noisy_sweep renders one draw.

This redraws the diagonal's noise ``--draws`` times on each scan of the sweep (each spot's
own cell summed again over its noise-free pixels times Gamma(samples, 1/samples), as
noisy_sweep makes them; the off-diagonal entries and the fine operator as built from
the rendered frames) and decomposes the three photos at full resolution with T's
diagonal as drawn and with decompose's correction (the diagonal raised by its variance
over itself, :func:`ilt.transport.regularise.diagonal_raise`, the variance as build-isf
measures it: the frames' share of the light times the drawn pixels' squares over 1 +
share), and with the noise-free diagonal (the floor). Errors as noisy_sweep's (relative
L2 of bounces 1-3 over the sparsest scan's cells), dense solver, no regularisation and no
spill (neither changed these scans' figures by more than 1e-4). It prints each scan's mean
error over the draws and its spread, the share of draws the correction lowered, which
figures rise from one density to the next on average, and the share of draws (the k-th
draw of one density against the k-th of the next) in which at least one figure rises.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))   # the sibling benchmarks
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import bench_refine as refine_bench  # noqa: E402
import noisy_sweep  # noqa: E402

PHOTOS = refine_bench.PHOTOS


class Scan:
    """One scan of the sweep: its ISF, the noise-free pixels of each spot's own cell, the
    noisy cell sums as rendered, the photos and the fine operator."""

    def __init__(self, case: Path, where: Path):
        from ilt.decompose.stage import read_photo
        from ilt.io.exr import read_exr
        from ilt.io.manifest import fingerprint_array
        from ilt.isf.cells import integrate
        from ilt.isf.directory import load_isf
        from ilt.isf.fine import load_fine
        from ilt.isf.noise import FrameNoise, light_share_variance, read_noise

        self.isf = isf = load_isf(where / "isf")
        m = isf.m
        cells = np.asarray(isf.cells).astype(np.int64)
        beams = sorted(json.loads((where / "beams.json").read_text()))
        self.raw = np.empty((m, m))
        self.own, clean_diagonal = [], np.empty(m)
        rows = range(m) if isf.beams is None else np.asarray(isf.beams).tolist()
        for row, n in enumerate(rows):   # the scan's frame of each row of T
            noisy = read_exr(where / "hdr" / f"beam-{n:05d}.exr")[0][..., 0].astype(np.float64)
            clean = read_exr(case / "hdr" / f"beam-{beams[n]:05d}.exr")[0][..., 0].astype(np.float64)
            self.raw[:, row] = integrate(noisy, cells, m)
            self.own.append(np.maximum(clean[cells == row], 0.0))
            clean_diagonal[row] = self.own[-1].sum()
        self.clean_diagonal = clean_diagonal
        self.share = light_share_variance(FrameNoise.from_record(read_noise(where / "isf")))
        self.photos = {p: read_photo(case / "photos" / f"{p}.exr", isf) for p in PHOTOS}
        self.fine, why = load_fine(isf, fingerprint_array(np.asarray(isf.T)))
        if self.fine is None:
            raise SystemExit(f"{where / 'isf'}: no fine operator ({why})")

    def drawn(self, rng, samples: float) -> tuple[np.ndarray, np.ndarray]:
        """(unit-column T, its entries' variance, diagonal only) with the diagonal redrawn."""
        raw = self.raw.copy()
        variance = np.zeros_like(raw)
        for j, pixels in enumerate(self.own):
            x = pixels * rng.gamma(samples, 1.0 / samples, pixels.size)
            raw[j, j] = x.sum()
            variance[j, j] = self.share * np.sum(x * x) / (1.0 + self.share)
        norms = np.linalg.norm(raw, axis=0)
        return raw / norms, variance / norms[None, :] ** 2

    def errors(self, T: np.ndarray, mask: np.ndarray, truth: dict) -> np.ndarray:
        """(photos x 3,) full-resolution errors of bounces 1-3 over ``mask``."""
        from ilt.decompose.fullres import full_resolution, photo_noise_models
        from ilt.decompose.stage import load_operator
        from ilt.transport.operators import bounce_images

        op, _ = load_operator(np.ascontiguousarray(T), None, "dense", None, regularise=False)
        out = []
        for p in PHOTOS:
            photo = self.photos[p]
            dec = bounce_images(op, photo.values, n_bounces=4)
            images = full_resolution(self.fine, photo.image, dec, op.t1, None, None, report={},
                                     photo_noise=photo_noise_models)
            for n in range(3):
                e, t = images[f"bounce-{n + 1}"][..., 0].astype(np.float64), truth[p][n]
                out.append(np.linalg.norm((e - t)[mask]) / np.linalg.norm(t[mask]))
        return np.array(out)


def bench_scene(root: Path, scene: str, frames: str, samples: float, draws: int, rng) -> dict:
    from ilt.transport.regularise import diagonal_raise, raise_diagonal

    m, _, _ = noisy_sweep.lattice(scene)
    case = root / f"{scene}-{m}"
    scans = {count: case / f"scans-{frames}" / f"sweep-{count}" for count in noisy_sweep.nested_sets(scene, m)}
    missing = [str(w) for w in scans.values() if not (w / "dec").exists()]
    if missing:
        raise SystemExit(f"run noisy_sweep.py --samples {samples:g} first: no {missing[0]}")
    mask = refine_bench.covered(scans[min(scans)], cells_only=True)
    truth = {p: refine_bench.truth_bounces(case, p) for p in PHOTOS}
    out = {}
    for count, where in sorted(scans.items()):
        scan = Scan(case, where)
        T_floor = scan.raw.copy()
        T_floor[np.diag_indices(scan.isf.m)] = scan.clean_diagonal
        floor = scan.errors(T_floor / np.linalg.norm(T_floor, axis=0), mask, truth)
        noisy, corrected = [], []
        for _ in range(draws):
            T, variance = scan.drawn(rng, samples)
            noisy.append(scan.errors(T, mask, truth))
            raise_by, _ = diagonal_raise(T, variance)
            corrected.append(scan.errors(T if raise_by is None else raise_diagonal(T, raise_by), mask, truth))
        out[count] = {"floor": floor, "noisy": np.array(noisy), "corrected": np.array(corrected)}
        print(f"  {scene} {count}: done", file=sys.stderr, flush=True)
    return out


def report(scene: str, samples: float, result: dict) -> str:
    names = [f"{p} b{n + 1}" for p in PHOTOS for n in range(3)]
    lines = [f"### {scene}: the diagonal's noise of {samples:g} samples redrawn "
             f"{len(next(iter(result.values()))['noisy'])} times", "",
             "| m | noise-free diagonal | as drawn (sd over draws) | corrected (sd) | draws the correction lowered |",
             "|---|---|---|---|---|"]
    for count, r in sorted(result.items()):
        a, c = r["noisy"].mean(1), r["corrected"].mean(1)
        lines.append(f"| {count} | {r['floor'].mean():.4f} | {a.mean():.4f} ({a.std():.4f}) | {c.mean():.4f} "
                     f"({c.std():.4f}) | {np.mean(c < a):.2f} |")
    lines.append("")
    for a, b in itertools.pairwise(sorted(result)):
        for kind in ("noisy", "corrected"):
            ea, eb = result[a][kind], result[b][kind]
            mean_rises = [names[i] for i in np.flatnonzero(eb.mean(0) > ea.mean(0))]
            lines.append(f"- {a} -> {b}, {'as drawn' if kind == 'noisy' else 'corrected'}: figures rising on "
                         f"average: {', '.join(mean_rises) or 'none'}; draws with some figure rising: "
                         f"{np.mean((eb > ea).any(1)):.2f}")
    return "\n".join(lines)


def plot(results: dict, samples: float, path: Path) -> None:
    """Each scene's mean error (bounces 1-3 of the three photos) against beams: every draw
    as drawn and corrected (thin lines), their means, and the noise-free diagonal's."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    fig, axes = plt.subplots(1, len(results), figsize=(4.2 * len(results), 3.6), squeeze=False)
    for ax, (scene, result) in zip(axes[0], results.items()):
        counts = sorted(result)
        for kind, colour, label in (("noisy", "tab:red", "as drawn"), ("corrected", "tab:blue", "corrected")):
            draws = np.array([result[c][kind].mean(axis=1) for c in counts])        # (scans, draws)
            ax.loglog(counts, draws, color=colour, alpha=0.15, lw=0.8)
            ax.loglog(counts, draws.mean(axis=1), "-o", color=colour, label=f"{label} (mean of draws)")
        ax.loglog(counts, [result[c]["floor"].mean() for c in counts], "--", color="k", label="noise-free diagonal")
        ax.set_xlabel("beams")
        ax.set_title(f"{scene} ({samples:g} samples, {len(result[counts[0]]['noisy'])} draws)")
        ax.grid(True, which="both", alpha=0.3)
        ax.set_xticks(counts, [str(c) for c in counts])
        ax.xaxis.set_minor_formatter(NullFormatter())
    axes[0][0].set_ylabel("mean relative L2 error, bounces 1-3")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    noisy_sweep.scan_arguments(ap, "m,textured")
    ap.add_argument("--samples", type=float, default=4.0, help="the sweep's --samples (its frames hdr-mcS)")
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--dense", action="store_true", help="the sweep's --dense lattices")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--json", type=Path, help="every draw's nine errors, as drawn and corrected, per scene and scan")
    ap.add_argument("--plot", type=Path, help="error against beams, every draw and their means (PNG)")
    args = ap.parse_args()
    if args.dense:
        noisy_sweep.dense()
    frames = args.frames or f"hdr-mc{args.samples:g}"
    rng = np.random.default_rng(args.seed)
    results = {}
    for scene in filter(None, args.scenes.split(",")):
        results[scene] = bench_scene(args.scratch / f"e{args.electrons:g}", scene, frames, args.samples, args.draws,
                                     rng)
        print("\n" + report(scene, args.samples, results[scene]), flush=True)
    if args.json:
        args.json.write_text(json.dumps({"samples": args.samples, "draws": args.draws, "scenes": {
            scene: {str(c): {k: np.asarray(v).tolist() for k, v in r.items()} for c, r in result.items()}
            for scene, result in results.items()}}))
    if args.plot:
        plot(results, args.samples, args.plot)


if __name__ == "__main__":
    sys.exit(main())
