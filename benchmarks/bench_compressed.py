"""`compressed` against `dense` as m grows (issue 6): time, memory, error.

Two kinds of T:

- ``box``: the simulated box scene (exact transport), Gaussian noise sigma x max |T|
  added; errors against the simulator's truth and against dense;
- ``kernel``: the synthetic ISF of :mod:`ilt.sim.kernel` for sizes the simulator
  cannot reach, written block by block into a memory-mapped ``T.npy``, left clean
  (sigma is the tolerance only); the compressed solve's residual against T is the
  error figure (dense is timed where it fits, with ``--dense``).

Compression uses the noise sigma as its tolerance (``--noise``), or 1e-8 of max |T|
for sigma = 0, and orders its tree by the samples' pixels (box) or 3-D positions
(kernel). Prints one row per case: median seconds of building C1 and splitting
16 photos into 8 bounces, memory of the operator (compressed: the HODLR form; dense:
its m x m factors), ranks of the top and second levels, and errors.

    python benchmarks/bench_compressed.py box --sizes 3072,6075 --noise 0,1e-6,1e-4
    python benchmarks/bench_compressed.py kernel --sizes 16384 --noise 1e-4 --dense
"""

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from ilt.evaluate.bench import median_time, scene_batch
from ilt.evaluate.errors import relative_errors
from ilt.sim import make_scene
from ilt.sim.kernel import corner_kernel_isf, corner_points
from ilt.transport.compressed import compressed_operator
from ilt.transport.operators import bounce_images, cancellation_operator


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("kind", choices=("box", "kernel"))
    parser.add_argument("--sizes", default="3072")
    parser.add_argument("--noise", default="0,1e-6,1e-4")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--dense", action="store_true", help="kernel: also time dense (needs 2 x 8 m^2 bytes)")
    args = parser.parse_args()
    print(f"{'T':>6} {'m':>6} {'sigma':>6} {'solver':>10} {'seconds':>8} {'MiB':>7} {'ranks':>12} "
          f"{'bounce err':>10} {'vs dense':>9} {'residual':>9}", flush=True)
    for size in map(int, args.sizes.split(",")):
        with tempfile.TemporaryDirectory() as tmp:
            if args.kind == "box":
                t0 = time.perf_counter()
                scene = make_scene("box", beams=size)
                clean = scene.isf()[0]
                photos, truth = scene_batch(scene, 16, 8)
                points = scene.samples
                print(f"# box m = {scene.m}: simulated in {time.perf_counter() - t0:.1f} s", flush=True)
            else:
                t0 = time.perf_counter()
                n = round(np.sqrt(size / 3))
                clean = corner_kernel_isf(Path(tmp) / "T.npy", n)
                photos, truth = np.random.default_rng(1).uniform(size=(3 * n * n, 16)), None
                points = corner_points(n)[0]
                print(f"# kernel m = {clean.shape[0]}: written to a memory map in {time.perf_counter() - t0:.1f} s",
                      flush=True)
            m = clean.shape[0]
            for sigma in map(float, args.noise.split(",")):
                T = clean
                if sigma and args.kind == "box":
                    T = clean + sigma * np.abs(clean).max() * np.random.default_rng(2).normal(size=clean.shape)
                if args.kind == "box" or sigma == float(args.noise.split(",")[0]):
                    dense_bounces = None  # kernel: T is the same for every sigma, dense runs once
                if (args.kind == "box" or args.dense) and dense_bounces is None:
                    seconds, (op, dense_bounces) = median_time(
                        lambda: (lambda o: (o, bounce_images(o, photos, 8).bounces))(cancellation_operator(T)),
                        args.repeats)
                    err = relative_errors(dense_bounces, truth).max() if truth is not None else float("nan")
                    print(f"{args.kind:>6} {m:>6} {sigma:>6.0e} {'dense':>10} {seconds:>8.2f} "
                          f"{op.factors.nbytes / 2**20:>7.0f} {'':>12} {err:>10.2e} {'':>9} {'':>9}", flush=True)
                    del op
                tol = sigma if sigma else None  # T's largest entry: 1 (its diagonal; box: 0.9-1)
                seconds, (op, bounces) = median_time(
                    lambda: (lambda o: (o, bounce_images(o, photos, 8).bounces))(compressed_operator(T, tol, points)),
                    args.repeats)
                f = op.figures
                ranks = "/".join(str(r[1]) for r in f["ranks_by_level"][:3])
                err = relative_errors(bounces, truth).max() if truth is not None else float("nan")
                vs = relative_errors(bounces, dense_bounces).max() if dense_bounces is not None else float("nan")
                print(f"{args.kind:>6} {m:>6} {sigma:>6.0e} {'compressed':>10} {seconds:>8.2f} "
                      f"{f['memory_bytes'] / 2**20:>7.0f} {ranks:>12} {err:>10.2e} {vs:>9.1e} "
                      f"{f['solve_residual']:>9.1e}  (compression {f['compression_seconds']:.1f} s)", flush=True)
                del T, op


if __name__ == "__main__":
    main()
