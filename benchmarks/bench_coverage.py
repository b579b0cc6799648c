"""Coverage and full-resolution errors against beam density, on noise-free and noisy frames (issue 21).

    python benchmarks/bench_coverage.py [--scenes m,box] [--beams 48,96,192] [--electrons 2e4]
                                        [--max-cell-radius R] [--keep DIR]

For each scene and beam count, ``ilt simulate SCENE --frames`` renders the beam frames
(noise-free, exact interreflections); a noisy copy of them is made with photon and read
noise at realistic counts: one camera and exposure per scene, ``--electrons``
photo-electrons for the brightest spot pixel of the sparsest scan (the same electrons per
unit of radiance at every m), then Poisson(signal) + N(0, read^2) electrons (read 3 e-)
and back to the frame's units. Both go through ``ilt centroids`` and
``ilt build-isf`` as a user runs them, and the coverage is the fraction of the frame's
pixels inside some cell (cells.exr >= 0), with the beams build-isf kept.

Then ``ilt decompose`` of the (noise-free) room photo with each ISF, and the relative L2
errors of its full-resolution bounce images 1-3 against the exact ones, over the pixels it
covers (coverage.exr > 0). The photo is left noise-free so that the errors are T's.

A denser scan must cover at least what a sparser one did, and be no less accurate: the
flags say whether coverage fell, or an error rose, from the previous m. Prints a markdown
table; timings are not the point here.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

READ_NOISE_E = 3.0


def frame_parameters(scene: str, m: int) -> tuple[float, float]:
    """(px_per_beam, spot): as benchmarks/fullres_accuracy.py sizes its cases."""
    spec = importlib.util.spec_from_file_location("fullres_accuracy", Path(__file__).with_name("fullres_accuracy.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.frame_parameters(scene, m)


def run(*args):
    subprocess.run([sys.executable, "-m", "ilt", "-q", *map(str, args)], check=True)


def peak_of(hdr: Path) -> float:
    from ilt.io.exr import read_exr

    return max(float(read_exr(f)[0].max()) for f in sorted(hdr.glob("beam-*.exr")))


def noisy_copy(src: Path, dst: Path, gain: float, rng, read_noise: float = READ_NOISE_E,
               samples: float = 0.0, direct=None, hits: float = 0.0) -> None:
    """dst/hdr: every beam frame of src/hdr with photon and read noise, ``gain``
    photo-electrons per frame unit (see the module doc); ``read_noise`` 0: photon noise
    alone, which never reads below zero (as a path tracer's Monte Carlo noise).

    ``samples`` > 0: a path tracer's Monte Carlo noise instead (``gain`` and ``read_noise``
    unused): each pixel is its value times Gamma(samples, 1 / samples), a mean of
    ``samples`` independent exponential path weights. Its relative noise, 1 / sqrt(samples),
    is the same at every level (photon noise's falls as the light grows), it never reads
    below zero, and its upper tail is long. ``direct`` (with ``samples``): a function of
    the beam's index giving its frame's direct light (the laser spot), which is then left
    noise-free and only the interreflected rest noisy, as a path tracer that samples the
    light source at every hit (next-event estimation) renders a spotlight's spot.

    ``hits`` in (0, 1) (with ``samples``): sparse path hits instead of Gamma weights. Each of
    the ``samples`` paths of a pixel finds the light with chance ``hits`` and then carries
    1 / (samples hits) of the pixel's value: the pixel reads its value times
    Binomial(samples, hits) / (samples hits). That is a path tracer's noise where the light
    is small (a laser's spot lighting the room is found by a bounce only now and then): a
    pixel reads exactly zero with chance (1 - hits)^samples and otherwise a few whole hits,
    relative noise sqrt((1 - hits) / (samples hits))."""
    from ilt.io.exr import read_exr, write_exr

    dst.mkdir(parents=True)
    frames = sorted(src.glob("beam-*.exr"))
    for j, f in enumerate(frames):
        image, attributes = read_exr(f)
        x = np.maximum(image.astype(np.float64), 0)
        if samples > 0:
            weights = (rng.binomial(int(samples), hits, image.shape) / (samples * hits) if hits > 0
                       else rng.gamma(samples, 1.0 / samples, image.shape))
            spot = 0.0 if direct is None else np.minimum(direct(j).reshape(image.shape), x)
            out = spot + (x - spot) * weights
        else:
            out = (rng.poisson(x * gain) + (rng.normal(0, read_noise, image.shape) if read_noise else 0.0)) / gain
        keep = {k: v for k, v in attributes.items() if k.startswith("ilt:")}
        write_exr(dst / f.name, out.astype(np.float32), ["Y"], keep)
    for other in src.iterdir():
        if not other.name.startswith("beam-") and other.is_file():
            shutil.copy2(other, dst / other.name)


def noisy_frames(case: Path, rng, electrons: float, read_noise: float = READ_NOISE_E,
                 samples: float = 0.0, exact_direct: bool = False, hits: float = 0.0) -> Path:
    """The frames of ``case/hdr`` a benchmark runs on, made once: with ``samples`` > 0 the
    Monte Carlo copy ``hdr-mcS``; else with ``electrons`` > 0 the photon and read noise copy
    ``hdr-noisy`` (``hdr-noisy-readR`` at another read noise), ``electrons`` at the brightest
    frame's peak; else ``hdr`` itself (:func:`noisy_copy`). ``exact_direct`` (with
    ``samples``): ``hdr-mcS-direct``, the spots noise-free (the scene rendered again from
    ``case``'s manifest for them)."""
    hdr = case / "hdr"
    if samples > 0:
        out = case / f"hdr-mc{samples:g}{f'-hits{hits:g}' if hits > 0 else ''}{'-direct' if exact_direct else ''}"
        if not out.exists():
            direct = None
            if exact_direct:
                from ilt.sim.render import render_scene

                p = json.loads((case / "manifest.json").read_text())["parameters"]
                scene = render_scene(p["scene"], p["beams"], p["albedo"], p["seed"], p["spot"], p["fine"],
                                     p["px_per_beam"])
                direct = scene.spot_image
            noisy_copy(hdr, out, 1.0, rng, samples=samples, direct=direct, hits=hits)
        return out
    if electrons > 0:
        out = case / ("hdr-noisy" if read_noise == READ_NOISE_E else f"hdr-noisy-read{read_noise:g}")
        if not out.exists():
            noisy_copy(hdr, out, electrons / peak_of(hdr), rng, read_noise)
        return out
    return hdr


def coverage(isf: Path) -> tuple[float, int]:
    from ilt.io.exr import read_exr

    labels, _ = read_exr(isf / "cells.exr")
    m = json.loads((isf / "manifest.json").read_text())["m"]
    return float(np.mean(labels[..., 0] >= 0)), int(m)


def bounce_errors(case: Path, dec: Path) -> list[float]:
    """||est - truth|| / ||truth|| of bounces 1-3 of the room photo over its covered pixels."""
    from ilt.io.exr import read_exr

    truth = np.load(case / "truth" / "photos" / "room-bounces.npy").astype(np.float64)
    covered = read_exr(dec / "room" / "coverage.exr")[0][..., 0] > 0
    out = []
    for n in (1, 2, 3):
        est = read_exr(dec / "room" / f"bounce-{n}.exr")[0][..., 0].astype(np.float64)
        out.append(float(np.linalg.norm((est - truth[n - 1])[covered]) / np.linalg.norm(truth[n - 1][covered])))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="m,box")
    ap.add_argument("--beams", default="48,96,192")
    ap.add_argument("--electrons", type=float, default=2e4, help="photo-electrons at the brightest spot pixel")
    ap.add_argument("--max-cell-radius", type=float, default=None)
    ap.add_argument("--keep", type=Path, default=None, help="keep the renders in this directory")
    args = ap.parse_args()
    root = args.keep or Path(tempfile.mkdtemp(prefix="ilt-coverage-"))
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    extra = ["--max-cell-radius", args.max_cell_radius] if args.max_cell_radius else []
    try:
        print("| scene | m asked | frames | m kept | coverage | room b1 | b2 | b3 | coverage fell? | error rose? |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        for scene in args.scenes.split(","):
            previous, gain = {}, None
            for m in map(int, args.beams.split(",")):
                case = root / f"{scene}-{m}"
                if not (case / "hdr").exists():
                    px, spot = frame_parameters(scene, m)
                    run("simulate", scene, "--frames", "--beams", m, "--px-per-beam", px, "--spot", spot,
                        "-o", case, "--force")
                if gain is None:  # one camera and exposure for the whole sweep of a scene
                    gain = args.electrons / peak_of(case / "hdr")
                if not (case / "hdr-noisy").exists():
                    noisy_copy(case / "hdr", case / "hdr-noisy", gain, rng)
                for kind, hdr in (("noise-free", case / "hdr"), ("noisy", case / "hdr-noisy")):
                    spots, isf, dec = case / f"spots-{kind}", case / f"isf-{kind}", case / f"dec-{kind}"
                    run("centroids", hdr, "-o", spots, "--force")
                    run("build-isf", hdr, spots, "-o", isf, "--force", *extra)
                    run("decompose", "--isf", isf, case / "photos" / "room.exr", "-o", dec, "--no-cache", "--force")
                    cov, kept = coverage(isf)
                    errors = bounce_errors(case, dec)
                    before = previous.get(kind)
                    fell = "**yes**" if before and cov < before[0] - 1e-9 else "no"
                    rose = [f"b{n + 1}" for n in range(3) if before and errors[n] > before[1][n] * 1.0001]
                    previous[kind] = (cov, errors)
                    print(f"| {scene} | {m} | {kind} | {kept} | {cov:.4f} | "
                          + " | ".join(f"{e:.4f}" for e in errors)
                          + f" | {fell} | {'**' + ', '.join(rose) + '**' if rose else 'no'} |", flush=True)
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
