"""What the lit test costs a build (ilt/isf/build.py ``lit_mask``), with and without its wide one-sided means.

    python benchmarks/bench_lit.py [--sizes 960x1280,3000x4000] [--repeats 5]

The lit test runs once per build-isf, on the frames' sum (spots/sum.exr) and their
largest local means (spots/peak.exr). This times it on a synthetic noisy sum of each size
(a lit disc over a dark background, sigma 1 a pixel, the noise model given as it is in a
build), first with the 5 x 5 test and the peak test alone (``LIT_WIDE = ()``), then as
build-isf runs it (the 11 x 11 and 21 x 21 corner windows too), alternating, and prints the
medians and their ratio; then, without the peak test (the sum itself as the largest
frame lights this synthetic sum far past the disc), with and without the noisy silhouette's
peel (``SILHOUETTE_PEELS = 0``: the disc's edge is a silhouette, and the lit test lets in
2 px of background past it). For scale: a build reads every beam frame once, so at m = 4096 on
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

    wide, peels = build.LIT_WIDE, build.SILHOUETTE_PEELS
    rng = np.random.default_rng(0)
    print(f"| frame | lit test without the wide means (s) | with them, as built (s) | ratio |\n|---|---|---|---|")
    rows = []
    for size in args.sizes.split(","):
        h, w = map(int, size.split("x"))
        yy, xx = np.mgrid[0:h, 0:w]
        frame_sum = rng.normal(0, 1, (h, w)) + 50.0 * (np.hypot(yy - h / 2, xx - w / 2) < h / 3)
        spots = np.array([[w / 2, h / 2], [w / 2 + 10, h / 2]])
        times = {(): [], wide: []}
        for _ in range(args.repeats):
            for key, widths in (((), ()), (wide, wide)):
                build.LIT_WIDE = widths
                t0 = time.perf_counter()
                build.lit_mask(frame_sum, spots, 1e-4, dark_noise=(1.0 / 4096, 4096), frame_peak=frame_sum, beams=4096)
                times[key].append(time.perf_counter() - t0)
            build.LIT_WIDE = wide
            # the peel, without the peak test (which lights this synthetic sum far past the disc)
            for key, peeled in (("unpeeled", 0), ("peeled", peels)):
                build.SILHOUETTE_PEELS = peeled
                t0 = time.perf_counter()
                _, info = build.lit_mask(frame_sum, spots, 1e-4, dark_noise=(1.0 / 4096, 4096))
                times.setdefault(key, []).append(time.perf_counter() - t0)
            build.SILHOUETTE_PEELS = peels
        a, b = np.median(times[()]), np.median(times[wide])
        c, d = np.median(times["unpeeled"]), np.median(times["peeled"])
        print(f"| {h} x {w} | {a:.3f} | {b:.3f} | {b / a:.2f} |", flush=True)
        rows.append(f"| {h} x {w} | {c:.3f} | {d:.3f} | {d / c:.2f} | {info['silhouette_pixels']} |")
    print(f"\n| frame | lit test without the silhouette's peel (s) | with it, as built (s) | ratio | pixels peeled |\n"
          f"|---|---|---|---|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
