"""What the lit test costs a build (ilt/isf/build.py ``lit_mask``), with and without its wide one-sided means.

    python benchmarks/bench_lit.py [--sizes 960x1280,3000x4000] [--repeats 5]

The lit test runs once per build-isf, on the frames' sum (spots/sum.exr) and their
largest local means (spots/peak.exr). This times it on a synthetic noisy sum of each size
(a lit disc over a dark background, sigma 1 a pixel, the noise model given as it is in a
build), first with the 5 x 5 test and the peak test alone (``LIT_WIDE = ()``), then as
build-isf runs it (the 11 x 11 and 21 x 21 corner windows too), alternating, and prints the
medians and their ratio. For scale: a build reads every beam frame once, so at m = 4096 on
such frames the lit test is one frame's worth of work against thousands.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="960x1280,3000x4000", help="frame sizes, HxW, comma-separated")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()

    import ilt.isf.build as build

    wide = build.LIT_WIDE
    rng = np.random.default_rng(0)
    print(f"| frame | lit test without the wide means (s) | with them, as built (s) | ratio |\n|---|---|---|---|")
    for size in args.sizes.split(","):
        h, w = map(int, size.split("x"))
        yy, xx = np.mgrid[0:h, 0:w]
        frame_sum = rng.normal(0, 1, (h, w)) + 50.0 * (np.hypot(yy - h / 2, xx - w / 2) < h / 3)
        spots = np.array([[w / 2, h / 2], [w / 2 + 10, h / 2]])
        times = {(): [], wide: []}
        for _ in range(args.repeats):
            for widths in ((), wide):
                build.LIT_WIDE = widths
                t0 = time.perf_counter()
                build.lit_mask(frame_sum, spots, 1e-4, dark_noise=(1.0 / 4096, 4096), frame_peak=frame_sum, beams=4096)
                times[widths].append(time.perf_counter() - t0)
        build.LIT_WIDE = wide
        a, b = np.median(times[()]), np.median(times[wide])
        print(f"| {h} x {w} | {a:.3f} | {b:.3f} | {b / a:.2f} |", flush=True)


if __name__ == "__main__":
    main()
