"""`compressed` against `dense` as m grows (issue 6): time, memory, error.

Two kinds of T:

- ``box``: the simulated box scene (exact transport), Gaussian noise sigma x max |T|
  added; errors against the simulator's truth and against dense;
- ``kernel``: a synthetic ISF for sizes the simulator cannot reach, written block by
  block into a memory-mapped ``T.npy``: the three inside faces of a unit cube's
  corner, n x n points each, point-to-point form factors
  ``F[i, j] = cos_i cos_j area / (pi r^2)`` (zero within a face), albedo 0.5, and
  ``T = (I + A) T1`` (the forward tracer truncated at 2 bounces), left clean (sigma is
  the tolerance only: adding noise would need T in memory); the compressed solve's
  residual against T is the error figure (dense is timed where it fits).

Compression uses the noise sigma as its tolerance (``--noise``), or 1e-10 of max |T|
for sigma = 0. Prints one row per case: median seconds of building C1 and splitting
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

from ilt.bench import median_time, scene_batch
from ilt.compressed import compressed_operator, grid_points
from ilt.evaluate import relative_errors
from ilt.sim import make_scene
from ilt.transport import bounce_images, cancellation_operator


def box_points(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres (3 n^2, 3), normals and face of the cube corner's three faces, each in
    scanline order of its n x n cells (the layout (3n, n), as the box scene's)."""
    cells = (np.arange(n) + 0.5) / n
    rows, cols = np.meshgrid(cells, cells, indexing="ij")
    faces = [np.stack([cols, np.zeros_like(rows), rows[::-1]], -1),  # wall y = 0
             np.stack([cols, rows, np.zeros_like(rows)], -1),  # floor z = 0
             np.stack([np.zeros_like(rows), cols, rows[::-1]], -1)]  # wall x = 0
    normals = np.repeat(np.eye(3)[[1, 2, 0]], n * n, axis=0)
    return np.concatenate([f.reshape(-1, 3) for f in faces]), normals, np.repeat(np.arange(3), n * n)


def kernel_isf(path: Path, n: int, albedo: float = 0.5, rows: int = 1024) -> np.ndarray:
    """Write the synthetic ISF (module docstring) of m = 3 n^2 points to ``path``; return
    it memory-mapped read-only."""
    x, normal, face = box_points(n)
    m, area = len(x), 1.0 / n**2
    T = np.lib.format.open_memmap(path, mode="w+", dtype=np.float64, shape=(m, m))
    for i0 in range(0, m, rows):
        d = x[None, :, :] - x[i0:i0 + rows, None, :]  # from receiver i to sender j
        r2 = np.einsum("ijk,ijk->ij", d, d)
        np.maximum(r2, 1e-30, out=r2)
        cos_i = np.einsum("ijk,ik->ij", d, normal[i0:i0 + rows])
        cos_j = -np.einsum("ijk,jk->ij", d, normal)
        block = albedo * np.clip(cos_i, 0, None) * np.clip(cos_j, 0, None) * area / (np.pi * r2 * r2)
        block[face[i0:i0 + rows, None] == face[None, :]] = 0.0
        block[np.arange(block.shape[0]), np.arange(i0, i0 + block.shape[0])] = 1.0  # T = (I + A) T1, T1 = I
        T[i0:i0 + rows] = block
    T.flush()
    del T
    return np.load(path, mmap_mode="r")


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
                layout = scene.layout
                print(f"# box m = {scene.m}: simulated in {time.perf_counter() - t0:.1f} s", flush=True)
            else:
                t0 = time.perf_counter()
                n = round(np.sqrt(size / 3))
                clean = kernel_isf(Path(tmp) / "T.npy", n)
                photos, truth, layout = np.random.default_rng(1).uniform(size=(3 * n * n, 16)), None, (3 * n, n)
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
                points = grid_points(layout, m)
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
