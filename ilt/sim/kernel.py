"""A synthetic ISF for sizes past the simulator, written block by block to a
memory-mapped ``T.npy``.

The simulator builds T densely (``(I - A)^-1`` and the truth need several m x m
arrays: 43 GiB at m = 32768). This kernel needs none: the three inside faces of a unit
cube's corner, n x n points each, point-to-point form factors
``F[i, j] = cos_i cos_j area / (pi r^2)`` (zero within a face), albedo 0.5, and
``T = (I + A) T1`` with ``T1 = I`` (the forward tracer truncated at 2 bounces), a block
of rows at a time. It has the box's structure (faces meeting along edges, light that
varies smoothly away from them) and no truth beyond T itself: a solve is checked
against T.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def corner_points(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres (3 n^2, 3), normals (3 n^2, 3) and face (3 n^2,) of the cube corner's
    three faces, each in scanline order of its n x n cells (the layout (3n, n), as the
    box scene's)."""
    cells = (np.arange(n) + 0.5) / n
    rows, cols = np.meshgrid(cells, cells, indexing="ij")
    faces = [np.stack([cols, np.zeros_like(rows), rows[::-1]], -1),  # wall y = 0
             np.stack([cols, rows, np.zeros_like(rows)], -1),  # floor z = 0
             np.stack([np.zeros_like(rows), cols, rows[::-1]], -1)]  # wall x = 0
    normals = np.repeat(np.eye(3)[[1, 2, 0]], n * n, axis=0)
    return np.concatenate([f.reshape(-1, 3) for f in faces]), normals, np.repeat(np.arange(3), n * n)


def corner_kernel_isf(path: str | Path, n: int, noise: float = 0.0, seed: int = 0, albedo: float = 0.5,
                      rows: int = 512) -> np.ndarray:
    """Write the kernel ISF (module docstring) of m = 3 n^2 points to the scratch file
    ``path`` (the benchmarks' temporary directory), with Gaussian noise of ``noise``
    per entry if above 0; return it memory-mapped read-only. Memory: a few
    ``rows x m`` blocks."""
    x, normal, face = corner_points(n)
    m, area = len(x), 1.0 / n**2
    rng = np.random.default_rng(seed)
    T = np.lib.format.open_memmap(path, mode="w+", dtype=np.float64, shape=(m, m))
    for i0 in range(0, m, rows):
        d = x[None, :, :] - x[i0:i0 + rows, None, :]  # from receiver i to sender j
        r2 = np.maximum(np.einsum("ijk,ijk->ij", d, d), 1e-30)
        cos_i = np.clip(np.einsum("ijk,ik->ij", d, normal[i0:i0 + rows]), 0, None)
        cos_j = np.clip(-np.einsum("ijk,jk->ij", d, normal), 0, None)
        block = albedo * cos_i * cos_j * (area / np.pi) / (r2 * r2)
        block[face[i0:i0 + rows, None] == face[None, :]] = 0.0
        block[np.arange(block.shape[0]), np.arange(i0, i0 + block.shape[0])] = 1.0
        if noise:
            block += noise * rng.standard_normal(block.shape)
        T[i0:i0 + rows] = block
    T.flush()
    del T
    return np.load(path, mmap_mode="r")
