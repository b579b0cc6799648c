"""Benchmark and accuracy study of the spots -> ISF stages.

    python benchmarks/bench_isf.py throughput [--quick] [--beams M] [--width W --height H]
    python benchmarks/bench_isf.py sampling [--quick] [--densities 32,64,128]
    python benchmarks/bench_isf.py noise [--quick] [--beams M] [--width W --height H]
    python benchmarks/bench_isf.py spill [--quick] [--beams M] [--width W --height H]
    python benchmarks/bench_isf.py lambertian [--quick] [--beams M] [--width W --height H]
    python benchmarks/bench_isf.py folds [--quick] [--beams M] [--width W --height H]

throughput: writes m synthetic beam frames (a Gaussian laser spot on a smooth
interreflection-like background), then times, in this process, (a) just reading
every EXR, (b) ilt centroids + build-isf run together (``centroids_and_isf``: every
EXR decoded once) with N workers and (c) with 1 worker, the three back
to back in every repeat. Prints medians and the ratios (stages / read, 1 worker / N
workers). ``--profile`` prints a cProfile of one single-worker run instead.

noise: the cost of carrying the frames' noise into T (issue 21, :mod:`ilt.isf.noise`:
the fit on the frames' sum, each entry's variance, the fine fit's noise terms): build-isf
on the synthetic frames (noise 0.01, and a dark strip where their sum reads below zero) as it is, and with the
noise fit switched off (no noise.json, the fine fit's old test), back to back in every
repeat; medians and the ratio (target <= 1.2).

spill: the cost of measuring each spot's direct light in its neighbours' cells (issue 21,
:mod:`ilt.isf.spill`): build-isf on the synthetic frames with and without it, back to back
in every repeat; medians and the ratio (target <= 1.15).

folds: the cost of ``--fold-cells`` (:mod:`ilt.isf.folds`: one more pass over the frames
for the far light, its valleys and the cells ended at them), the same way.

lambertian: the cost of the reciprocity check (issue 22, :mod:`ilt.transport.reciprocity`),
build-isf with and without it, the same way (target <= 1.10 at m = 4096).

sampling: renders the flatland M at several beam densities (spot sigma 1/20 of the
beam spacing, 16 surface patches per spacing), runs centroids, build-isf with cell
and point sampling, decomposes the room-light and flashlight photos, and prints the
relative error of bounces 1-4 against the truth read the same way (cell integrals of
the true n-bounce frames, or their values at the sample pixels).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def synthetic_frames(directory: Path, m: int, width: int, height: int, seed: int = 0, noise: float = 1e-4,
                     dark: int = 0) -> None:
    """``dark``: the background is 0 over that many px along the left edge (noise only there)."""
    from scipy.special import ndtr

    from ilt.io.exr import write_exr
    from ilt.io.manifest import write_json

    rng = np.random.default_rng(seed)
    cols = int(np.ceil(np.sqrt(m * width / height)))
    rows = int(np.ceil(m / cols))
    gx = (np.arange(cols) + 0.5) * width / cols
    gy = (np.arange(rows) + 0.5) * height / rows
    yy, xx = np.mgrid[:height, :width]
    ex, ey = np.arange(width + 1) - 0.5, np.arange(height + 1) - 0.5
    directory.mkdir(parents=True)
    for j in range(m):
        cx = gx[j % cols] + rng.uniform(-0.5, 0.5)
        cy = gy[j // cols] + rng.uniform(-0.5, 0.5)
        spot = 2000.0 * np.outer(np.diff(ndtr((ey - cy) / 1.5)), np.diff(ndtr((ex - cx) / 1.5)))
        background = 0.05 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * (0.3 * width) ** 2))
        background[:, :dark] = 0.0
        write_exr(directory / f"beam-{j:05d}.exr", spot + background + rng.normal(0, noise, (height, width)))
    write_json(directory / "manifest.json", {"layout": [1, m]})


def throughput(m: int, width: int, height: int, workers: int, repeats: int, profile: bool = False) -> None:
    from ilt.io.frames import open_hdr_directory, read_frame
    from ilt.isf.build import centroids_and_isf

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t = time.perf_counter()
        synthetic_frames(tmp / "hdr", m, width, height)
        print(f"wrote {m} frames of {width} x {height} in {time.perf_counter() - t:.1f} s", file=sys.stderr)
        hdr = open_hdr_directory(tmp / "hdr")

        def read_all():
            for f in hdr.files:
                read_frame(f)

        def stages(n):
            centroids_and_isf(tmp / "hdr", tmp / "spots", tmp / "isf", workers=n, force=True)

        if profile:
            import cProfile
            import pstats

            cProfile.runctx("stages(1)", globals(), {"stages": stages}, str(tmp / "profile"))
            pstats.Stats(str(tmp / "profile")).sort_stats("cumtime").print_stats(40)
            return
        read_all()  # warm the page cache
        # the three runs back to back in every repeat, so load from other users of the
        # machine falls on all of them alike; medians over the repeats
        times: dict = {"read": [], workers: [], 1: []}
        for _ in range(repeats):
            for key, run in (("read", read_all), (workers, lambda: stages(workers)), (1, lambda: stages(1))):
                t = time.perf_counter()
                run()
                times[key].append(time.perf_counter() - t)
    t_read, t_n, t_1 = (statistics.median(times[k]) for k in ("read", workers, 1))
    ratio_n = statistics.median(n / r for n, r in zip(times[workers], times["read"]))
    speedup = statistics.median(o / n for o, n in zip(times[1], times[workers]))
    print(f"m = {m}, {width} x {height}, medians of {repeats} repeats (read, {workers} workers, 1 worker back to back)")
    print(f"  read every EXR once (1 process)        {t_read:8.2f} s   {1e3 * t_read / m:6.2f} ms/frame")
    print(f"  centroids + build-isf, {workers} workers     {t_n:8.2f} s   ratio to read {ratio_n:.2f} (target <= 1.5)")
    print(f"  centroids + build-isf, 1 worker        {t_1:8.2f} s   ratio to read "
          f"{statistics.median(o / r for o, r in zip(times[1], times['read'])):.2f}")
    print(f"  speed-up {workers} workers over 1            {speedup:.2f} x (target >= 1.6 with 2)")
    print("  all times (s): " + "; ".join(f"{k}: " + ", ".join(f"{v:.2f}" for v in times[k]) for k in times))


def noise_cost(m: int, width: int, height: int, workers: int, repeats: int) -> None:
    from ilt.isf import build
    from ilt.spots.stage import run_centroids

    fit = build.fit_frame_noise
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        synthetic_frames(tmp / "hdr", m, width, height, noise=0.01, dark=width // 10)  # reads below 0 there
        run_centroids(tmp / "hdr", tmp / "spots", workers=workers)
        times: dict = {"with noise": [], "without": []}
        try:
            for _ in range(repeats + 1):   # the first round warms the page cache and is not counted
                for key, f in (("with noise", fit), ("without", lambda *a, **k: None)):
                    build.fit_frame_noise = f
                    t = time.perf_counter()
                    build.build_isf(tmp / "hdr", tmp / "spots", tmp / "isf", workers=workers, force=True)
                    times[key].append(time.perf_counter() - t)
                    assert (tmp / "isf" / "noise.json").exists() == (key == "with noise")
        finally:
            build.fit_frame_noise = fit
    with_, without = (statistics.median(times[k][1:]) for k in ("with noise", "without"))
    ratio = statistics.median(a / b for a, b in zip(times["with noise"][1:], times["without"][1:]))
    print(f"build-isf, m = {m}, {width} x {height}, {workers} workers, medians of {repeats} repeats")
    print(f"  noise carried into T     {with_:8.2f} s")
    print(f"  without (as before)      {without:8.2f} s")
    print(f"  ratio {ratio:.3f} (target <= 1.2)")


def applied(isf: Path, output: str) -> bool:
    """Whether a build wrote ``output``: a file of the ISF, or (``manifest:KEY``) a record of
    its manifest that says it was applied."""
    if output.startswith("manifest:"):
        record = json.loads((isf / "manifest.json").read_text()).get(output.split(":", 1)[1])
        return bool(record and record.get("applied"))
    return (isf / output).exists()


def toggle_cost(option: str, output: str, target: float, what: str, m: int, width: int, height: int,
                workers: int, repeats: int) -> None:
    """build-isf with ``option`` on and off, back to back in every repeat: medians and their ratio
    (``output``: what the option writes, :func:`applied`)."""
    from ilt.isf import build
    from ilt.spots.stage import run_centroids

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        synthetic_frames(tmp / "hdr", m, width, height, noise=0.01)
        run_centroids(tmp / "hdr", tmp / "spots", workers=workers)
        times: dict = {True: [], False: []}
        for _ in range(repeats + 1):   # the first round warms the page cache and is not counted
            for on in (True, False):
                t = time.perf_counter()
                build.build_isf(tmp / "hdr", tmp / "spots", tmp / "isf", workers=workers, force=True, **{option: on})
                times[on].append(time.perf_counter() - t)
                assert applied(tmp / "isf", output) == on
    with_, without = (statistics.median(times[k][1:]) for k in (True, False))
    ratio = statistics.median(a / b for a, b in zip(times[True][1:], times[False][1:]))
    print(f"build-isf, m = {m}, {width} x {height}, {workers} workers, medians of {repeats} repeats")
    print(f"  with {what:22s} {with_:8.2f} s")
    print(f"  without                    {without:8.2f} s")
    print(f"  ratio {ratio:.3f} (target <= {target})")


def sampling_errors(scene_name: str, beams: int, spot: float, workdir: Path, n_bounces: int = 4) -> dict:
    """{(sampling, kind): (n_bounces,) relative errors} for one rendered scene."""
    from ilt.decompose.stage import decompose
    from ilt.isf.build import build_isf, sample_like
    from ilt.isf.directory import load_isf
    from ilt.sim.render import render_scene
    from ilt.spots.stage import run_centroids
    from ilt.workspace.simulate import write_frames

    rs = render_scene(scene_name, beams=beams, spot=spot)
    sim = write_frames(rs, workdir / "sim", {"scene": scene_name, "beams": beams})
    run_centroids(sim / "hdr", workdir / "spots", workers=1)
    out = {}
    for sampling in ("cell", "point"):
        build_isf(sim / "hdr", workdir / "spots", workdir / sampling, sampling=sampling, workers=1)
        isf = load_isf(workdir / sampling)
        kinds = ("room", "flashlight")
        decompose(isf, [sim / "photos" / f"{k}.exr" for k in kinds], workdir / f"dec-{sampling}",
                  n_bounces=n_bounces)
        for k in kinds:
            est = np.load(workdir / f"dec-{sampling}" / k / "bounces.npy")
            truth = sample_like(isf, np.load(sim / "truth" / "photos" / f"{k}-bounces.npy")[:n_bounces])
            out[(sampling, k)] = np.linalg.norm(est - truth, axis=1) / np.linalg.norm(truth, axis=1)
    return out


def sampling_table(densities: list[int], spot: float, scene: str) -> None:
    import logging

    logging.basicConfig(level=logging.ERROR)
    print(f"scene {scene}, spot sigma = {spot:g} beam spacing; relative error ||Ln - truth|| / ||truth||")
    print(f"{'m':>5} {'photo':>10} {'sampling':>8} " + " ".join(f"{'L' + str(n):>7}" for n in range(1, 5)))
    for m in densities:
        with tempfile.TemporaryDirectory() as tmp:
            errors = sampling_errors(scene, m, spot, Path(tmp))
        for (sampling, kind), e in sorted(errors.items(), key=lambda kv: (kv[0][1], kv[0][0])):
            print(f"{m:>5} {kind:>10} {sampling:>8} " + " ".join(f"{100 * v:6.1f}%" for v in e), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="what", required=True)
    def frames_parser(name):
        p = sub.add_parser(name)
        p.add_argument("--quick", action="store_true", help="m = 128, 320 x 240")
        p.add_argument("--beams", type=int, default=1024)
        p.add_argument("--width", type=int, default=640)
        p.add_argument("--height", type=int, default=480)
        p.add_argument("--workers", type=int, default=2)
        p.add_argument("--repeats", type=int, default=3)
        return p

    frames_parser("throughput").add_argument("--profile", action="store_true",
                                             help="cProfile one single-worker run instead")
    frames_parser("noise")
    frames_parser("spill")
    frames_parser("lambertian")
    frames_parser("folds")
    s = sub.add_parser("sampling")
    s.add_argument("--quick", action="store_true", help="densities 16, 32")
    s.add_argument("--densities", default="32,64,128")
    s.add_argument("--spot", type=float, default=0.05)
    s.add_argument("--scene", default="m")
    args = parser.parse_args()
    if args.what == "throughput":
        if args.quick:
            args.beams, args.width, args.height, args.repeats = 128, 320, 240, 1
        throughput(args.beams, args.width, args.height, args.workers, args.repeats, args.profile)
    elif args.what == "noise":
        if args.quick:
            args.beams, args.width, args.height = 128, 320, 240
        noise_cost(args.beams, args.width, args.height, args.workers, args.repeats)
    elif args.what in ("spill", "lambertian", "folds"):
        if args.quick:
            args.beams, args.width, args.height = 128, 320, 240
        option = {"spill": ("spill", "spill.npz", 1.15, "the spill measured"),
                  "lambertian": ("lambertian", "lambertian.json", 1.10, "the reciprocity check"),
                  "folds": ("fold_cells", "manifest:folds", 1.5, "cells ended at folds")}[args.what]
        toggle_cost(*option, args.beams, args.width, args.height, args.workers, args.repeats)
    else:
        densities = [16, 32] if args.quick else [int(d) for d in args.densities.split(",")]
        sampling_table(densities, args.spot, args.scene)


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
