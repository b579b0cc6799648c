"""Benchmark of the HDR stage (issue 3): calibration and merge accuracy against OpenCV
(8-bit brackets, which OpenCV's merges take), dynamic range, and merge throughput (wall
and user CPU time) against plain rawpy decoding, in one process.

    python benchmarks/bench_hdr.py --quick            # small sizes, a minute or two
    python benchmarks/bench_hdr.py --beams 100 --width 3504 --height 2336   # the issue's size

Generated files live in a temporary directory that is deleted at the end. Timings are
medians of --repeat runs. Prints one line per figure.
"""

from __future__ import annotations

import argparse
import itertools
import resource
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import rawpy

from ilt.hdr.merge import NoiseModel, cramer_rao_bound, merge_bracket
from ilt.hdr.mitsunaga_nayar import fit_response, usable_samples
from ilt.hdr.stages import MergeOptions, merge_capture
from ilt.sim.sensor import PAPER_BRACKET, SensorModel, expose, spot_radiance, write_bracket


def response(x):
    return x ** (1 / 2.2) * (1.1 - 0.1 * x)


#: exposure times (s, at f/1) of the 8-bit brackets, one stop apart
LDR_TIMES = np.array([1 / 1000, 1 / 500, 1 / 250, 1 / 125, 1 / 60, 1 / 30, 1 / 15])


def ldr_sensor(width: int, height: int) -> SensorModel:
    """A grey 8-bit camera through the non-linear ``response``: 15300 e- full scale
    (60 e-/DN), 30 e- read noise (which also dithers the 8-bit steps)."""
    return SensorModel(width=width, height=height, black_level=0, white_level=255, bits=8, gain=60.0,
                       read_noise=30.0, response=response, colour_scale=(1, 1, 1))


def calibrate_ours(frames: list[np.ndarray], times: np.ndarray):
    """Mitsunaga-Nayar fit on 8-bit frames (product of the ratios pinned to the nominal)."""
    images = [f / 255.0 for f in frames]
    return fit_response(images, times, usable_samples(images, 3 / 255, 254 / 255, 254.5 / 255), pin_span=True)


def calibration(rng):
    """8-bit non-linear bracket: max |f_est - f_true| of ours, Debevec, Robertson."""
    sensor = ldr_sensor(200, 120)
    X = np.logspace(2, 6, 200)[None, :].repeat(120, 0)
    times = LDR_TIMES
    frames = [expose(X, t, 1.0, sensor, rng).astype(np.uint8) for t in times]
    grid = np.linspace(0, 1, 256)
    xx = np.linspace(0, 1, 200001)
    truth = np.interp(grid, response(xx), xx)
    fit = calibrate_ours(frames, times)
    ours = np.abs(fit(grid) - truth)[3:253].max()
    out = {"ours": ours}
    stack = [cv2.merge([f, f, f]) for f in frames]
    for name, calib in (("debevec", cv2.createCalibrateDebevec()), ("robertson", cv2.createCalibrateRobertson())):
        crf = calib.process(stack, times.astype(np.float32))[:, 0, 1].astype(float)
        crf = crf / crf[254]  # same normalisation as ours: f(clip) = 1
        out[name] = np.abs(crf - truth)[3:253].max()
    print(f"calibration 8-bit max|f-f_true| (M in 3..252/255): ours {out['ours']:.4f}, "
          f"Debevec {out['debevec']:.4f}, Robertson {out['robertson']:.4f}")
    return out


def merge_accuracy(rng, rows):
    """Paper bracket on a log ramp: relative RMS error / Cramer-Rao bound per decade, DR,
    and OpenCV's MergeDebevec/MergeRobertson on the same frames."""
    w = 64
    X = np.logspace(1.0, 10.4, w)[None, :].repeat(rows, 0)
    sensor = SensorModel(width=2 * w, height=2 * rows)
    e = np.array([t / n**2 for t, n, _ in PAPER_BRACKET])
    noise = NoiseModel(sensor.gain, sensor.read_noise)
    frames, sats = [], []
    for t, n, _ in PAPER_BRACKET:
        m = expose(X, t, n, sensor, rng).astype(float) - sensor.black_level
        frames.append((m[0::2, 1::2] + m[1::2, 0::2]) / 2)
        sats.append(np.maximum(m[0::2, 1::2], m[1::2, 0::2]) >= 0.97 * sensor.full_scale)
    R, _, _ = merge_bracket(frames, e, sats, noise=noise)
    rel = np.sqrt((((R - X) / X) ** 2).mean(axis=0))
    crb = np.sqrt(cramer_rao_bound(X[0], e, 0.97 * sensor.full_scale, noise)) / X[0]
    inside = rel < 1.0  # where SNR >= 1: the dynamic range
    ratio = rel[inside] / crb[inside]
    top = X[0][inside].max()
    bottom = X[0][inside].min()
    print(f"merge paper bracket: DR (SNR>=1 .. unsaturated) {20 * np.log10(top / bottom):.1f} dB "
          f"[{bottom:.3g} .. {top:.3g}]; error/CRB median {np.median(ratio):.3f}, "
          f"90th pct {np.percentile(ratio, 90):.3f}, max {ratio.max():.3f}")


def spot_scene(height: int, width: int, floor: float) -> np.ndarray:
    """(h, w) e-/s at f/1: a laser spot (peak 1e7: unsaturated at 1/1000 s) with a halo
    over a constant ``floor`` (1e4 reads 667 e-, M = 0.25, at 1/15 s; 2e3 reads M = 0.12)."""
    return spot_radiance((height, width), (width / 2, height / 2), 1e7, min(height, width) / 16,
                         floor=floor, tail=0.02)


def merge_8bit_vs_opencv(rng, height: int, width: int, repeat: int = 1, floor: float = 1e4) -> dict:
    """One spot scene, one 8-bit bracket (`ldr_sensor`, `LDR_TIMES`): our Mitsunaga-Nayar
    calibration + noise-weighted merge against OpenCV's CalibrateDebevec + MergeDebevec and
    CalibrateRobertson + MergeRobertson, each calibrated on the same frames; plus our
    linear RAW merge of the same scene and times (14-bit sensor, green of 2x2 cells).

    Each result is scaled by one global factor (least squares on log values: OpenCV's
    scale is arbitrary) and compared with the true radiance over the pixels every method
    covers (finite, > 0, and for ours at least one unsaturated sample that carried weight).
    Returns {"pixels", "covered", "truth", "methods": {name: {"relative_error" (covered
    pixels), "scale", "calibrate_s", "merge_s"}}}; times are medians of ``repeat`` runs.
    """
    X = spot_scene(height, width, floor)
    frames = [expose(X, t, 1.0, ldr_sensor(width, height), rng).astype(np.uint8) for t in LDR_TIMES]
    stack = [cv2.merge([f, f, f]) for f in frames]
    times32 = LDR_TIMES.astype(np.float32)

    def ours_calibrate():
        return calibrate_ours(frames, LDR_TIMES)

    def ours_merge(fit):
        # linear-domain noise model of the 8-bit camera: 60 e-/DN, 0.5 DN read noise, one site
        return merge_bracket([f.astype(np.float32) for f in frames], LDR_TIMES, [f >= 255 for f in frames],
                             noise=NoiseModel(gain=60.0, read_noise=0.5, sites=1), response=fit, full_scale=255.0)

    def opencv(calibrate, merge):
        return (lambda: calibrate.process(stack, times32),
                lambda crf: merge.process(stack, times32, crf)[..., 1])

    raw_sensor = SensorModel(width=2 * width, height=2 * height)
    mosaics = [expose(X, t, 1.0, raw_sensor, rng).astype(np.float32) - raw_sensor.black_level
               for t in LDR_TIMES]
    greens = [(m[0::2, 1::2] + m[1::2, 0::2]) / 2 for m in mosaics]
    raw_sat = [np.maximum(m[0::2, 1::2], m[1::2, 0::2]) >= 0.97 * raw_sensor.full_scale for m in mosaics]
    methods = {
        "ours (Mitsunaga-Nayar + merge)": (ours_calibrate, lambda fit: ours_merge(fit)),
        "OpenCV Debevec": opencv(cv2.createCalibrateDebevec(), cv2.createMergeDebevec()),
        "OpenCV Robertson": opencv(cv2.createCalibrateRobertson(), cv2.createMergeRobertson()),
        "ours, 14-bit linear RAW (reference)": (lambda: None, lambda _: merge_bracket(
            greens, LDR_TIMES, raw_sat, noise=NoiseModel(raw_sensor.gain, raw_sensor.read_noise))),
    }
    results, estimates, covers = {}, {}, []
    for name, (calibrate, merge) in methods.items():
        t_cal, t_merge = [], []
        for _ in range(repeat):
            t0 = time.perf_counter()
            crf = calibrate()
            t1 = time.perf_counter()
            out = merge(crf)
            t_cal.append(t1 - t0)
            t_merge.append(time.perf_counter() - t1)
        if isinstance(out, tuple):  # merge_bracket: (radiance, count, all saturated)
            out, count, saturated = out
            covers.append((count > 0) & ~saturated)
        estimate = np.asarray(out, dtype=np.float64)
        covers.append(np.isfinite(estimate) & (estimate > 0))
        estimates[name] = estimate
        results[name] = {"calibrate_s": statistics.median(t_cal), "merge_s": statistics.median(t_merge)}
    covered = np.logical_and.reduce(covers)
    for name, estimate in estimates.items():
        scale = np.exp(np.mean(np.log(X[covered]) - np.log(estimate[covered])))
        results[name].update(scale=scale, relative_error=np.abs(scale * estimate[covered] / X[covered] - 1))
    return {"pixels": X.size, "covered": covered, "truth": X[covered], "floor": floor, "methods": results}


def print_merge_8bit(result: dict) -> None:
    truth = result["truth"]
    edges = np.arange(np.floor(np.log10(truth.min())), np.ceil(np.log10(truth.max())) + 1)
    bins = list(itertools.pairwise(edges))
    print(f"merge, 8-bit spot bracket ({len(LDR_TIMES)} frames 1/1000 .. 1/15 s, non-linear response, "
          f"floor {result['floor']:.0e} e-/s): relative error |s R / X - 1| after one least-squares log "
          f"scale s per method, over the {result['covered'].sum()} of {result['pixels']} pixels every "
          f"method covers")
    head = "| method | median | RMS | " + " | ".join(f"median, X in 1e{lo:g}..1e{hi:g}" for lo, hi in bins)
    print(head + " | scale s | calibrate s | merge s |")
    for name, r in result["methods"].items():
        err = r["relative_error"]
        per_bin = [np.median(err[(truth >= 10**lo) & (truth < 10**hi)]) for lo, hi in bins]
        print(f"| {name} | {np.median(err):.4f} | {np.sqrt(np.mean(err**2)):.4f} | "
              + " | ".join(f"{v:.4f}" for v in per_bin)
              + f" | {r['scale']:.4g} | {r['calibrate_s']:.3f} | {r['merge_s']:.3f} |")


def make_capture(cap: Path, beams: int, width: int, height: int, distinct: int, rng) -> None:
    """A capture directory of ``beams`` beams of the paper's bracket of simulated DNGs,
    ``distinct`` of them simulated and the others hard links to them, with the
    fingerprints in capture.jsonl as ``ilt capture`` logs them."""
    import os

    from ilt.capture.log import CaptureLog
    from ilt.io.manifest import LOG_NAME, fingerprint_file

    sensor = SensorModel(width=width, height=height)
    distinct = min(distinct, beams)
    for b in range(beams):
        beam = cap / f"beam-{b:05d}"
        if b < distinct:
            X = spot_radiance((height // 2, width // 2), (width / 4, height / 4 + b), 5e9, 3.0, floor=100, tail=1e-3)
            write_bracket(beam, X, PAPER_BRACKET, sensor, rng)
        else:
            beam.mkdir()
            for f in (cap / f"beam-{b % distinct:05d}").iterdir():
                os.link(f, beam / f.name)
    journal = CaptureLog(cap / LOG_NAME)
    for f in sorted(cap.rglob("*.dng")):
        journal.append("frame", beam=int(f.parent.name.split("-")[1]), file=f"{f.parent.name}/{f.name}",
                       sha256=fingerprint_file(f))
    journal.close()


def throughput(tmp: Path, beams: int, width: int, height: int, repeat: int, rng, distinct: int | None = None):
    """Decode only against merge, wall and user CPU time (medians of ``repeat``). The
    capture log holds each frame's sha256 as ``ilt capture`` writes it, so the merge takes
    its fingerprints from there; the run without the log hashes every DNG.

    ``distinct``: brackets simulated (default: every beam); the other beams are hard
    links to them (a full-size bracket takes seconds to simulate and 180 MB of disk).
    The page cache then holds the distinct files, so decoding and merging both read
    from memory: the ratio is of compute, as on a capture disk fast enough to stream."""
    from ilt.io.manifest import LOG_NAME

    cap = tmp / "cap"
    make_capture(cap, beams, width, height, distinct or beams, rng)
    files = sorted(cap.rglob("*.dng"))

    def decode():
        for f in files:
            with rawpy.imread(str(f)) as raw:
                raw.raw_image_visible.copy()

    def merge(workers, logged=True):
        shutil.rmtree(tmp / "hdr", ignore_errors=True)
        if not logged:
            (cap / LOG_NAME).rename(tmp / LOG_NAME)
        try:
            merge_capture(cap, tmp / "hdr", MergeOptions(), workers=workers)
        finally:
            if not logged:
                (tmp / LOG_NAME).rename(cap / LOG_NAME)

    def timed(fn, *a):
        """(wall s, user CPU s of this process and its waited-for children), medians."""
        walls, cpus = [], []
        for _ in range(repeat):
            u0, t0 = user_cpu(), time.perf_counter()
            fn(*a)
            walls.append(time.perf_counter() - t0)
            cpus.append(user_cpu() - u0)
        return statistics.median(walls), statistics.median(cpus)

    decode_s, decode_cpu = timed(decode)
    rows = [("decode only (rawpy)", decode_s, decode_cpu),
            ("merge, 1 worker, fingerprints from the capture log", *timed(merge, 1)),
            ("merge, 1 worker, no capture log (hashes every DNG)", *timed(merge, 1, False)),
            ("merge, 2 workers, fingerprints from the capture log", timed(merge, 2)[0], None)]
    print(f"throughput {beams} beams x {len(PAPER_BRACKET)} DNG of {width} x {height} ({distinct} distinct "
          f"brackets), medians of {repeat}:")
    print("| run | wall s | x decode | user CPU s | x decode |")
    for name, wall, cpu in rows:
        cpu_text = "n/a (forkserver workers)" if cpu is None else f"{cpu:.2f} | {cpu / decode_cpu:.2f}x"
        print(f"| {name} | {wall:.2f} | {wall / decode_s:.2f}x | {cpu_text} |")
    print(f"two workers against one: {rows[1][1] / rows[3][1]:.2f}x faster")
    peaks = [peak_memory(tmp, n) for n in sorted({max(1, beams // 4), beams})]
    print("peak RSS of a one-worker merge process: " + ", ".join(f"{n} beams {m:.0f} MiB" for n, m in peaks))


def user_cpu() -> float:
    """User CPU seconds of this process plus its terminated, waited-for children."""
    return sum(resource.getrusage(who).ru_utime for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))


def peak_memory(tmp: Path, beams: int) -> tuple[int, float]:
    """(beams, MiB): maximum resident size of a fresh process merging the first ``beams``."""
    import subprocess
    import sys

    cap = tmp / f"cap-{beams}"
    cap.mkdir()
    for b in sorted((tmp / "cap").glob("beam-*"))[:beams]:
        (cap / b.name).symlink_to(b)
    code = ("import resource, sys; from ilt.hdr.stages import merge_capture; "
            "merge_capture(sys.argv[1], sys.argv[2]); "
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)")
    out = subprocess.run([sys.executable, "-c", code, str(cap), str(tmp / f"hdr-{beams}")],
                         check=True, capture_output=True, text=True).stdout
    return beams, int(out.split()[-1]) / 1024


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes")
    ap.add_argument("--beams", type=int, default=None)
    ap.add_argument("--width", type=int, default=None)
    ap.add_argument("--height", type=int, default=None)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--distinct", type=int, default=None,
                    help="simulate this many brackets, hard-link the other beams to them (default: all)")
    ap.add_argument("--throughput-only", action="store_true", help="skip the accuracy figures")
    args = ap.parse_args()
    beams = args.beams or (4 if args.quick else 100)
    width = args.width or (876 if args.quick else 3504)
    height = args.height or (584 if args.quick else 2336)
    rng = np.random.default_rng(0)
    tmp = Path(tempfile.mkdtemp(prefix="ilt-bench-hdr-"))
    try:
        if not args.throughput_only:
            accuracy(rng, args)
        throughput(tmp, beams, width, height, args.repeat, rng, args.distinct)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def accuracy(rng, args):
    calibration(rng)
    merge_accuracy(rng, 200 if args.quick else 1000)
    size = (120, 160) if args.quick else (300, 400)
    print_merge_8bit(merge_8bit_vs_opencv(rng, *size, args.repeat))
    floors = {f: merge_8bit_vs_opencv(rng, *size, floor=f)["methods"] for f in (2e3, 5e3, 1e4, 3e4)}
    print("merge, 8-bit spot bracket: median relative error by the scene's floor (e-/s)")
    print("| floor | " + " | ".join(floors[1e4]) + " |")
    for f, methods in floors.items():
        print(f"| {f:.0e} | " + " | ".join(f"{np.median(r['relative_error']):.4f}" for r in methods.values()) + " |")


if __name__ == "__main__":
    main()
