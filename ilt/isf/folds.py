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
(:func:`far_chunk`, a pass over the frames). Where the spots lie on a line (a flatland
scan, :func:`spot_line`) a frame's near light is a stripe across its strip, not a disc: each
frame's pixels within a spacing of its spot *along the line* are left out, at any distance
across it. A disc one spacing wide left the strip's top and bottom rows in wherever the strip
is higher than a spacing, where the near spots' own light hid the fold's valley: on the M's
4x lattice (2e4 e-) the barriers of a 64-beam scan (12 px between spots, a 32-row strip)
stopped at the rows the discs did not reach, and a cell straddled the fold; 0.0939 against
the 48 beams' 0.0758, now 0.0653 (docs/fullres.md "A flatland spot's stripe").
:func:`valley_barriers` smooths that light by a Gaussian of a quarter spacing and takes the
larger eigenvalue of its Hessian, over its noise (the frames' noise model through the same
filters). Barriers are its ridge pixels (local maxima across the valley) above
:data:`FOLD_LOW` sigma, connected to ones above :data:`FOLD_SIGMAS`, whose light lies
:data:`FOLD_DEPTH` or more below the light a spot spacing either side (:func:`valley_depth`,
the median along the line), or :data:`LONG_DEPTH` along a line :data:`LONG_DEPTH_SPACINGS`
spacings long or more. The far light has shallow dips of its own, one a spacing, where
each frame's disc ends: frames bright enough, or noise-free ones judged against a nominal
noise, show them far above their noise, and on the M at 16 beams (spots 32 px apart) they
split 8 of its 16 cells midway between spots and along the spots' row (depth 0.01-0.13,
the folds 0.68-0.74; the M's folds at 48-384 beams 0.37-0.82). :func:`fold_cells`
gives each pixel to the nearest spot in its own region of the lit mask that the barriers
leave (4-connected), except each spot's own disc, which stays its own (a barrier between
a spot 2 px from a fold and its own pixels gave them to the neighbour); a spot on a barrier
pixel is in the region of the nearest pixel that is not one. A region that holds spots in
less than half the cells' median size (:data:`POCKET_CELLS`) is a pocket, no face: at a
crease's end, where the far light dips all about two close spots, its
barriers closed a ring about them and gave their cells' pixels outside it to spots 1.5-2
spacings away (the box's 4x lattice, a 72-beam scan 0.0945 -> 0.0900). A pocket's spots keep
their cells.

A fold's valley fades towards the light's edge, where fewer far beams light it, so its
barrier may stop short of that edge and enclose nothing. So each barrier that spans
:data:`LONG_SPACINGS` spacings has its two ends carried on along the valley's floor
(:func:`_follow`), and such a barrier also ends the cells whose pixels' straight lines to
their spots cross it (:func:`_line_of_sight`).
"""

from __future__ import annotations

import numpy as np

#: a barrier's pixels stand this many sigmas above the noise somewhere along it ...
FOLD_SIGMAS = 4.5
#: ... and this many everywhere
FOLD_LOW = 3.0
#: ... and its light lies this share below the mean of the light a spot spacing either side
#: across it (the median along the line; :func:`valley_depth`)
FOLD_DEPTH = 0.15
#: ... or, along a line of ridge pixels :data:`LONG_DEPTH_SPACINGS` spot spacings long or more, this
#: share: a fold crosses the scan, the far light's own dips are one spacing long (the box's floor
#: creases at 48 beams of its 4x lattice: 0.148-0.155 deep along 6.5 spacings; the longest dips
#: measured 0.093, the 16-beam M's convex fold, one spacing long, 0.13)
LONG_DEPTH, LONG_DEPTH_SPACINGS = 0.12, 3.0
#: the far light is the scan's sum less each frame's disc unless the frames' fireflies
#: (:func:`ilt.isf.outliers.fresh_outliers`, times the frames summed) would be this share of
#: its pixels: past it they stand side by side there, where the isolated test cannot tell
#: them, and each frame is read again whole with its own replaced
SUM_OUTLIER_SHARE = 1e-3
#: the Gaussian's sigma as a share of the spot spacing, and its bounds (px)
SMOOTH_SHARE, SMOOTH_MIN, SMOOTH_MAX = 0.25, 2.0, 8.0
#: the depth (:func:`valley_depth`) is read on the light smoothed by that share of the
#: spacing down to this (px), not :data:`SMOOTH_MIN`
DEPTH_SMOOTH_MIN = 1.0
#: a long barrier's ends carried on along its valley's floor where that is this many
#: sigmas above the noise, up to this many spot spacings and within this many px of its
#: axis (:func:`_follow`)
FOLD_FOLLOW, FOLLOW_SPACINGS, FOLLOW_WIDTH = 1.5, 4.0, 1.5
#: a barrier that encloses nothing still ends the cells whose lines to their spots cross
#: it, if it spans this many spot spacings (noise's stray ridges span under 1.6)
LONG_SPACINGS = 2.0


#: spots are on a line when they stray across its principal axis by less than this share of
#: their spacing along it, rms (a flatland plan's spots jitter across it by a pixel)
LINE_SPREAD = 0.25


def spot_line(centroids: np.ndarray) -> np.ndarray | None:
    """The unit direction (x, y) of the line the spots lie on (:data:`LINE_SPREAD`), or None:
    a grid, or fewer than 3 spots (ilt.refine reads its neighbours along the same line)."""
    centroids = np.asarray(centroids, dtype=np.float64)
    if len(centroids) < 3:
        return None
    centred = centroids - centroids.mean(axis=0)
    _, singular, axes = np.linalg.svd(centred, full_matrices=False)
    spacing = float(np.median(np.diff(np.sort(centred @ axes[0]))))
    if singular[1] / np.sqrt(len(centroids)) <= LINE_SPREAD * spacing:
        return axes[0]
    return None


def spacing_of(centroids: np.ndarray) -> float:
    """The median distance (px) from a spot to its nearest neighbour."""
    from scipy.spatial import cKDTree

    if len(centroids) < 2:
        return float("inf")
    return float(np.median(cKDTree(centroids).query(centroids, k=2)[0][:, 1]))


def far_chunk(files, shape, centres, spacing, noise=None, discs=None, along=None):
    """Worker: the chunk's frames summed where farther than ``spacing`` from their own spot,
    (H, W) float64, each frame's isolated outliers replaced first as build-isf's own pass
    replaces them (:func:`ilt.isf.outliers.clamp_isolated`, with ``noise`` and each spot's
    disc radius in ``discs``): a firefly left in would read as a valley's rim. ``along``: the
    spots' line (:func:`spot_line`): a stripe across it instead of the disc (module doc)."""
    from ilt.io.frames import load_frame
    from ilt.isf.outliers import clamp_isolated

    light = np.zeros(shape)
    frame = np.empty(shape)
    for k, (path, centre) in enumerate(zip(files, centres)):
        load_frame(path, shape, out=frame)
        if noise is not None:
            clamp_isolated(frame, noise, centre, float(discs[k]))
        light += frame
        near = _disc(centre, shape, spacing, along)   # and the disc about the spot taken back out
        if near is not None:
            window, inside = near
            light[window][inside] -= frame[window][inside]
    return light


def near_chunk(files, shape, centres, radius, taper: bool = False, along=None):
    """Worker: (H, W) float64, the chunk's frames summed within ``radius`` of their own
    spot (``centres``), each read only over the rows of that disc; a centre of NaN: the
    whole frame (a beam build-isf dropped, whose frame the scan's sum holds). The scan's
    sum less these is the far light (:func:`far_from_sum`) without a second full read.

    ``taper``: each frame all within ``radius``, none past twice that, and between the share
    ``1 - smoothstep`` of its distance from ``radius`` to ``2 radius``. The far light then has
    no step where a frame's disc ends. With the steps, a pixel's far light left out both
    spots either side of it and took in the next ones: it dipped midway between every two
    spots by itself, a valley of the lattice's period that noise hides and noise-free frames
    show (judged against :func:`nominal_noise`, the emulated rig's 16 beams split their cells
    there, the flashlight's bounce 2 0.07 -> 0.14). ``along``: the spots' line
    (:func:`spot_line`): the stripe across it (module doc), tapered by the distance along it."""
    from ilt.io.frames import load_frame, read_frame_rows

    light = np.zeros(shape)
    for path, centre in zip(files, centres):
        if not np.all(np.isfinite(centre)):
            light += load_frame(path, shape)
            continue
        near = _disc(centre, shape, 2 * radius if taper else radius, along)
        if near is not None:
            (rows, cols), inside = near
            values = read_frame_rows(path, shape, (rows.start, rows.stop))[:, cols]
            if taper:
                yy, xx = np.ogrid[rows, cols]
                distance = np.hypot(xx - centre[0], yy - centre[1]) if along is None else \
                    np.abs((xx - centre[0]) * along[0] + (yy - centre[1]) * along[1])
                t = np.clip((distance - radius) / radius, 0.0, 1.0)
                values = values * (1.0 - t * t * (3.0 - 2.0 * t))
            light[rows, cols][inside] += values[inside]
    return light


#: noise-free frames have no noise to judge a valley against: they are judged as if they had
#: photon noise of this many photo-electrons at their brightest pixel (the noisy sweep's,
#: benchmarks/noisy_sweep.py), so that better frames find at least the folds noisy ones do
NOMINAL_ELECTRONS = 2e4


def nominal_noise(brightest: float):
    """The noise model noise-free frames' folds are judged against (:data:`NOMINAL_ELECTRONS`
    at ``brightest``, the frames' brightest pixel): photon noise alone, a pixel's variance
    ``level * brightest / NOMINAL_ELECTRONS``."""
    from ilt.isf.noise import FrameNoise

    slope = float(brightest) / NOMINAL_ELECTRONS
    return FrameNoise(levels=(0.0, float(brightest)), variances=(0.0, slope * float(brightest)), frames=0,
                      pixels=0, bins=0, slope=slope)


def sum_noise(noise, frames: int):
    """The noise model of a sum of ``frames`` frames of the level of its mean (each knot's
    level and variance times ``frames``; photon noise's slope is a sum's too)."""
    from dataclasses import replace

    return replace(noise, levels=tuple(frames * np.asarray(noise.levels)),
                   variances=tuple(frames * np.asarray(noise.variances)))


def far_from_sum(frame_sum: np.ndarray, near: np.ndarray, noise, frames: int) -> np.ndarray:
    """The far light from the scan's sum (``sum.exr``) less ``near`` (:func:`near_chunk`),
    its isolated outliers replaced on the sum's noise (a firefly of any frame stands out of
    the sum as of its frame; one too faint to, smoothed by the valley test's Gaussian of at
    least 2 px, stays under its 3 sigma); ``noise`` None (noise-free frames): none replaced."""
    from ilt.isf.outliers import clamp_isolated

    light = frame_sum - near
    if noise is not None:       # noise-free frames: nothing to replace
        clamp_isolated(light, sum_noise(noise, frames))
    return light


def _disc(centre, shape, radius: float, along=None):
    """The window about ``centre`` (x, y) and the mask of its pixels within ``radius``
    (inclusive) of it, or None when the disc misses the frame. ``along``: the unit direction
    of the line the spots lie on (:func:`spot_line`): the pixels within ``radius`` of the spot
    along it, at any distance across (a flatland scan's spot lights a stripe across its strip)."""
    x, y = centre
    if along is not None:
        # the stripe's window: all of the frame across the line, its width along it
        ax, ay = abs(float(along[0])), abs(float(along[1]))
        height, width = shape
        r0, r1, c0, c1 = 0, height, 0, width
        if ax >= ay:
            half = (radius + max(y, height - 1 - y) * ay) / ax
            c0, c1 = max(0, int(np.floor(x - half))), min(width, int(np.ceil(x + half)) + 1)
        else:
            half = (radius + max(x, width - 1 - x) * ax) / ay
            r0, r1 = max(0, int(np.floor(y - half))), min(height, int(np.ceil(y + half)) + 1)
        if r0 >= r1 or c0 >= c1:
            return None
        rows, cols = np.ogrid[r0:r1, c0:c1]
        inside = np.abs((cols - x) * along[0] + (rows - y) * along[1]) <= radius
        return (slice(r0, r1), slice(c0, c1)), inside
    reach = int(np.ceil(radius))
    r0, r1 = max(0, int(np.floor(y)) - reach), min(shape[0], int(np.ceil(y)) + reach + 1)
    c0, c1 = max(0, int(np.floor(x)) - reach), min(shape[1], int(np.ceil(x)) + reach + 1)
    if r0 >= r1 or c0 >= c1:
        return None
    rows, cols = np.ogrid[r0:r1, c0:c1]
    return (slice(r0, r1), slice(c0, c1)), (cols - x) ** 2 + (rows - y) ** 2 <= radius**2


def far_counts(centroids: np.ndarray, shape, spacing: float, along=None) -> np.ndarray:
    """(H, W) float64: how many frames count in the far light at each pixel (those whose
    spot is farther than ``spacing``): every frame less the discs about the spots (``along``:
    the stripes across the spots' line, :func:`spot_line`)."""
    count = np.full(shape, float(len(centroids)))
    for centre in centroids:
        near = _disc(centre, shape, spacing, along)
        if near is not None:
            count[near[0]] -= near[1]
    return count


def valley_barriers(light: np.ndarray, count: np.ndarray, noise, lit: np.ndarray, spacing: float,
                    record: dict | None = None) -> np.ndarray:
    """(H, W) bool: the ridge pixels of the far light's valleys (module docstring), inside
    ``lit``. ``record``: a dict given gets ``shallow_lines``, how many lines stood above the
    noise but were shallower than :data:`FOLD_DEPTH` (:func:`valley_depth`)."""
    from scipy.ndimage import gaussian_filter, label, median

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
    # a fold's valley is deep, the lattice's own dimples are not (module docstring): each
    # line kept only if its median depth is FOLD_DEPTH or more
    lines = np.flatnonzero(keep)
    shallow = 0
    if lines.size:
        rows, cols = np.nonzero(keep[regions])
        # read on the light smoothed by a quarter spacing, under the test's 2 px where the
        # spots are closer than 8 px: there a fold's valley is as narrow as a spacing
        fine = SMOOTH_SHARE * spacing
        light_at = smooth if fine >= sigma else gaussian_filter(light, max(fine, DEPTH_SMOOTH_MIN))
        depth = valley_depth(light_at, rows, cols, theta[rows, cols], spacing)
        size = np.bincount(regions[rows, cols], minlength=regions.max() + 1)[lines]
        need = np.where(size >= LONG_DEPTH_SPACINGS * spacing, LONG_DEPTH, FOLD_DEPTH)
        low = lines[np.atleast_1d(median(depth, regions[rows, cols], lines)) < need]
        keep[low] = False
        shallow = int(low.size)
    if record is not None:
        record["shallow_lines"] = shallow
    barriers = keep[regions]
    _follow(barriers, ridge & lit & (z > FOLD_FOLLOW), z, LONG_SPACINGS * spacing,
            int(np.ceil(FOLLOW_SPACINGS * spacing)))
    return barriers


def valley_depth(smooth: np.ndarray, rows: np.ndarray, cols: np.ndarray, theta: np.ndarray, spacing: float) -> np.ndarray:
    """(n,) float64: how far the ``smooth`` light at each pixel (``rows``, ``cols``) lies
    below the mean of the light one ``spacing`` either side of it across the valley (along
    ``theta``, the direction of the Hessian's larger eigenvalue, bilinear, clipped to the
    frame): 1 - light / that mean. A straight ramp is 0 at any distance, and so is a ripple
    with the spots' period: the dips the far light makes by itself where each frame's disc
    ends, one a spacing, which noise-free or bright frames show far above their noise."""
    from scipy.ndimage import map_coordinates

    height, width = smooth.shape
    rim = np.zeros(len(rows))
    for sign in (1.0, -1.0):
        r = np.clip(rows + sign * spacing * np.sin(theta), 0, height - 1)
        c = np.clip(cols + sign * spacing * np.cos(theta), 0, width - 1)
        rim += 0.5 * map_coordinates(smooth, [r, c], order=1)
    return 1.0 - smooth[rows, cols] / np.maximum(rim, 1e-300)


def _follow(barriers: np.ndarray, floor: np.ndarray, z: np.ndarray, extent: float, steps: int) -> None:
    """The two ends of each barrier that spans ``extent`` px (its pixels farthest along its
    principal axis) carried on (in place) along the valley's ``floor`` pixels (its ridge,
    over :data:`FOLD_FOLLOW` sigma, lit): a step to the one of the pixels ahead (within 45
    degrees of the axis, outwards, and within :data:`FOLLOW_WIDTH` px of the axis through
    the end) that is on the floor, the highest ``z`` of them, while one is, up to ``steps``,
    ending where it meets another barrier pixel. A fold's valley fades towards the light's
    edge, where fewer far beams light it, and its barrier stops short of that edge,
    enclosing nothing; the floor still runs on there in a line, where noise's ridges do not.
    (The highest ridge pixel of a faint valley drifts with its noise: a step at 45 degrees
    each row carried the textured M's fold 5 columns into the facet it faces. A branch off
    the line is not carried on: ahead of its end the floor is the valley's shoulder, ridges
    of noise, and a branch carried across a cell gave that cell's far side to spots two
    cells away.)"""
    height, width = barriers.shape
    lines, boxes, long = _lines(barriers, extent)
    for i, box in enumerate(boxes, start=1):
        if not long[i]:
            continue
        rows, cols = np.nonzero(lines[box] == i)
        rows, cols = rows + box[0].start, cols + box[1].start
        points = np.column_stack([rows, cols]).astype(np.float64)
        axis = np.linalg.svd(points - points.mean(axis=0), full_matrices=False)[2][0]
        along = (points - points.mean(axis=0)) @ axis
        for end, direction in ((np.argmax(along), axis), (np.argmin(along), -axis)):
            r, c = start = int(rows[end]), int(cols[end])
            ahead = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1)
                     if (dr or dc) and (dr * direction[0] + dc * direction[1]) / np.hypot(dr, dc) > 0.7]
            def near_axis(p):
                return abs((p[0] - start[0]) * direction[1] - (p[1] - start[1]) * direction[0]) <= FOLLOW_WIDTH

            for _ in range(steps):
                options = [(r + dr, c + dc) for dr, dc in ahead
                           if 0 <= r + dr < height and 0 <= c + dc < width and floor[r + dr, c + dc]
                           and near_axis((r + dr, c + dc))]
                if not options:
                    break
                previous = (r, c)
                r, c = max(options, key=lambda p: z[p])
                if barriers[r, c]:
                    break
                around = barriers[max(r - 1, 0):r + 2, max(c - 1, 0):c + 2].sum() - barriers[previous]
                barriers[r, c] = True
                if around > 0:
                    break                                      # it met another barrier


#: a region holding spots in less than this share of the cells' median size is a pocket of the
#: barriers about close spots, not a face (:func:`fold_cells`): at the box's crease ends, two
#: spots 3 px apart in 48 px, the cells' median 158 px
POCKET_CELLS = 0.5


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
    # a region that holds spots in less than POCKET_CELLS of the cells' median size is a pocket
    # of the barriers about close spots, no face the scan sees: its spots keep their cells as
    # they were, and its pixels theirs
    area = np.bincount(flat_regions, minlength=count + 1)
    spots_in = np.bincount(spot_region, minlength=count + 1)
    sizes = np.bincount(flat_labels[flat_labels >= 0], minlength=len(centroids))
    cell = float(np.median(sizes[sizes > 0])) if np.any(sizes > 0) else 0.0
    small = (spots_in > 0) & (area < POCKET_CELLS * cell)
    small[0] = False
    pocket_spot = small[spot_region]
    keep = (pocket_spot[np.maximum(flat_labels, 0)] & (flat_labels >= 0)) | small[flat_regions]
    out = flat_labels.copy()
    # a pixel whose cell's spot (its nearest) is in its region keeps it: that spot is its
    # nearest there too. The others, but for each spot's own disc, go to the nearest spot
    # of their region (if it has one)
    moving = np.flatnonzero((flat_regions > 0) & lit.ravel() & ~keep)
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
    blocked = _line_of_sight(out, centroids, barriers, regions, spot_region, disc, spacing,
                             keep=keep.reshape(labels.shape))
    return out, {"barrier_pixels": int(barriers.sum()), "moved_pixels": int(np.count_nonzero(out != labels)),
                 "regions": int(count), "blocked_pixels": blocked, "pocket_spots": int(pocket_spot.sum())}


#: a cell with a pixel this close (px, chessboard) to a barrier keeps no plane of its own
#: (:func:`cells_at_barriers`)
FOLD_FLAT_PX = 2


def cells_at_barriers(labels: np.ndarray, barriers: np.ndarray, reach: int = FOLD_FLAT_PX) -> np.ndarray:
    """The cells (sorted labels) with a pixel within ``reach`` px of a barrier pixel. A cell
    at a fold takes its neighbours' limited slope, not a plane of its own: where its edge
    runs a pixel or two off the fold's line (the valley test's ridge wanders with the
    noise and its filters) its pixels over the fold hold another facet's light, and the
    plane fitted through them tilts. Kept flat (fine fit), the noise-free M at 48-192 beams
    was 6 / 3 / 9% better, with ten times the sweep's light 6 / 13 / 7%, the box within
    0.7% (docs/fullres.md)."""
    from scipy.ndimage import binary_dilation

    if not barriers.any():
        return np.empty(0, np.int64)
    near = binary_dilation(barriers, np.ones((3, 3), bool), iterations=reach) & (labels >= 0)
    return np.unique(labels[near]).astype(np.int64)


def _closed(barriers: np.ndarray) -> np.ndarray:
    """``barriers`` made 4-connected: where two barrier pixels touch only at a corner, the
    pixel beside both on one side is added. A straight segment that crosses such a line
    runs at least 1/sqrt(2) px inside it, so samples 0.5 px apart land on it."""
    out = barriers.copy()
    out[:-1, :-1] |= barriers[:-1, 1:] & barriers[1:, :-1] & ~barriers[:-1, :-1] & ~barriers[1:, 1:]
    out[:-1, 1:] |= barriers[:-1, :-1] & barriers[1:, 1:] & ~barriers[:-1, 1:] & ~barriers[1:, :-1]
    return out


def _crosses(wall: np.ndarray, start: np.ndarray, end: np.ndarray, step: float = 0.5) -> np.ndarray:
    """(n,) bool: whether the segment from each ``start`` to ``end`` pixel ((n, 2) x, y)
    passes a ``wall`` pixel between them (its two ends' own pixels not counted)."""
    height, width = wall.shape
    out = np.zeros(len(start), bool)
    delta = end - start
    steps = np.ceil(np.hypot(delta[:, 0], delta[:, 1]) / step).astype(int)
    first, last = np.rint(start).astype(int), np.rint(end).astype(int)
    for lo in range(0, len(start), 4096):
        hi = min(lo + 4096, len(start))
        n = int(steps[lo:hi].max(initial=0))
        if n < 2:
            continue
        t = np.arange(1, n) / n                                                   # (n - 1,)
        share = np.minimum(t[None, :] * n / np.maximum(steps[lo:hi, None], 1), 1.0)
        xs = np.rint(start[lo:hi, 0, None] + share * delta[lo:hi, 0, None]).astype(int)
        ys = np.rint(start[lo:hi, 1, None] + share * delta[lo:hi, 1, None]).astype(int)
        own = ((xs == first[lo:hi, 0, None]) & (ys == first[lo:hi, 1, None])) | \
              ((xs == last[lo:hi, 0, None]) & (ys == last[lo:hi, 1, None]))
        hit = wall[np.clip(ys, 0, height - 1), np.clip(xs, 0, width - 1)] & ~own
        out[lo:hi] = hit.any(axis=1)
    return out


def _long(barriers: np.ndarray, extent: float, edge: int) -> np.ndarray:
    """The barriers' pixels farther than ``edge`` px from the frame's edge (where the
    filters' mirror makes valleys of their own) whose 8-connected line spans at least
    ``extent`` px along x or y (noise's ridges are short)."""
    inner = np.zeros_like(barriers)
    inner[edge:barriers.shape[0] - edge, edge:barriers.shape[1] - edge] = \
        barriers[edge:barriers.shape[0] - edge, edge:barriers.shape[1] - edge]
    lines, _, long = _lines(inner, extent)
    return long[lines]


def _lines(barriers: np.ndarray, extent: float):
    """The barriers' 8-connected lines: their labels (H, W), bounding boxes (one a line) and
    (lines + 1,) bool, whether each spans at least ``extent`` px along x or y (index 0: none)."""
    from scipy.ndimage import find_objects, label

    lines, count = label(barriers, np.ones((3, 3), bool))
    boxes = find_objects(lines)
    long = np.zeros(count + 1, bool)
    for i, box in enumerate(boxes, start=1):
        long[i] = max(box[0].stop - box[0].start, box[1].stop - box[1].start) >= extent
    return lines, boxes, long


def _line_of_sight(out: np.ndarray, centroids: np.ndarray, barriers: np.ndarray, regions: np.ndarray,
                   spot_region: np.ndarray, disc: float, spacing: float, candidates: int = 8,
                   keep: np.ndarray | None = None) -> int:
    """A barrier that ends short of the light's edge encloses nothing, and the regions leave
    the cells about it as they were; so each lit pixel whose straight line to its cell's spot
    crosses a barrier goes (in place, in ``out``) to the nearest of its ``candidates``
    nearest spots within a ``spacing`` of it and in its own region that it sees (no barrier
    between), if any (a barrier's short branch into a cell, noise's, would otherwise give
    its far side to spots two cells away), but for the spots' own discs and the barrier
    pixels themselves and the ``keep`` pixels (a pocket's, :func:`fold_cells`). Returns how many
    pixels were blocked."""
    from scipy.ndimage import distance_transform_cdt
    from scipy.spatial import cKDTree

    edge = int(np.ceil(np.clip(SMOOTH_SHARE * spacing, SMOOTH_MIN, SMOOTH_MAX))) + 1
    height, width = out.shape
    wall = _closed(_long(barriers, LONG_SPACINGS * spacing, edge))
    if not wall.any():
        return 0
    flat = out.ravel()
    # a line to the spot can cross a barrier only if one is nearer the pixel than the spot is
    # (the chessboard distance, at most the Euclidean one, and a third of its time); so only
    # the pixels within the farthest any pixel lies from its spot of a barrier are looked at
    to_wall = distance_transform_cdt(~wall, metric="chessboard")
    reach = 0.0
    for r0 in range(0, height, 256):
        rows = out[r0:r0 + 256]
        y, x = np.nonzero(rows >= 0)
        if y.size:
            reach = max(reach, float(np.hypot(*(centroids[rows[y, x]] - np.column_stack([x, y + r0])).T).max()))
    free = (out >= 0) & ~(wall | barriers) & (to_wall <= reach)
    lit = np.flatnonzero((free if keep is None else free & ~keep).ravel())
    if lit.size == 0:
        return 0
    xy = np.column_stack([lit % width, lit // width]).astype(np.float64)
    own = centroids[flat[lit]]
    length = np.hypot(*(own - xy).T)
    near = (to_wall.ravel()[lit] <= length) & (length > disc)
    idx = np.flatnonzero(near)
    if idx.size == 0:
        return 0
    hit = _crosses(wall, xy[idx], own[idx])
    idx = idx[hit]
    if idx.size == 0:
        return 0
    tree = cKDTree(centroids)
    k = min(candidates, len(centroids))
    _, order = tree.query(xy[idx], k=k, distance_upper_bound=spacing * (1 + 1e-9))
    order = order.reshape(len(idx), k)
    region = regions.ravel()[lit[idx]]
    choice = np.full(len(idx), -1)
    for j in range(k):
        open_ = np.flatnonzero((choice < 0) & (order[:, j] < len(centroids)))
        if open_.size == 0:
            break
        spot = order[open_, j]
        same = spot_region[spot] == region[open_]
        test = open_[same]
        seen = ~_crosses(wall, xy[idx[test]], centroids[order[test, j]])
        choice[test[seen]] = order[test[seen], j]
    moved = choice >= 0
    flat[lit[idx[moved]]] = choice[moved]
    return int(idx.size)


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


__all__ = ["DEPTH_SMOOTH_MIN", "FOLD_DEPTH", "FOLD_FLAT_PX", "FOLD_LOW", "FOLD_SIGMAS", "LINE_SPREAD", "LONG_DEPTH",
           "LONG_DEPTH_SPACINGS", "NOMINAL_ELECTRONS",
           "SUM_OUTLIER_SHARE", "cells_at_barriers", "far_chunk", "far_counts", "far_from_sum", "fold_cells",
           "near_chunk", "nominal_noise", "spacing_of", "spot_line", "sum_noise", "valley_barriers", "valley_depth"]
