"""What the outlier test costs a beam frame (ilt.isf.outliers.clamp_isolated, docs/spots-and-isf.md).

    python benchmarks/bench_outliers.py [--size 4000x3000] [--repeats 5]

One synthetic beam frame (smooth light, a spot, photon and read noise, or with
``--read-noise 0`` photon noise alone over mostly dark pixels; 1e-4 of its pixels fireflies) is written as build-isf reads frames (a zip EXR, ``ilt.io.exr.write_exr``), then
read (``ilt.io.frames.load_frame``, the baseline: build-isf reads every frame once) and
tested, back to back in this process. Prints the medians, the median of the per-repeat
ratios, and how many of the fireflies the test replaced.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from ilt.io.exr import write_exr
from ilt.io.frames import load_frame
from ilt.isf.noise import FrameNoise
from ilt.isf.outliers import clamp_isolated


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--size", default="4000x3000", help="WxH (default 4000x3000, 12 Mpx)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--read-noise", type=float, default=2.0,
                        help="read noise, electrons (default 2; 0: photon noise alone, most faint pixels at zero)")
    args = parser.parse_args()
    width, height = map(int, args.size.split("x"))
    rng = np.random.default_rng(0)
    gain, read = 4.0, args.read_noise
    y, x = np.mgrid[:height, :width].astype(np.float32)
    light = (0.05 if read == 0 else 50.0) + 40.0 * np.exp(-((x - 0.6 * width) ** 2 + (y - 0.4 * height) ** 2) / (2 * (0.3 * width) ** 2))
    light += 5e4 * np.exp(-((x - 0.3 * width) ** 2 + (y - 0.5 * height) ** 2) / 2.0)
    frame = (rng.poisson(light * gain) / gain + rng.normal(0, read / gain, light.shape)).astype(np.float32)
    hits = rng.choice(frame.size, frame.size // 10**4, replace=False)
    frame.flat[hits] += 20 * np.quantile(frame, 0.999) * rng.exponential(1.0, hits.size).astype(np.float32)
    noise = FrameNoise((0.0, 1e4), ((read / gain) ** 2, (read / gain) ** 2 + 1e4 / gain), 8, 10**6, 2, 1.0 / gain)
    if read == 0:   # a photon-only fit: no variance where most pixels count no photon
        noise = FrameNoise((0.0, 0.05, 1e4), (0.0, 0.0, 1e4 / gain), 8, 10**6, 3, 1.0 / gain)
    spot = np.array([0.3 * width, 0.5 * height])
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "beam-00000.exr"
        write_exr(path, frame, ["Y"])
        buffer = np.empty((height, width))
        reads, tests, ratios = [], [], []
        for _ in range(args.repeats):
            t = time.perf_counter()
            load_frame(path, (height, width), out=buffer)
            reads.append(time.perf_counter() - t)
            t = time.perf_counter()
            replaced = clamp_isolated(buffer, noise, spot, 5.0)
            tests.append(time.perf_counter() - t)
            ratios.append(tests[-1] / reads[-1])
    print(f"frame {width} x {height}: read median {statistics.median(reads):.3f} s, outlier test median "
          f"{statistics.median(tests):.3f} s, ratio (median of repeats) {statistics.median(ratios):.2f}; "
          f"replaced {replaced} of {hits.size} fireflies")


if __name__ == "__main__":
    main()
