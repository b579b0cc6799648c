"""Cells that end at the scene's concave folds, read from the frames (build-isf's default;
``--no-fold-cells`` turns it off).

Cells are the spots' Voronoi regions, which know nothing of the surface: a spot beside a
fold makes a cell that holds pixels of both facets, whose light differs (docs/fullres.md,
"A spot on a fold"). The frames show the fold. The light of the beams farther than one
spot spacing from a pixel has a valley at a concave fold: a facet lights the facet it faces
the less, the nearer the fold, as that light leaves it at grazing angles. The near beams
are left out because their own indirect light peaks about their spots and hides it.

The far light is the scan's sum (``sum.exr``) less each frame's disc about its spot
(:func:`near_chunk`, reading the disc's rows only; :func:`far_from_sum`), or, where the sum
has no such use (no ``sum.exr``, a dark frame taken off it, fireflies crowding it:
:data:`SUM_OUTLIER_SHARE`), each frame summed where it is far from its spot
(:func:`far_chunk`, a pass over the frames).
:func:`valley_barriers` smooths that light by a Gaussian of a quarter spacing and takes the
larger eigenvalue of its Hessian, over its noise (the frames' noise model through the same
filters). Barriers are its ridge pixels (local maxima across the valley) above
:data:`FOLD_LOW` sigma, connected to ones above :data:`FOLD_SIGMAS`. :func:`fold_cells`
gives each pixel to the nearest spot in its own region of the lit mask that the barriers
leave (4-connected), except each spot's own disc, which stays its own (a barrier between
a spot 2 px from a fold and its own pixels gave them to the neighbour); a spot on a barrier
pixel is in the region of the nearest pixel that is not one.
"""

from __future__ import annotations

import numpy as np

#: a barrier's pixels stand this many sigmas above the noise somewhere along it ...
FOLD_SIGMAS = 4.5
#: ... and this many everywhere
FOLD_LOW = 3.0
#: the far light is the scan's sum less each frame's disc unless the frames' fireflies
#: (:func:`ilt.isf.outliers.fresh_outliers`, times the frames summed) would be this share of
#: its pixels: past it they stand side by side there, where the isolated test cannot tell
#: them, and each frame is read again whole with its own replaced
SUM_OUTLIER_SHARE = 1e-3
#: the Gaussian's sigma as a share of the spot spacing, and its bounds (px)
SMOOTH_SHARE, SMOOTH_MIN, SMOOTH_MAX = 0.25, 2.0, 8.0


def spacing_of(centroids: np.ndarray) -> float:
    """The median distance (px) from a spot to its nearest neighbour."""
    from scipy.spatial import cKDTree

    if len(centroids) < 2:
        return float("inf")
    return float(np.median(cKDTree(centroids).query(centroids, k=2)[0][:, 1]))


def far_chunk(files, shape, centres, spacing, noise=None, discs=None):
    """Worker: the chunk's frames summed where farther than ``spacing`` from their own spot,
    (H, W) float64, each frame's isolated outliers replaced first as build-isf's own pass
    replaces them (:func:`ilt.isf.outliers.clamp_isolated`, with ``noise`` and each spot's
    disc radius in ``discs``): a firefly left in would read as a valley's rim."""
    from ilt.io.frames import load_frame
    from ilt.isf.outliers import clamp_isolated

    light = np.zeros(shape)
    frame = np.empty(shape)
    for k, (path, centre) in enumerate(zip(files, centres)):
        load_frame(path, shape, out=frame)
        if noise is not None:
            clamp_isolated(frame, noise, centre, float(discs[k]))
        light += frame
        near = _disc(centre, shape, spacing)          # and the disc about the spot taken back out
        if near is not None:
            window, inside = near
            light[window][inside] -= frame[window][inside]
    return light


def near_chunk(files, shape, centres, radius):
    """Worker: (H, W) float64, the chunk's frames summed within ``radius`` of their own
    spot (``centres``), each read only over the rows of that disc; a centre of NaN: the
    whole frame (a beam build-isf dropped, whose frame the scan's sum holds). The scan's
    sum less these is the far light (:func:`far_from_sum`) without a second full read."""
    from ilt.io.frames import load_frame, read_frame_rows

    light = np.zeros(shape)
    for path, centre in zip(files, centres):
        if not np.all(np.isfinite(centre)):
            light += load_frame(path, shape)
            continue
        near = _disc(centre, shape, radius)
        if near is not None:
            (rows, cols), inside = near
            light[rows, cols][inside] += read_frame_rows(path, shape, (rows.start, rows.stop))[:, cols][inside]
    return light


def sum_noise(noise, frames: int):
    """The noise model of a sum of ``frames`` frames of the level of its mean (each knot's
    level and variance times ``frames``; photon noise's slope is a sum's too)."""
    from ilt.isf.noise import FrameNoise

    return FrameNoise(tuple(frames * np.asarray(noise.levels)), tuple(frames * np.asarray(noise.variances)),
                      noise.frames, noise.pixels, noise.bins, noise.slope)


def far_from_sum(frame_sum: np.ndarray, near: np.ndarray, noise, frames: int) -> np.ndarray:
    """The far light from the scan's sum (``sum.exr``) less ``near`` (:func:`near_chunk`),
    its isolated outliers replaced on the sum's noise (a firefly of any frame stands out of
    the sum as of its frame; one too faint to, smoothed by the valley test's Gaussian of at
    least 2 px, stays under its 3 sigma)."""
    from ilt.isf.outliers import clamp_isolated

    light = frame_sum - near
    clamp_isolated(light, sum_noise(noise, frames))
    return light


def _disc(centre, shape, radius: float):
    """The window about ``centre`` (x, y) and the mask of its pixels within ``radius``
    (inclusive) of it, or None when the disc misses the frame."""
    x, y = centre
    reach = int(np.ceil(radius))
    r0, r1 = max(0, int(np.floor(y)) - reach), min(shape[0], int(np.ceil(y)) + reach + 1)
    c0, c1 = max(0, int(np.floor(x)) - reach), min(shape[1], int(np.ceil(x)) + reach + 1)
    if r0 >= r1 or c0 >= c1:
        return None
    rows, cols = np.ogrid[r0:r1, c0:c1]
    return (slice(r0, r1), slice(c0, c1)), (cols - x) ** 2 + (rows - y) ** 2 <= radius**2


def far_counts(centroids: np.ndarray, shape, spacing: float) -> np.ndarray:
    """(H, W) float64: how many frames count in the far light at each pixel (those whose
    spot is farther than ``spacing``): every frame less the discs about the spots."""
    count = np.full(shape, float(len(centroids)))
    for centre in centroids:
        near = _disc(centre, shape, spacing)
        if near is not None:
            count[near[0]] -= near[1]
    return count


def valley_barriers(light: np.ndarray, count: np.ndarray, noise, lit: np.ndarray, spacing: float) -> np.ndarray:
    """(H, W) bool: the ridge pixels of the far light's valleys (module docstring), inside ``lit``."""
    from scipy.ndimage import gaussian_filter, label

    sigma = float(np.clip(SMOOTH_SHARE * spacing, SMOOTH_MIN, SMOOTH_MAX))
    smooth = gaussian_filter(light, sigma)
    gy, gx = np.gradient(smooth)
    gyy, gyx = np.gradient(gy)
    gxx = np.gradient(gx, axis=1)
    valley = 0.5 * (gxx + gyy) + np.sqrt(0.25 * (gxx - gyy) ** 2 + gyx**2)
    # its noise: each pixel's variance (the frames counted there at the dark level, and the
    # photon noise of their light) through the filters' squared weights
    dark = float(noise.pixel_variance(np.zeros(1))[0])
    variance = gaussian_filter(count * dark + noise.slope * np.maximum(light, 0.0), sigma)
    z = valley / np.sqrt(_weight(sigma) * np.maximum(variance, 1e-300))
    # a local maximum across the valley (along the eigenvector of the larger eigenvalue)
    theta = 0.5 * np.arctan2(2.0 * gyx, gxx - gyy)
    dx, dy = np.rint(np.cos(theta)).astype(int), np.rint(np.sin(theta)).astype(int)
    height, width = z.shape
    rows, cols = np.mgrid[:height, :width]
    ahead = z[np.clip(rows + dy, 0, height - 1), np.clip(cols + dx, 0, width - 1)]
    behind = z[np.clip(rows - dy, 0, height - 1), np.clip(cols - dx, 0, width - 1)]
    ridge = lit & (z >= ahead) & (z >= behind)
    # (the filters mirror the light at the frame's edge: where it falls towards the edge
    # that makes a valley along it, a barrier that encloses no spot, and moves no pixel)
    weak, strong = ridge & (z > FOLD_LOW), ridge & (z > FOLD_SIGMAS)
    regions, _ = label(weak, np.ones((3, 3), bool))
    keep = np.zeros(regions.max() + 1, bool)
    keep[np.unique(regions[strong])] = True
    keep[0] = False
    return keep[regions]


def _weight(sigma: float) -> float:
    """The sum of squares of the filters' weights (Gaussian, then the second difference):
    a white noise's variance in the valley-ness, per unit of a pixel's."""
    from scipy.ndimage import gaussian_filter

    size = 2 * int(np.ceil(5 * sigma)) + 5
    delta = np.zeros((size, size))
    delta[size // 2, size // 2] = 1.0
    second = np.gradient(np.gradient(gaussian_filter(delta, sigma), axis=1), axis=1)
    return float(np.sum(second**2))


def fold_cells(labels: np.ndarray, centroids: np.ndarray, barriers: np.ndarray, spacing: float) -> tuple[np.ndarray, dict]:
    """The cells with ``barriers`` (module docstring): (H, W) labels and a record."""
    from scipy.ndimage import label
    from scipy.spatial import cKDTree

    height, width = labels.shape
    lit = labels >= 0
    disc = max(3.0, SMOOTH_SHARE * spacing)
    regions, count = label(lit & ~barriers)                                   # 4-connected
    spot = np.clip(np.floor(centroids + 0.5).astype(int), 0, [width - 1, height - 1])
    spot_region = regions[spot[:, 1], spot[:, 0]]
    for i in np.flatnonzero(spot_region == 0):
        # a spot on a barrier pixel: the region of the nearest pixel about it that is none
        # (region 0 gave its cell to its neighbours, bar its disc)
        spot_region[i] = _nearest_region(regions, spot[i], int(np.ceil(disc)))
    flat_regions, flat_labels = regions.ravel(), labels.ravel()
    out = flat_labels.copy()
    # a pixel whose cell's spot (its nearest) is in its region keeps it: that spot is its
    # nearest there too. The others, but for each spot's own disc, go to the nearest spot
    # of their region (if it has one)
    moving = np.flatnonzero((flat_regions > 0) & lit.ravel())
    moving = moving[spot_region[flat_labels[moving]] != flat_regions[moving]]
    if moving.size:
        near, _ = cKDTree(centroids).query(np.column_stack([moving % width, moving // width]),
                                           distance_upper_bound=disc * (1 + 1e-9))
        moving = moving[~np.isfinite(near)]
    moving = moving[np.argsort(flat_regions[moving], kind="stable")]
    starts = np.flatnonzero(np.r_[True, np.diff(flat_regions[moving]) != 0])
    for pixels in np.split(moving, starts[1:]) if moving.size else []:
        mine = np.flatnonzero(spot_region == flat_regions[pixels[0]])
        if mine.size:
            _, nearest = cKDTree(centroids[mine]).query(np.column_stack([pixels % width, pixels // width]))
            out[pixels] = mine[nearest]
    out = out.reshape(labels.shape)
    return out, {"barrier_pixels": int(barriers.sum()), "moved_pixels": int(np.count_nonzero(out != labels)),
                 "regions": int(count)}


def _nearest_region(regions: np.ndarray, pixel: np.ndarray, reach: int) -> int:
    """The region (> 0) of the pixel nearest ``pixel`` (x, y) within ``reach`` px, or 0."""
    x, y = int(pixel[0]), int(pixel[1])
    r0, c0 = max(0, y - reach), max(0, x - reach)
    window = regions[r0:y + reach + 1, c0:x + reach + 1]
    rows, cols = np.nonzero(window)
    if rows.size == 0:
        return 0
    k = np.argmin((rows + r0 - y) ** 2 + (cols + c0 - x) ** 2)
    return int(window[rows[k], cols[k]])


__all__ = ["FOLD_LOW", "FOLD_SIGMAS", "SUM_OUTLIER_SHARE", "far_chunk", "far_counts", "far_from_sum", "fold_cells", "near_chunk",
           "spacing_of", "sum_noise", "valley_barriers"]
