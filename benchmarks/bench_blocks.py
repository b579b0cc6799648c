"""`blocks` against `dense` on scenes of k independent objects (issue 6).

m points in total, split into k separate M scenes of m/k points (T block diagonal
after a random permutation). Prints median times of building C1 and splitting a
batch of photos into 8 bounces, the ratio dense/blocks next to k^2 (the flop ratio
of one m^3 LU against k LUs of (m/k)^3), and the largest difference between them.

    python benchmarks/bench_blocks.py [--m 2048] [--repeats 3]
"""

import argparse

import numpy as np
import scipy.linalg

from ilt.evaluate.bench import median_time
from ilt.sim import make_scene
from ilt.transport.operators import bounce_images
from ilt.transport.solvers import build_operator


def objects(m: int, k: int, seed: int = 0):
    scenes = [make_scene("m", beams=m // k, albedo=0.5 + 0.4 * i / max(k - 1, 1)) for i in range(k)]
    T = scipy.linalg.block_diag(*[s.isf()[0] for s in scenes])
    order = np.random.default_rng(seed).permutation(T.shape[0])
    return T[np.ix_(order, order)]




def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--m", type=int, default=2048)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(f"{'k':>3} {'m':>6} {'dense s':>8} {'blocks s':>9} {'dense/blocks':>12} {'k^2':>5} {'max diff':>9}")
    for k in (1, 2, 4, 8, 16):
        T = objects(args.m, k)
        photos = np.random.default_rng(1).uniform(size=(T.shape[0], 16))

        def run(solver):
            op, _ = build_operator(T, solver)
            return bounce_images(op, photos, 8).bounces

        dense_s, dense = median_time(lambda: run("dense"), args.repeats)
        blocks_s, blocks = median_time(lambda: run("blocks"), args.repeats)
        diff = np.abs(dense - blocks).max() / np.abs(dense).max()
        print(f"{k:>3} {T.shape[0]:>6} {dense_s:>8.3f} {blocks_s:>9.3f} {dense_s / blocks_s:>12.1f} {k * k:>5} {diff:>9.1e}")


if __name__ == "__main__":
    main()
