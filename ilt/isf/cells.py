"""Cells: the image region each sample stands for, and integrating frames over them.

The paper reads each beam image at the m spot pixels, which is right only when each
spot covers its whole patch. A laser spot is much smaller than the beam spacing, so
the point sample of the spot's own pixel counts the spot's peak radiance as if the
whole patch glowed that bright, and the interreflected light (spread evenly over the
patch) is under-counted by the ratio of spot area to patch area. Integrating every
image over the *cell* of each spot (its Voronoi region in image space among the lit
pixels) counts the spot's whole flux and the interreflected flux over the same area,
which is the discrete transport of paper Eq. (3) with cells as the patches.

A label image ``cells`` (H, W) int32 holds, per pixel, the row of T whose cell it
belongs to, -1 outside every cell. Integrating is a sparse product: O(pixels in cells)
per frame.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
from scipy.spatial import cKDTree


def voronoi_cells(centroids: np.ndarray, frame_shape: tuple[int, int], lit: np.ndarray | None = None,
                  max_radius: float | None = None, threads: int = 1) -> np.ndarray:
    """Label every pixel with its nearest centroid.

    centroids: (m, 2) float64 pixel (x, y); frame_shape: (H, W);
    lit: (H, W) bool pixels that belong to the scene (None: all);
    max_radius: pixels farther than this from every centroid get -1 (None: no limit);
    threads: for the k-d tree queries (-1: all cores).
    Returns (H, W) int32 labels in 0..m-1, -1 outside every cell.
    """
    height, width = frame_shape
    flat = np.arange(height * width) if lit is None else np.flatnonzero(lit)  # unlit pixels: no query
    pixels = np.stack([flat % width, flat // width], axis=1).astype(np.float64)
    bound = np.inf if max_radius is None else float(max_radius)
    dist, index = cKDTree(np.asarray(centroids, dtype=np.float64)).query(pixels, distance_upper_bound=bound,
                                                                           workers=threads)
    labels = np.full(height * width, -1, dtype=np.int32)
    labels[flat] = np.where(np.isfinite(dist), index, -1)
    return labels.reshape(height, width)


def cell_operator(labels: np.ndarray, m: int | None = None) -> scipy.sparse.csr_matrix:
    """(m, H W) sparse 0/1 matrix summing a flattened frame over each cell, for
    :func:`integrate_with`; m = labels.max() + 1 by default."""
    flat = np.asarray(labels).ravel()
    inside = np.flatnonzero(flat >= 0)
    m = int(flat.max()) + 1 if m is None else m
    return scipy.sparse.csr_matrix((np.ones(inside.size), (flat[inside], inside)), shape=(m, flat.size))


def integrate(image: np.ndarray, labels: np.ndarray, m: int | None = None) -> np.ndarray:
    """Sum an image over each cell.

    image: (H, W) or (H, W, C); labels: (H, W) int as from :func:`voronoi_cells`.
    Returns (m,) or (m, C) float64, m = number of cells (labels.max() + 1 by default).
    """
    return integrate_with(image, cell_operator(labels, m))


def integrate_with(image: np.ndarray, operator: scipy.sparse.csr_matrix) -> np.ndarray:
    """:func:`integrate` with the operator built once (the per-frame cost is one sparse
    product over the pixels inside cells)."""
    image = np.asarray(image)
    return operator @ image.reshape(image.shape[0] * image.shape[1], -1)[:, 0] if image.ndim == 2 else \
        operator @ image.reshape(image.shape[0] * image.shape[1], -1)


def mosaic(values: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Paint each cell with its value per pixel (value / cell area): the camera-frame view
    of a vector of cell integrals, in the units of the frame it came from.

    values: (m,) or (m, k); labels: (H, W). Returns (H, W) or (H, W, k) float32, 0 outside cells.
    """
    values = np.asarray(values, dtype=np.float64)
    m = values.shape[0]
    area = np.bincount(labels[labels >= 0], minlength=m).astype(np.float64)
    per_pixel = values / np.maximum(area, 1).reshape(-1, *([1] * (values.ndim - 1)))
    out = np.zeros((*labels.shape, *values.shape[1:]), dtype=np.float32)
    inside = labels >= 0
    out[inside] = per_pixel[labels[inside]]
    return out
