"""Benchmark of the HDR stage (issue 3): calibration and merge accuracy against OpenCV,
dynamic range, and merge throughput against plain rawpy decoding, in one process.

    python benchmarks/bench_hdr.py --quick            # small sizes, a minute or two
    python benchmarks/bench_hdr.py --beams 100 --width 3504 --height 2336   # the issue's size

Generated files live in a temporary directory that is deleted at the end. Timings are
medians of --repeat runs. Prints one line per figure.
"""

from __future__ import annotations

import argparse
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


def calibration(rng):
    """8-bit non-linear bracket: max |f_est - f_true| of ours, Debevec, Robertson."""
    sensor = SensorModel(width=200, height=120, black_level=0, white_level=255, bits=8, gain=60.0,
                         read_noise=30.0, response=response, colour_scale=(1, 1, 1))
    X = np.logspace(2, 6, 200)[None, :].repeat(120, 0)
    times = np.array([1 / 1000, 1 / 500, 1 / 250, 1 / 125, 1 / 60, 1 / 30, 1 / 15])
    frames = [expose(X, t, 1.0, sensor, rng).astype(np.uint8) for t in times]
    grid = np.linspace(0, 1, 256)
    xx = np.linspace(0, 1, 200001)
    truth = np.interp(grid, response(xx), xx)
    images = [f / 255.0 for f in frames]
    fit = fit_response(images, times, usable_samples(images, 3 / 255, 254 / 255, 254.5 / 255), pin_span=True)
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
    # OpenCV on the same float frames (scaled to its 0..1 float convention), linear response
    scale = 0.97 * sensor.full_scale
    stack = [cv2.merge([np.clip(f / scale, 0, 1).astype(np.float32)] * 3) for f in frames]
    lin = np.linspace(0, 1, 256, dtype=np.float32).reshape(256, 1, 1).repeat(3, axis=2)
    results = {"ours": np.median(rel[inside])}
    for name, merger in (("MergeDebevec", cv2.createMergeDebevec()), ("MergeRobertson", cv2.createMergeRobertson())):
        try:
            hdr = merger.process(stack, e.astype(np.float32), lin)[..., 1] * scale
            r = np.sqrt((((hdr - X) / X) ** 2).mean(axis=0))
            results[name] = np.median(r[inside])
        except cv2.error as exc:
            results[name] = f"refused float input ({str(exc).splitlines()[-1].strip()[:60]})"
    print("merge median relative error over the range: " + ", ".join(
        f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in results.items()))


def throughput(tmp: Path, beams: int, width: int, height: int, repeat: int, rng):
    sensor = SensorModel(width=width, height=height)
    for b in range(beams):
        X = spot_radiance((height // 2, width // 2), (width / 4, height / 4 + b), 5e9, 3.0, floor=100, tail=1e-3)
        write_bracket(tmp / "cap" / f"beam-{b:05d}", X, PAPER_BRACKET, sensor, rng)
    files = sorted((tmp / "cap").rglob("*.dng"))

    def decode():
        for f in files:
            with rawpy.imread(str(f)) as raw:
                raw.raw_image_visible.copy()

    def merge(workers):
        shutil.rmtree(tmp / "hdr", ignore_errors=True)
        merge_capture(tmp / "cap", tmp / "hdr", MergeOptions(), workers=workers)

    def timed(fn, *a):
        runs = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            fn(*a)
            runs.append(time.perf_counter() - t0)
        return statistics.median(runs)

    t_decode = timed(decode)
    t1 = timed(merge, 1)
    t2 = timed(merge, 2)
    print(f"throughput {beams} beams x {len(PAPER_BRACKET)} DNG of {width} x {height}: decode only "
          f"{t_decode:.2f} s, merge 1 worker {t1:.2f} s ({t1 / t_decode:.2f}x decode), "
          f"2 workers {t2:.2f} s (speed-up {t1 / t2:.2f}x)")
    peaks = [peak_memory(tmp, n) for n in sorted({max(1, beams // 4), beams})]
    print("peak RSS of a one-worker merge process: " + ", ".join(f"{n} beams {m:.0f} MiB" for n, m in peaks))


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
    args = ap.parse_args()
    beams = args.beams or (4 if args.quick else 100)
    width = args.width or (876 if args.quick else 3504)
    height = args.height or (584 if args.quick else 2336)
    rng = np.random.default_rng(0)
    calibration(rng)
    merge_accuracy(rng, 200 if args.quick else 1000)
    tmp = Path(tempfile.mkdtemp(prefix="ilt-bench-hdr-"))
    try:
        throughput(tmp, beams, width, height, args.repeat, rng)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
