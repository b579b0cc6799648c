"""Full-resolution accuracy against beam density on noisy frames, one rig, one set of pixels (issue 21).

    python benchmarks/noisy_sweep.py [--scenes m,occluded,textured,box] [--electrons 2e4]
                                     --scratch DIR [--plot PNG] [--json PATH]
    python benchmarks/noisy_sweep.py --replot JSON --plot PNG

A user who wants better bounce images scans more beams of the same scene with the same
camera. So each scene is rendered once as a dense beam lattice (``ilt simulate SCENE
--frames``: flatland m = 384 at 8 px per beam, as benchmarks/fullres_accuracy.py sizes
m = 384; the box 3 x 12 x 12 = 432 at 10 px), photon and read noise are added to every
beam frame (``--electrons`` photo-electrons at the brightest spot pixel, 3 e- read noise,
as benchmarks/bench_coverage.py makes them), and the scans are nested subsets of the
lattice's frames, every k-th beam (flatland m = 48, 96, 192, 384; the box every 3rd, 2nd
and each row and column of a face: 48, 108, 432), run through ``ilt centroids``,
``ilt build-isf`` and ``ilt decompose`` as a user runs them (benchmarks/bench_refine.py's
``scan``). The photos (room, flashlight, projector) are the simulator's, noise-free.

Errors: relative L2 of the full-resolution bounces 1-3 of each photo against the exact
ones over the pixels inside the sparsest scan's cells (so every scan is judged on the same
pixels; a pixel a denser scan leaves uncovered, in no cell and not on their rim, counts as
all error), and the share of those pixels each scan covers (cells and rim). The rig's time of each scan is m x the per-beam time of
``ilt capture --estimate configs/rig-example.toml`` (a tethered DSLR, its 11-exposure
bracket and a dark frame a beam). The table flags every photo and bounce whose error
rises from one density to the next; ``--plot`` draws error against beams and hours.
"""

from __future__ import annotations

import argparse
import itertools
import json
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
PHOTOS = ("room", "flashlight", "projector")
FLATLAND_LATTICE, FLATLAND_STRIDES = 384, (8, 4, 2, 1)
BOX_SIDE, BOX_STRIDES = 12, (3, 2, 1)


sys.path.insert(0, str(Path(__file__).resolve().parent))   # the sibling benchmarks
import bench_refine as refine_bench

coverage_bench = refine_bench.coverage_bench


def seconds_per_beam() -> float:
    from ilt.capture.config import load_config
    from ilt.capture.estimate import estimate

    e = estimate(load_config(ROOT / "configs" / "rig-example.toml"))
    return e.seconds / e.beams


def lattice(scene: str) -> tuple[int, float, float]:
    """(beams, px_per_beam, spot in beam spacings) of the scene's lattice: the frame and the
    spot's size in pixels are those of the 384-beam (box: 12 x 12 a face) lattice whatever
    the lattice (one camera, one laser: ``--dense`` puts twice the beams in the same frame)."""
    if scene == "box":
        m = 3 * BOX_SIDE * BOX_SIDE
        px = 10.0 * 12 / BOX_SIDE
        return m, px, 0.05 * 16.0 / px
    px, spot = coverage_bench.frame_parameters(scene, 384)
    scale = 384 / FLATLAND_LATTICE
    return FLATLAND_LATTICE, px * scale, spot / scale


def dense() -> None:
    """``--dense``: lattices of 768 beams (flatland at half the pixels per beam, every 16th
    ... every beam: 48 to 768; the box 16 x 16 a face, every 4th, 2nd and each row and
    column: 48, 192, 768), in the same frames as the default's."""
    global FLATLAND_LATTICE, FLATLAND_STRIDES, BOX_SIDE, BOX_STRIDES
    FLATLAND_LATTICE, FLATLAND_STRIDES = 768, (16, 8, 4, 2, 1)
    BOX_SIDE, BOX_STRIDES = 16, (4, 2, 1)


def nested_sets(scene: str, m: int) -> dict[int, list[int]]:
    """Beam count -> the lattice beams of every k-th beam (flatland), or every k-th row
    and column of each face (the box, beams face by face in scanline order)."""
    if scene != "box":
        return {len(range(0, m, k)): list(range(0, m, k)) for k in FLATLAND_STRIDES}
    side = BOX_SIDE
    out = {}
    for k in BOX_STRIDES:
        keep = range(0, side, k)
        beams = [f * side * side + r * side + c for f in range(3) for r in keep for c in keep]
        out[len(beams)] = beams
    return out


def sweep(root: Path, scene: str, electrons: float, rng, spot_px: float | None = None,
          keep_covered: bool = False, read_noise: float = coverage_bench.READ_NOISE_E,
          samples: float = 0.0, exact_direct: bool = False, hits: float = 0.0,
          photo_samples: float = 0.0, photo_snr: float = 0.0) -> dict:
    m, px, spot = lattice(scene)
    if spot_px is not None:   # the laser's spot, whatever the scan: sigma in full-resolution pixels
        spot = spot_px / px
    case = root / (f"{scene}-{m}" if spot_px is None else f"{scene}-{m}-spot{spot_px:g}")
    if not (case / "hdr").exists():
        # the occluded M's 768 beams at the renderer's 16 fine patches a spacing need 35 GiB: 8 there
        fine = ("--fine", 8) if scene == "occluded" and m > 384 else ()
        refine_bench.run("simulate", scene, "--frames", "--beams", m, "--px-per-beam", px, "--spot", spot,
                         *fine, "-o", case, "--force")
    hdr = coverage_bench.noisy_frames(case, rng, electrons, read_noise, samples, exact_direct, hits)
    where, earlier = {}, None
    for count, beams in sorted(nested_sets(scene, m).items()):
        # --keep-covered: each scan built with the sparser scan's coverage (ilt build-isf --keep-covered)
        if keep_covered and earlier is not None:
            where[count] = refine_bench.scan(case, hdr, f"sweep-{count}-kept", beams,
                                             ("--keep-covered", earlier / "isf"))
        else:
            where[count] = refine_bench.scan(case, hdr, f"sweep-{count}", beams)
        earlier = where[count]
    mask = refine_bench.covered(where[min(where)], cells_only=True)
    dec = "dec"
    if photo_samples > 0 or photo_snr > 0:   # every scan decomposes the same noisy photos, judged against the exact bounces
        photos = noisy_photos(case, photo_samples, photo_snr)
        dec = dec_name(photos.name)
        for w in where.values():
            if not (w / dec).exists():
                refine_bench.run("decompose", "--isf", w / "isf", *[photos / f"{p}.exr" for p in PHOTOS],
                                 "-o", w / dec, "--no-cache")
    rows = {}
    for count, w in where.items():
        manifest = json.loads((w / "isf" / "manifest.json").read_text())
        rows[count] = {"errors": refine_bench.errors(case, w, mask, dec).tolist(),
                       "covered": float(refine_bench.covered(w)[mask].mean()),
                       "frame_coverage": float(manifest["coverage"]["fraction"]),
                       "m_kept": int(manifest["m"])}
    return {"scene": scene, "lattice": m, "px_per_beam": px, "spot": spot, "electrons": electrons,
            "read_noise": read_noise, "samples": samples, "exact_direct": exact_direct, "hits": hits,
            "photo_samples": photo_samples, "photo_snr": photo_snr,
            "keep_covered": keep_covered,
            "base_pixels": int(mask.sum()), "scans": rows}


def dec_name(photos: str) -> str:
    """A scan's decompose directory for the case's photos directory ``photos``: ``dec`` for the
    exact ``photos``, ``dec-NAME`` for the noisy ones (:func:`noisy_photos`)."""
    return "dec" if photos == "photos" else f"dec-{photos}"


def noisy_photos(case: Path, samples: float = 0.0, snr: float = 0.0) -> Path:
    """``case / photos-mcS``: the scene's photos with a path tracer's noise of ``samples``
    samples (each pixel times Gamma(S, 1/S)); or ``case / photos-snrX``: with photon noise
    of signal-to-noise ratio ``snr`` at each photo's median (Poisson counts, X^2 photons
    there). Drawn once: every scan sees the same photos."""
    from ilt.io.exr import read_exr, write_exr

    out = case / (f"photos-mc{samples:g}" if samples > 0 else f"photos-snr{snr:g}")
    if not out.exists():
        rng = np.random.default_rng(1)
        tmp = out.with_name(out.name + ".tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        for photo in PHOTOS:
            image, attributes = read_exr(case / "photos" / f"{photo}.exr")
            x = np.maximum(image.astype(np.float64), 0)
            if samples > 0:
                noisy = x * rng.gamma(samples, 1.0 / samples, image.shape)
            else:
                gain = snr**2 / np.median(x[x > 0])
                noisy = rng.poisson(x * gain) / gain
            write_exr(tmp / f"{photo}.exr", noisy.astype(np.float32), attributes.get("channels"),
                      {k: v for k, v in attributes.items() if k.startswith("ilt:")})
        tmp.rename(out)
    return out


def scan_arguments(ap: argparse.ArgumentParser, scenes: str) -> None:
    """The options of a benchmark that reads this sweep's scans (``--scratch`` and so on)."""
    ap.add_argument("--scratch", type=Path, required=True, help="noisy_sweep.py's --scratch")
    ap.add_argument("--scenes", default=scenes)
    ap.add_argument("--electrons", type=float, default=2e4)
    ap.add_argument("--frames", default=None, help="the frames' directory name (default: hdr-noisy, or hdr at 0 e-)")


def frames_name(args) -> str:
    """The frames' directory of :func:`scan_arguments`' options."""
    return args.frames or ("hdr" if args.electrons == 0 else "hdr-noisy")


def rises(result: dict) -> list[str]:
    """Every photo and bounce whose error rises from one density to the next, and any fall in coverage."""
    counts = sorted(result["scans"])
    out = []
    for a, b in itertools.pairwise(counts):
        ea, eb = np.array(result["scans"][a]["errors"]), np.array(result["scans"][b]["errors"])
        for p, photo in enumerate(PHOTOS):
            for n in range(3):
                if eb[p, n] > ea[p, n]:
                    out.append(f"{photo} b{n + 1} {a} -> {b}: {ea[p, n]:.4f} -> {eb[p, n]:.4f}")
        if result["scans"][b]["covered"] < result["scans"][a]["covered"]:
            out.append(f"coverage {a} -> {b}: {result['scans'][a]['covered']:.4f} -> {result['scans'][b]['covered']:.4f}")
    return out


def table(result: dict, per_beam: float) -> str:
    kept = ", each built keeping the sparser scan's coverage" if result.get("keep_covered") else ""
    noise = f"{result['electrons']:g} e-" + ("" if result.get("read_noise", 3.0) else ", no read noise")
    if result.get("samples"):
        noise = f"Monte Carlo noise of {result['samples']:g} samples (no photon or read noise)"
        if result.get("hits"):
            noise = noise[:-1] + f"; sparse hits, each path finding the light with chance {result['hits']:g})"
        if result.get("exact_direct"):
            noise = noise[:-1] + "; the spots' direct light noise-free)"
    if result.get("photo_samples"):
        noise += f", photos with {result['photo_samples']:g} samples' noise"
    elif result.get("photo_snr"):
        noise += f", photos with photon noise of SNR {result['photo_snr']:g} at their median"
    lines = [(f"### {result['scene']}: lattice {result['lattice']} ({result['px_per_beam']:g} px per beam), "
              f"{noise}{kept}, over the {result['base_pixels']} pixels of the sparsest scan"), "",
             ("| m | m kept | rig hours | covered | " + " | ".join(f"{p} b{n}" for p in PHOTOS for n in (1, 2, 3))
              + " | mean |"), "|---|---|---|---|" + "---|" * 10]
    for count, row in sorted(result["scans"].items()):
        e = np.array(row["errors"])
        lines.append(f"| {count} | {row['m_kept']} | {count * per_beam / 3600:.2f} | {row['covered']:.4f} | "
                     + " | ".join(f"{v:.4f}" for v in e.ravel()) + f" | {e.mean():.4f} |")
    bad = rises(result)
    lines += ["", "rises: " + ("none" if not bad else "; ".join(bad))]
    return "\n".join(lines)


def plot(results: list[dict], per_beam: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    fig, axes = plt.subplots(1, len(results), figsize=(4.2 * len(results), 3.6), squeeze=False)
    for ax, result in zip(axes[0], results):
        counts = sorted(result["scans"])
        errors = np.array([result["scans"][c]["errors"] for c in counts])       # (scans, photos, 3)
        for n, style in zip(range(3), ("-o", "-s", "-^")):
            ax.loglog(counts, errors[:, :, n].mean(axis=1), style, label=f"bounce {n + 1} (mean of photos)")
        ax.set_xlabel("beams")
        photos = (f", photos {result['photo_samples']:g} samples" if result.get("photo_samples") else
                  f", photos SNR {result['photo_snr']:g}" if result.get("photo_snr") else "")
        ax.set_title(f"{result['scene']} ({result['samples']:g} samples{photos})" if result.get("samples")
                     else f"{result['scene']} ({result['electrons']:g} e-{photos})")
        ax.grid(True, which="both", alpha=0.3)
        ax.set_xticks(counts, [str(c) for c in counts])
        ax.xaxis.set_minor_formatter(NullFormatter())
        top = ax.secondary_xaxis("top", functions=(lambda m: m * per_beam / 3600, lambda h: h * 3600 / per_beam))
        top.set_xticks([c * per_beam / 3600 for c in counts], [f"{c * per_beam / 3600:.2f}" for c in counts])
        top.xaxis.set_minor_formatter(NullFormatter())
        top.set_xlabel("rig hours (configs/rig-example.toml's estimate)")
    axes[0][0].set_ylabel("relative L2 error over the sparsest scan's pixels")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="m,occluded,textured,box")
    ap.add_argument("--electrons", type=float, default=2e4, help="0: noise-free frames")
    ap.add_argument("--spot-px", type=float, default=None,
                    help="the laser spot's sigma in full-resolution pixels (default: 0.6 px flatland, 0.8 px "
                         "the box: no flank reaches the next cell even at the lattice; 2.4 puts the lattice "
                         "3.3 sigmas apart, where each spot lights its neighbours' cells)")
    ap.add_argument("--read-noise", type=float, default=coverage_bench.READ_NOISE_E,
                    help="read noise in e- (0: photon noise alone, which never reads below zero, as a path "
                         "tracer's Monte Carlo noise: ilt then measures the noise only where it is plain)")
    ap.add_argument("--samples", type=float, default=0.0,
                    help="a path tracer's Monte Carlo noise instead of photon and read noise: each pixel times "
                         "Gamma(S, 1/S), relative noise 1/sqrt(S) at every level (bench_coverage.noisy_copy)")
    ap.add_argument("--exact-direct", action="store_true",
                    help="with --samples: the laser spots noise-free, only the interreflected light noisy (a path "
                         "tracer that samples a spotlight at every hit; frames hdr-mcS-direct)")
    ap.add_argument("--hits", type=float, default=0.0,
                    help="with --samples: sparse path hits instead of Gamma weights: each path finds the light "
                         "with this chance, the pixel reads its value times Binomial(S, H) / (S H), exactly 0 "
                         "with chance (1 - H)^S (frames hdr-mcS-hitsH)")
    ap.add_argument("--photo-samples", type=float, default=0.0,
                    help="decompose photos with a path tracer's noise of this many samples (each pixel times "
                         "Gamma(S, 1/S), drawn once a scene; photos-mcS) instead of the exact ones; the truth "
                         "stays exact")
    ap.add_argument("--photo-snr", type=float, default=0.0,
                    help="decompose photos with photon noise of this signal-to-noise ratio at each photo's median "
                         "(Poisson; photos-snrX) instead of the exact ones; the truth stays exact")
    ap.add_argument("--keep-covered", action="store_true",
                    help="build each scan with 'ilt build-isf --keep-covered' the next sparser scan's ISF (a lab "
                         "that rescans denser, or ilt run's refine passes)")
    ap.add_argument("--dense", action="store_true",
                    help="lattices of 768 beams in the same frames (scans of 48 ... 768 beams)")
    ap.add_argument("--scratch", type=Path, help="renders and scans (kept: a rerun reuses them)")
    ap.add_argument("--plot", type=Path)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--replot", type=Path, help="only draw --plot from this --json of an earlier run")
    args = ap.parse_args()
    if args.replot:
        plot([{**r, "scans": {int(k): v for k, v in r["scans"].items()}} for r in json.loads(args.replot.read_text())],
             seconds_per_beam(), args.plot)
        return
    if args.scratch is None:
        ap.error("--scratch is required (unless --replot)")
    if args.dense:
        dense()
    per_beam = seconds_per_beam()
    print(f"rig time: {per_beam:.1f} s a beam (ilt capture --estimate configs/rig-example.toml)")
    rng = np.random.default_rng(0)
    results = []
    for scene in filter(None, args.scenes.split(",")):
        results.append(sweep(args.scratch / f"e{args.electrons:g}", scene, args.electrons, rng, args.spot_px,
                             args.keep_covered, args.read_noise, args.samples, args.exact_direct, args.hits,
                             args.photo_samples, args.photo_snr))
        print("\n" + table(results[-1], per_beam), flush=True)
    if args.plot:
        plot(results, per_beam, args.plot)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    sys.exit(main())
