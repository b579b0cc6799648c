"""What judging the bounces against their noise costs, and how well it predicts the error.

    python benchmarks/bench_bounce_noise.py [--sizes 64,256,1024,4096] [--noise 3e-3] [--repeats 3]

For the flatland "M" of m beams (ilt.sim), T + N(0, sigma^2) on its unit columns and the
three photos: the decomposition itself (factorise T, split the photos, 8 bounces) against
the draws that measure each bounce sample's noise (ilt.decompose.noise.bounce_sigma, as
many draws as `ilt decompose` takes at that m), both timed in this process (medians over
--repeats), and the draws' predicted error of bounces 1-3 (the 2-norm of their sigma)
against the true error (the simulator's exact bounces): the ratio should be near 1.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from threadpoolctl import threadpool_info

from ilt.decompose.noise import bounce_sigma, draws_for
from ilt.sim.scene import make_scene
from ilt.transport.operators import bounce_images, cancellation_operator

KINDS = ("flashlight", "room", "projector")


def split(op, values, n):
    return bounce_images(op, values, n)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="64,256,1024,4096")
    parser.add_argument("--noise", type=float, default=3e-3)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    threads = sum(p.get("num_threads", 0) for p in threadpool_info() if p.get("user_api") == "blas")
    print(f"BLAS threads {threads}; noise {args.noise:g} on T's unit columns; medians of {args.repeats}")
    print(f"{'m':>6} {'draws':>5} {'decompose s':>12} {'draws s':>9} {'ratio':>6}   predicted / true error, bounces 1-3")
    for m in map(int, args.sizes.split(",")):
        scene = make_scene("m", m)
        T, _ = scene.isf()
        T = T / np.linalg.norm(T, axis=0)
        noisy = T + np.random.default_rng(m).normal(scale=args.noise, size=T.shape)
        photos, truths = zip(*(scene.photo(kind, 8) for kind in KINDS))
        L = np.stack(photos, axis=1)
        truth = np.stack(truths, axis=2)       # (8, m, 3)
        base, drawn = [], []
        for r in range(args.repeats):
            start = time.perf_counter()
            dec = bounce_images(cancellation_operator(noisy), L, 8)
            base.append(time.perf_counter() - start)
            start = time.perf_counter()
            (sigma,) = bounce_sigma(noisy, args.noise, [dec], [L], split, seed=r)
            drawn.append(time.perf_counter() - start)
        error = np.linalg.norm((dec.bounces - truth).reshape(8, -1), axis=1)
        predicted = np.linalg.norm(sigma.reshape(8, -1), axis=1)
        b, d = statistics.median(base), statistics.median(drawn)
        ratios = " ".join(f"{p / e:.2f}" for p, e in zip(predicted[:3], error[:3]))
        print(f"{m:>6} {draws_for(m):>5} {b:>12.3f} {d:>9.3f} {d / b:>6.1f}   {ratios}")


if __name__ == "__main__":
    main()
