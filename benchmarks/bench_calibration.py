"""Radiometric calibration side by side (issue 20): ilt's Mitsunaga-Nayar fit against
OpenCV's CalibrateDebevec and CalibrateRobertson on real brackets and on the simulated
8-bit camera, whose response is known.

    python benchmarks/bench_calibration.py                 # every set it finds
    python benchmarks/bench_calibration.py --frobisher DIR # + the Canon 5D Mark II JPEGs

The figure for every set is **consistency**: the median over pixels mid-range in both
(0.1 < M < 0.9) of |log(E_q / E_q+1)| for consecutive exposures q, q+1, E = f(M) / t
with each method's own f and the nominal exposure times (what a merge of the bracket
would disagree with itself by, in log units; 0.01 = 1 %). On the simulated camera also
the error of f itself: max |f(M) - f_true(M)| over M in [0, 1] (ilt; OpenCV's curves
have no f(1) = 1, so they are scaled to f_true by least squares on log values first) and
the RMS relative error of f over M in [0.05, 0.95], scaled the same way for every method.
A one-parameter gamma curve (f = M^2.2) is the floor any calibration must beat.

Sets: the Memorial Church sequence (Debevec & Malik 1997, 16 PNGs, 1-stop steps) from
``../shared/realdata/memorial`` (skipped when absent); the Canon EOS 5D Mark II bracket
``IMG_2600.jpg ... IMG_2602.jpg`` (1/8, 1, 8 s at f/8, EXIF; colour-science's
colour-hdri-tests-datasets, ``frobisher_001/``) when ``--frobisher`` names its
directory; the simulated camera always. Times are medians of ``--repeat`` runs.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import time
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np

from ilt.hdr.mitsunaga_nayar import fit_response, usable_samples
from ilt.sim.sensor import SensorModel, expose

REALDATA = Path(__file__).resolve().parents[1].parent / "shared" / "realdata"


def response(x):
    """The simulated camera's response (normalised exposure -> normalised code)."""
    return x ** (1 / 2.2) * (1.1 - 0.1 * x)


def true_inverse(m):
    xx = np.linspace(0, 1, 200001)
    return np.interp(m, response(xx), xx)


def simulated(rng, height=240, width=320):
    """An 8-bit grey camera (60 e-/DN, 30 e- read noise) through ``response``, 7 exposures
    one stop apart, a scene of radiances over four decades (a ramp and noise texture)."""
    sensor = SensorModel(width=width, height=height, black_level=0, white_level=255, bits=8, gain=60.0,
                         read_noise=30.0, response=response, colour_scale=(1, 1, 1))
    ramp = np.logspace(2, 6, width)[None, :] * np.exp(0.3 * rng.standard_normal((height, width)))
    times = np.array([1 / 1000, 1 / 500, 1 / 250, 1 / 125, 1 / 64, 1 / 32, 1 / 16])
    frames = [expose(ramp, t, 1.0, sensor, rng).astype(np.uint8) for t in times]
    return [cv2.merge([f, f, f]) for f in frames], times


def memorial():
    d = REALDATA / "memorial"
    if not (d / "shutter_times.txt").exists():
        return None
    times = np.array([float(Fraction(t)) for t in (d / "shutter_times.txt").read_text().split()])
    return [cv2.imread(str(f)) for f in sorted(d.glob("memorial*.png"))], times


def frobisher(directory: Path | None):
    if directory is None:
        return None
    files = [directory / f"IMG_260{k}.jpg" for k in range(3)]
    if not all(f.exists() for f in files):
        raise SystemExit(f"{directory}: needs IMG_2600.jpg, IMG_2601.jpg, IMG_2602.jpg")
    return [cv2.imread(str(f)) for f in files], np.array([1 / 8, 1.0, 8.0])


def consistency(linear, times, codes, lo=0.1, hi=0.9) -> float:
    errors = []
    for q in range(len(linear) - 1):
        a, b = codes[q], codes[q + 1]
        ok = (a > lo) & (a < hi) & (b > lo) & (b < hi)
        ea, eb = linear[q][ok] / times[q], linear[q + 1][ok] / times[q + 1]
        good = (ea > 0) & (eb > 0)
        errors.append(np.abs(np.log(ea[good] / eb[good])))
    return float(np.median(np.concatenate(errors)))


def ilt_fit(images, times):
    """ilt's calibration as ``ilt calibrate`` runs it on 8-bit images (green channel)."""
    m = [im[:, :, 1] / 255.0 for im in images]
    valid = [v & (im[:, :, 1] < 255) for v, im in zip(usable_samples(m, 3 / 255, 254 / 255, 1.0), images)]
    fit = fit_response(m, times, valid, max_order=12, pin_span=True)
    table = fit(np.arange(256) / 255.0)
    return table, fit


def opencv_fit(method):
    def run(images, times):
        crf = method.process(images, times.astype(np.float32))
        return crf[:, 0, 1].astype(np.float64), None
    return run


def gamma_fit(images, times):
    return (np.arange(256) / 255.0) ** 2.2, None


METHODS = {
    "ilt (Mitsunaga-Nayar, monotone)": ilt_fit,
    "OpenCV Debevec": opencv_fit(cv2.createCalibrateDebevec()),
    "OpenCV Robertson": opencv_fit(cv2.createCalibrateRobertson()),
    "gamma 2.2": gamma_fit,
}


def evaluate(images, times, repeat: int, truth=None) -> dict:
    order = np.argsort(times)
    images, times = [images[k] for k in order], times[order]
    codes = [im[:, :, 1] for im in images]
    m = [c / 255.0 for c in codes]
    rows = {}
    for name, method in METHODS.items():
        seconds = []
        for _ in range(repeat):
            start = time.perf_counter()
            table, fit = method(images, times)
            seconds.append(time.perf_counter() - start)
        row = {"consistency": consistency([table[c] for c in codes], times, m),
               "seconds": statistics.median(seconds),
               "monotone": bool(np.all(np.diff(table[np.isfinite(table)]) >= 0))}
        if fit is not None:
            row["order"] = fit.order
        if truth is not None:
            grid = np.arange(256) / 255.0
            true = truth(grid)
            mid = (grid > 0.05) & (grid < 0.95) & (table > 0)
            scale = np.exp(np.mean(np.log(true[mid]) - np.log(table[mid])))
            row["rms_f"] = float(np.sqrt(np.mean((scale * table[mid] / true[mid] - 1) ** 2)))
            if fit is not None:
                fine = np.linspace(0, 1, 1001)
                row["max_f"] = float(np.max(np.abs(fit(fine) - truth(fine))))
        rows[name] = row
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frobisher", type=Path, default=None,
                    help="directory of IMG_2600.jpg ... IMG_2602.jpg (colour-hdri-tests-datasets frobisher_001)")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    logging.disable(logging.WARNING)
    rng = np.random.default_rng(0)
    sets = {"Memorial Church (16 PNGs, 1-stop)": memorial(),
            "Canon 5D Mark II (3 JPEGs, 3-stop)": frobisher(args.frobisher),
            "simulated 8-bit camera (7 frames, 1-stop)": simulated(rng)}
    for name, data in sets.items():
        if data is None:
            print(f"{name}: skipped (files absent)")
            continue
        truth = true_inverse if name.startswith("simulated") else None
        rows = evaluate(*data, args.repeat, truth)
        print(f"\n{name}")
        head = "| method | consistency (median abs log) | seconds | monotone |"
        head += " max abs f - f_true | rms rel. f error |" if truth else ""
        print(head)
        print("|" + "---|" * (head.count("|") - 1))
        best = min(r["consistency"] for k, r in rows.items() if not k.startswith("gamma"))
        for method, r in rows.items():
            line = (f"| {method}{' (order %d)' % r['order'] if 'order' in r else ''} | {r['consistency']:.4f} "
                    f"({r['consistency'] / best:.2f}x best) | {r['seconds']:.2f} | {'yes' if r['monotone'] else 'no'} |")
            if truth:
                line += f" {r['max_f']:.4f} |" if "max_f" in r else " - |"
                line += f" {r['rms_f']:.4f} |"
            print(line)


if __name__ == "__main__":
    main()
