"""The build-isf stage: beam frames + spots -> the impulse scatter matrix T (paper Sec. 4).

Column j of T is beam j's frame integrated over the cell of every kept spot
(:mod:`ilt.isf.cells`, ``sampling="cell"``), or read at the pixel of every spot's centroid
(``sampling="point"``, the paper's method), then scaled to unit 2-norm; the scales
are kept. Flagged beams and near-duplicate spots are dropped, each with its reason,
so that beams, points and pixels stay one to one.

Spots and ``samples.csv`` are in full-frame sensor pixels; the cells, and the frames
they integrate, are on the HDR frame grid (half resolution after ``ilt merge``), whose
mapping to full-frame pixels is recorded in ``cells.exr`` and the manifest.
"""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path

import numpy as np
import scipy.sparse
from scipy.spatial import cKDTree

from ilt.io.exr import write_exr
from ilt.io.frames import FrameError, FrameScratch, load_frame, open_hdr_directory
from ilt.io.manifest import (
    MANIFEST,
    fingerprint_array,
    fingerprint_file,
    fingerprint_npy,
    read_manifest,
    save_npy,
    write_manifest,
)
from ilt.io.preview import save_png
from ilt.io.staged import staged_directory
from ilt.isf.cells import cell_operator, integrate_with, voronoi_cells
from ilt.isf.directory import CELLS_FILE, SCALES_FILE, T_FILE, write_isf
from ilt.isf.fine import (
    COEFFICIENTS_FILE,
    DEFAULT_DEGREE,
    FINE_DIR,
    CellGeometry,
    FineAccumulator,
    adjacent_cells,
    basis_terms,
    fit_operator,
    frames_inputs,
    write_fine,
)
from ilt.isf.folds import SUM_OUTLIER_SHARE, spacing_of
from ilt.isf.lambertian import check_lambertian
from ilt.isf.outliers import OUTLIER_SIGMAS, clamp_isolated, fresh_outliers, screening_model, spot_radius
from ilt.isf.noise import (
    SAMPLE_FRAMES,
    T_VAR_FILE,
    EntryNoise,
    cap_spot_cells,
    cell_variance,
    fit_frame_noise,
    light_share_variance,
    write_noise,
)
from ilt.isf.spill import SPILL_FILE, spill_matrix, spot_spill, spot_windows
from ilt.parallel.chunks import beam_executor, chunks, run_chunks
from ilt.spots.stage import INDIRECT_SUM_FILE, PEAK_FILE, PEAK_SMOOTH, SUM_FILE, inside_mean
from ilt.spots.table import SPOTS_FILE, format_flags, read_spots

log = logging.getLogger(__name__)

SAMPLINGS = ("cell", "point")


class BuildError(ValueError):
    """Spots and frames that do not make an ISF; the message names the file or beam."""


def select_beams(beams: list[int], spots, min_separation: float) -> tuple[list[int], list[dict]]:
    """Indices (into ``beams``) of the spots to keep, and one ``{beam, reason}`` per drop.

    Flagged spots go first; then, in beam order, a spot closer than ``min_separation``
    pixels to a kept one is dropped as a near-duplicate.
    """
    drops, keep = [], []
    for i, (b, s) in enumerate(zip(beams, spots)):
        if s.flags:
            drops.append({"beam": b, "reason": "flagged: " + format_flags(s.flags)})
        elif not (np.isfinite(s.x) and np.isfinite(s.y)):
            drops.append({"beam": b, "reason": "no centroid"})
        else:
            keep.append(i)
    xy = np.array([[spots[i].x, spots[i].y] for i in keep]).reshape(-1, 2)
    # candidates for near-duplicates: pairs closer than min_separation (a k-d tree, not all pairs)
    close: dict[int, list[int]] = {}
    for a, b in cKDTree(xy).query_pairs(min_separation) if len(xy) > 1 else ():
        close.setdefault(max(a, b), []).append(min(a, b))
    kept: list[int] = []
    kept_k: set[int] = set()
    for k, i in enumerate(keep):
        earlier = [q for q in close.get(k, ()) if q in kept_k]
        if earlier:
            d = np.hypot(*(xy[earlier] - xy[k]).T)
            nearest = int(np.argmin(d))
            drops.append({"beam": beams[i], "reason": f"near-duplicate: {d[nearest]:.3g} px from beam "
                                                       f"{beams[keep[earlier[nearest]]]} (< {min_separation:g})"})
            continue
        kept.append(i)
        kept_k.add(k)
    return kept, sorted(drops, key=lambda d: d["beam"])


#: a pixel is lit when the 3 x 3 mean of the sum of the beam frames is this many times
#: that mean's noise above zero
LIT_SIGMAS = 5.0
#: ... or this many, where 8-connected to such a pixel (:func:`_hysteresis`)
LIT_LOW_SIGMAS = 2.0
#: the mean's window (px) on noisy frames
LIT_SMOOTH = 5
#: ... or on the one-sided means of these widths (:func:`_window_means`)
LIT_WIDE = (11, 21)
#: the peak test's thresholds are those of the largest of this many noise-only frames (or of m, when more)
PEAK_BEAMS = 4096


def lit_mask(frame_sum: np.ndarray, centroids: np.ndarray, fraction: float,
             sigmas: float = LIT_SIGMAS, dark_noise: tuple[float, int] | None = None,
             frame_peak: np.ndarray | None = None, beams: int | None = None,
             indirect: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """(H, W) bool pixels the scan lights, and how the threshold was set.

    Noise-free frames (no negatives): a pixel is lit where the sum of all beam frames is
    above ``fraction`` x its median at the spot pixels (build-isf's default 1e-4: between
    the spots of a sparse scan the sum is only indirect light, 2e-4 to 7.5e-4 of the
    spots' level on the simulator's M at 48 beams, and 1e-3 left three quarters of it out)
    and it is not on a silhouette, partly background (:func:`_silhouette`, judged on
    ``indirect``, the sum without the spots, when given). Noisy frames: where the sum's
    5 x 5 mean (:data:`LIT_SMOOTH`) is above both that and ``sigmas`` x the mean's noise,
    or down to
    :data:`LIT_LOW_SIGMAS` / ``sigmas`` of both where it touches such a pixel
    (:func:`_hysteresis`), or where the same two tests pass on the wider one-sided means
    of :data:`LIT_WIDE` (:func:`_window_means`, with the noise of their width), with the
    holes the lit region encloses filled, and its edge peeled where it is a bright
    silhouette's background or cut pixels (:func:`_noisy_silhouette`; ``silhouette_pixels``
    in the returned dict counts them): the faint rim
    of the scan's light is not let in or out by the noise, so that a denser scan lights
    what a sparser one did (on the noisy M lattice of benchmarks/noisy_sweep.py the 96-beam
    scan lit 0.880 of the 48-beam scan's pixels when the fraction was a test of single
    pixels and the mean 3 x 3; 0.997 so). The mean's noise is ``sqrt(m v0) / 5`` with
    ``dark_noise = (v0, m)``, a dark pixel's variance in one frame (the frames' noise
    model, :mod:`ilt.isf.noise`) and the frames summed: so it grows as sqrt(m) exactly.
    Without it, it is measured from the mean's negative values (black-subtracted frames
    read below zero only by noise, and the negative half of zero-mean noise gives its
    sigma as sqrt(mean(x^2 | x < 0))), which reads low where few pixels are truly dark (on
    the noisy M lattice at m = 48, 0.59 against 0.82): a sparse scan's rim then went
    further than a denser one's. Without the noise test, background pixels
    that only noise lit joined the cells and added their noise to T: on the noisy box
    (benchmarks/bench_coverage.py, 2e4 e- at the brightest spot pixel) the cells covered
    more than on noise-free frames, and bounces 1 and 2 got worse from m = 108 to 189;
    with it they fall with m and halve (bounce 2 at m = 189: 0.179 -> 0.092). The 5 x 5
    mean alone left out light the scan had measured: between a sparse scan's spots the
    indirect light is below its noise, and those pixels got no bounces at all (the noisy
    M at 48 beams lit 74008 pixels; 90461 with the wide means, 98367 at 384 beams, all
    at a lit fraction of 1e-3) and
    the pixels at its rim went in or out by the noise, so a denser scan lost up to 1.1%
    of a sparser one's (with them, and a lit fraction of 1e-4, up to 0.37% on the
    flatland scenes and the box's 0.44%, at its silhouette). Over the pixels the 5 x 5
    test lit (both at a fraction of 1e-3), the mean error of bounces 1-3 of the
    48- and 96-beam flatland scans is 9-20% lower with them, and the box's the same
    (docs/fullres.md).
    """
    from scipy.ndimage import binary_fill_holes

    frame_sum = np.asarray(frame_sum, dtype=np.float64)
    rows = np.clip(np.floor(centroids[:, 1] + 0.5).astype(int), 0, frame_sum.shape[0] - 1)
    cols = np.clip(np.floor(centroids[:, 0] + 0.5).astype(int), 0, frame_sum.shape[1] - 1)
    relative = fraction * float(np.median(frame_sum[rows, cols]))
    lit = frame_sum > relative
    noise = 0.0
    trimmed = 0
    signed = np.count_nonzero(frame_sum < 0) >= 16
    if not signed:
        # no negatives (noise-free, or noise that never reads below zero): and not partly
        # background. (Where noise reads below zero, half the dark pixels would count as
        # background, and the test gather a window about every pixel next to them.)
        lit &= ~_silhouette(frame_sum, indirect)
    if dark_noise is not None or signed:
        (smooth, root), = _window_means(frame_sum, LIT_SMOOTH, corners=False)
        if dark_noise is not None:   # a dark pixel's variance in one frame, and the frames summed
            noise = float(np.sqrt(dark_noise[0] * dark_noise[1])) / LIT_SMOOTH
        elif (negative := smooth[smooth < 0]).size >= 16:
            noise = float(np.sqrt(np.mean(negative**2)))
        if noise > 0:
            # both tests on the smoothed sum, both with the hysteresis: the relative one on
            # single noisy pixels let a third of the rim in or out by the noise alone
            pixel = noise * LIT_SMOOTH    # one pixel's noise; a mean of n pixels has 1 / sqrt(n) of it

            def tests(mean, root):   # (weak, strong) of means of root^2 pixels
                z = mean * root
                return ((mean > relative * LIT_LOW_SIGMAS / sigmas) & (z > LIT_LOW_SIGMAS * pixel),
                        (mean > relative) & (z > sigmas * pixel))

            lit = _connected(*tests(smooth, root))
            # ... and on wider one-sided means, which see the faint light between a sparse
            # scan's spots without carrying an object's light past its silhouette: a pixel
            # passes where all four of its corner windows do (:func:`_window_means`)
            for size in LIT_WIDE:
                weak = strong = True
                for mean, root in _window_means(frame_sum, size):
                    passes = tests(mean, root)
                    weak, strong = weak & passes[0], strong & passes[1]
                lit |= _connected(weak, strong)
            if frame_peak is not None and beams:
                lit |= _peak_test(np.asarray(frame_peak, np.float64), rows, cols, fraction, sigmas,
                                  noise * np.sqrt(LIT_SMOOTH**2 / (PEAK_SMOOTH**2 * beams)), beams)
            lit = binary_fill_holes(lit)
            silhouette = _noisy_silhouette(lit, frame_sum if indirect is None else np.asarray(indirect, np.float64),
                                           sigmas * noise)
            lit &= ~silhouette
            trimmed = int(np.count_nonzero(silhouette))
    return lit, {"relative_threshold": relative, "noise_sigma": noise, "noise_threshold": sigmas * noise,
                 "silhouette_pixels": trimmed}


#: a noise-free pixel next to one with no light is on a silhouette, partly background,
#: where it holds less than this share of the median lit pixel about it (:func:`_silhouette`)
SILHOUETTE_SHARE = 0.5


def _silhouette(frame_sum: np.ndarray, indirect: np.ndarray | None = None) -> np.ndarray:
    """(H, W) bool: on noise-free frames, the pixels partly background: next to a pixel
    with no light at all (8-connected) and under :data:`SILHOUETTE_SHARE` of the median of
    the lit pixels in the 5 x 5 window about them. Where an object's edge cuts across a
    pixel (the box's silhouette) the pixel holds its share of the object's light, and a
    cell's model of it does not: at a lit fraction of 1e-4 those pixels of the noise-free box
    had 6x their bounce 2 as error. Where the scene ends on a pixel's edge (a flatland
    strip's rows, a frame's rendered border) the last pixel holds the light of the one
    inside it and stays.

    ``indirect``: the sum with each frame's own spot taken out (``sum-indirect.exr``,
    :mod:`ilt.spots.stage`), which the share is judged on when given. In the sum itself a
    spot near the silhouette raises the median about it, and a whole pixel of the object
    next to it reads as partly background: on the box's 4x lattice (noise-free) the 768-beam
    scan left out 118 of the 48-beam scan's pixels so (bounce 1's error 0.039 -> 0.103 over
    them), 24-30 judged on the spots' indirect light alone."""
    from scipy.ndimage import binary_dilation

    dark = frame_sum <= 0
    edge = np.flatnonzero(binary_dilation(dark, np.ones((3, 3), bool)) & ~dark)
    out = np.zeros(frame_sum.shape, bool)
    if not edge.size:
        return out
    if indirect is not None:
        frame_sum = np.where(dark, 0.0, indirect)
    median = _window_median(np.where(frame_sum > 0, frame_sum, np.nan), edge)
    out.flat[edge] = frame_sum.flat[edge] < SILHOUETTE_SHARE * median
    return out


#: on noisy frames, the lit region's edge is peeled (:func:`_noisy_silhouette`) this many
#: times: the 2 px of background the lit test's 5 x 5 mean lets in past a bright edge, and
#: the pixels the edge cuts
SILHOUETTE_PEELS = 3


def _noisy_silhouette(lit: np.ndarray, light: np.ndarray, threshold: float) -> np.ndarray:
    """(H, W) bool: the pixels of the noisy lit mask ``lit`` that are partly or wholly
    background past a silhouette, left out of the cells. A pixel at the lit region's edge
    (next to an unlit one, 8-connected) goes where its ``light`` (the sum without the spots,
    else the sum) is under :data:`SILHOUETTE_SHARE` of the median of the lit pixels inside
    the edge in its 5 x 5 window, where that median is ``threshold`` or more (the lit
    test's own, ``sigmas`` x the noise of a 5 x 5 mean: light that a 5 x 5 mean at that
    level would light by itself); the new edge is judged again, :data:`SILHOUETTE_PEELS`
    times in all, and what the peel left as islands within that reach of the edge (an edge
    pixel kept while the pixels inside it went: the flatland M's noisy strip end, whose
    fold cells then counted 9 regions for 3) goes too.

    The lit test judges 5 x 5 means, and at a bright silhouette they let in about 2 px of
    background and the pixels the edge cuts. Inside a cell those took their cell's whole
    indirect light (the photo's bound gave a background pixel's excess to the cell's other
    pixels) and held most of the silhouette's error. Left out, they are the rim, which
    takes the nearest cell pixel's light in the photo's own share (docs/fullres.md "The
    rim"): right for a pixel the edge cuts, and for a whole pixel the noise took out (the
    photo's share is then about 1), so the test takes its pixel's light as read, with no
    margin for its noise (one sigma of margin kept 1-5% of the box's error: docs/fullres.md
    "A noisy silhouette"). Where the light inside is under the threshold (a faint rim
    between sparse spots, level with the pixels inside) nothing goes: a noisy pixel there
    reads under half its neighbours' often, and without the threshold the flatland scenes'
    sparse scans lost 1-2%; at twice it, the box kept half its gain."""
    from scipy.ndimage import binary_dilation

    given, lit = lit, lit.copy()
    out = np.zeros(lit.shape, bool)
    for _ in range(SILHOUETTE_PEELS):
        edge = lit & binary_dilation(~lit, np.ones((3, 3), bool))
        idx = np.flatnonzero(edge)
        if not idx.size:
            break
        median = _window_median(np.where(lit & ~edge, light, np.nan), idx)
        # NaN (no lit pixel inside the edge in the window) stays
        drop = (light.flat[idx] < SILHOUETTE_SHARE * median) & (median >= threshold)
        if not drop.any():
            break
        lit.flat[idx[drop]] = False
        out.flat[idx[drop]] = True
    if out.any():
        # an edge pixel kept while the pixels inside it went is left an island: it goes too
        from scipy.ndimage import distance_transform_cdt, label

        band = distance_transform_cdt(given, metric="chessboard") <= SILHOUETTE_PEELS
        parts, _ = label(lit)      # 4-connected, as the fold cells' regions are (ilt.isf.folds)
        reaching = np.zeros(int(parts.max()) + 1, bool)
        reaching[parts[lit & ~band]] = True
        islands = lit & ~reaching[parts]
        out |= islands
    return out


def _window_median(image: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """(n,) the median of ``image``'s non-NaN values in the 5 x 5 window about each flat
    index ``idx`` (NaN where the window has none)."""
    import warnings

    padded = np.pad(image, 2, constant_values=np.nan)
    rows, cols = np.divmod(idx, image.shape[1])
    dy, dx = np.mgrid[0:5, 0:5]
    windows = padded[rows[:, None, None] + dy, cols[:, None, None] + dx].reshape(idx.size, 25)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)    # all-NaN windows: NaN
        return np.nanmedian(windows, axis=1)


def _window_means(image: np.ndarray, size: int, corners: bool = True):
    """For each ``size`` x ``size`` window about a pixel: (H, W) the mean of the window and
    the square root of the count of pixels it averages (a mean's noise is a pixel's / that).

    ``corners``: the four windows that have the pixel at a corner, else the one centred
    on it. Where the light goes on in every direction (the faint indirect light between
    spots) all four are its level with 1 / size of a pixel's noise; just outside an
    object's silhouette the windows facing away hold no light, so a test that all four
    pass does not carry the object's light past it, as a centred mean of that width
    carries it half the width (on the noisy box a 21 x 21 mean lit a 10 px ring of
    background and made bounces 1-3 38% worse at 432 beams).

    Near the image's edge no window is padded: a padded window counts the edge pixels
    many times and their noise with it (a padded 5 x 5 mean lit strips of pure noise
    along a frame's edge). A corner window is cut at the edge (moved inside, the four
    windows of an edge pixel would be the same two, facing nowhere), the centred one
    moved inside whole (cut, it averaged fewer pixels: on the noisy M strip, 32 rows
    high, that lost 0.7% of its lit pixels, in its top and bottom rows)."""
    from scipy.ndimage import uniform_filter

    half = size // 2
    height, width = image.shape
    if not corners and height >= size and width >= size:
        yield inside_mean(image, size), float(size)
        return
    # the window centred on each pixel of the image padded by ``half``: a corner window of
    # a pixel is the centred one of its diagonal neighbour ``half`` away (one filter, four
    # slices: four filters cost 5.7x the 5 x 5 test alone on a 12 Mpx frame)
    total = uniform_filter(np.pad(image, half), size=size, mode="constant")
    share = uniform_filter(np.pad(np.ones(image.shape), half), size=size, mode="constant")   # of it inside
    root = np.sqrt(share) * size
    starts = [(y, x) for y in (0, 2 * half) for x in (0, 2 * half)] if corners else [(half, half)]
    for y, x in starts:
        window = (slice(y, y + height), slice(x, x + width))
        yield total[window] / share[window], root[window]


def earlier_coverage(source: str | os.PathLike, frame_shape: tuple[int, int],
                     mapping) -> tuple[np.ndarray, Path, str]:
    """(H, W) bool: the pixels an earlier build's cells covered, the ``cells.exr`` read
    and its :func:`~ilt.io.manifest.fingerprint_file` (for the manifest's inputs: the
    file is read here once, not again to be recorded).

    ``source``: that build's ISF directory, a directory holding its ``cells.exr`` (a refine
    pass keeps one: :mod:`ilt.refine.stage`), or the file. It must be on this build's frame
    grid (the same shape and pixel mapping: the same camera and merge), else BuildError
    naming it. A scan's lit test judges each pixel against that scan's own noise, so at
    the faint rim of the light a denser scan can leave out pixels a sparser one let in
    (docs/fullres.md: 0.1-0.5% of them); where the earlier scan is known, they stay.
    """
    from ilt.io.exr import ImageError, read_exr

    path = Path(source)
    if path.is_dir():
        path = path / CELLS_FILE
    if not path.is_file():
        raise BuildError(f"{path}: no such file; --keep-covered takes an earlier ISF directory (or its {CELLS_FILE})")
    fingerprint = fingerprint_file(path)
    try:
        pixels, attributes = read_exr(path)
    except ImageError as exc:
        raise BuildError(str(exc)) from None
    if attributes.get("channels") != ["label"]:
        raise BuildError(f"{path}: channels {attributes.get('channels')}, not an ISF's cells (one channel 'label', "
                         f"as 'ilt build-isf' writes {CELLS_FILE})")
    if pixels.shape[:2] != tuple(frame_shape):
        raise BuildError(f"{path}: its cells are {pixels.shape[1]} x {pixels.shape[0]}, this scan's frames "
                         f"{frame_shape[1]} x {frame_shape[0]}: not a build of the same camera and merge")
    ours = mapping.attributes()
    theirs = [attributes.get(k) for k in ours]
    if any(t is None or not np.allclose(t, v) for t, v in zip(theirs, ours.values())):
        raise BuildError(f"{path}: its pixel mapping {theirs} is not this scan's {list(ours.values())}: not a "
                         f"build of the same camera and merge")
    return pixels[:, :, 0] >= 0, path, fingerprint


def _peak_test(peak: np.ndarray, rows, cols, fraction: float, sigmas: float, noise: float, beams: int) -> np.ndarray:
    """Pixels that one beam frame lights: where the largest of the frames' local means
    (``peak.exr``) passes the sum's two tests, with the noise of one frame's mean
    (``noise``) and the thresholds raised so that the largest of :data:`PEAK_BEAMS` (or
    ``beams``, when more) noise-only means passes no more often than one at the sum's
    (6.4 and 4.4 sigma). A pixel that only its nearest beams
    light gains nothing from other beams but their noise, so the sum's test lost it as a
    scan grew denser (on the noisy occluded M, 1.1% of the 48-beam scan's pixels at 96
    beams, holding 3.7% of a photo's direct light); the largest frame never falls."""
    from scipy.special import ndtr, ndtri

    relative = fraction * float(np.median(peak[rows, cols]))
    # at a fixed count of frames up to PEAK_BEAMS: thresholds that rose with m (as ln m) lost
    # a sparser scan's rim at the next density, where the largest frame was the same
    count = max(beams, PEAK_BEAMS)
    high = float(ndtri(1.0 - ndtr(-sigmas) / count)) * noise
    low = float(ndtri(1.0 - ndtr(-LIT_LOW_SIGMAS) / count)) * noise
    return _hysteresis(peak, max(low, relative * LIT_LOW_SIGMAS / sigmas), max(high, relative))


def _hysteresis(image: np.ndarray, low, high) -> np.ndarray:
    """(H, W) bool: pixels above ``low`` 8-connected to a pixel above ``high`` (as Canny's
    edges): the lit region's faint rim stays lit whatever the noise does there, where a
    single threshold at ``high`` let a rim pixel in or out by the noise alone. ``low``
    and ``high`` are numbers or (H, W) arrays."""
    return _connected(image > low, image > high)


def _connected(weak: np.ndarray, strong: np.ndarray) -> np.ndarray:
    """(H, W) bool: the 8-connected regions of ``weak`` that hold a pixel of ``strong``."""
    from scipy.ndimage import label

    regions, _ = label(weak | strong, structure=np.ones((3, 3), bool))
    hit = np.unique(regions[strong])
    return np.isin(regions, hit[hit > 0])


def _spot_cells_variance(variance: np.ndarray, block: np.ndarray, m: int, done: int, share: float) -> np.ndarray:
    """``variance`` (m, b) of the columns ``done`` ... with each column's own row (its spot's
    cell, T's diagonal) at least ``share`` times that cell's sum of squared pixels (the
    block's last m rows, with a fine fit; a noisy pixel's square is (1 + share) times its
    light's on average, so the sum is divided by that): a copy, or ``variance`` itself when
    ``share`` is 0."""
    if not share > 0:
        return variance
    cols = np.arange(variance.shape[1])
    rows = done + cols                                   # each column's own cell: T's diagonal
    out = variance.copy()
    out[rows, cols] = np.maximum(out[rows, cols], share * block[-m:][rows, cols] / (1.0 + share))
    return out


def _column_chunk(beams, files, shape, sampler, m, scratch=None, degree=None, spill=None, outliers=None):
    """Worker: one column of raw T per frame, (m, len(beams)) float64, and below it, with
    a fine ``degree``, the frame's (K m) raw fine-operator coefficients (:mod:`ilt.isf.fine`)
    and the cell sums of its squares (m). With ``spill`` (cell sampling: each beam's row
    of T, spot centre and window on the grid, and the frames' noise model), also each
    spot's share in the other cells (:func:`ilt.isf.spill.spot_spill`). With ``outliers``
    (each beam's spot centre and window on the grid, and the frames' noise model), each
    frame's isolated outlier pixels are replaced first (:func:`ilt.isf.outliers.clamp_isolated`).
    With either, returns (the array, {"shares": a dict per beam or None, "clamped": the
    pixels replaced in each frame}).

    sampler: the path of ``cells.exr`` (cell sampling; read once per worker process), or
    the (m,) flat pixel indices of the samples (point sampling). files: each beam's EXR,
    or None for a beam whose frame ``scratch`` (:class:`ilt.io.frames.FrameScratch`) keeps.
    """
    operator, cells, labels = _cached_operator(sampler, m, degree) if isinstance(sampler, (str, Path)) \
        else (None, None, None)
    out = np.empty((m if operator is None else operator.shape[0] + (m if degree else 0), len(files)))
    frame = np.empty(shape)  # one float64 buffer for the chunk: the product reads it as is
    kept = np.empty(shape, np.float32) if scratch is not None else None
    fd = scratch.open() if scratch is not None and None in files else None
    shares, clamped = [], []
    try:
        for k, (beam, path) in enumerate(zip(beams, files)):
            if path is None:
                np.copyto(frame, scratch.read(fd, beam, kept))
            else:
                load_frame(path, shape, out=frame)
            if outliers is not None:
                centres, radii, noise = outliers
                clamped.append(clamp_isolated(frame, noise, centres[k], float(radii[k])))
            if spill is not None and labels is not None:
                rows, centres, radii, noise = spill
                shares.append(spot_spill(frame, labels, int(rows[k]), centres[k], float(radii[k]), noise))
            if operator is None:
                out[:, k] = frame.ravel()[sampler]
            elif degree:
                out[:operator.shape[0], k] = integrate_with(frame, operator)
                out[operator.shape[0]:, k] = integrate_with(np.square(frame, out=frame), cells)
            else:
                out[:, k] = integrate_with(frame, operator)
    finally:
        if fd is not None:
            os.close(fd)
    if spill is None and outliers is None:
        return out
    return out, {"shares": shares if spill is not None else None, "clamped": clamped}


_OPERATOR_CACHE: dict = {}


def _cached_operator(path, m, degree=None):
    """The cell operator of ``cells.exr`` at ``path`` (with a fine ``degree``, the fine
    operator's fit stacked below it: one sparse product per frame gives both; a row's
    sum is the same as alone, so T is the same bit for bit) and the cell operator alone
    (for the squared frames, which judge each cell's fit), built once per worker process."""
    from ilt.isf.directory import read_cells

    key = (str(path), os.stat(path).st_mtime_ns, m, degree)
    if key not in _OPERATOR_CACHE:
        _OPERATOR_CACHE.clear()
        labels = read_cells(Path(path), m)
        cells = cell_operator(labels, m)
        operator = cells
        if degree:
            operator = scipy.sparse.vstack([cells, fit_operator(CellGeometry.from_labels(labels, m), degree)],
                                           format="csr")
        _OPERATOR_CACHE[key] = operator, cells, labels
    return _OPERATOR_CACHE[key]


def build_isf(hdr_dir: str | os.PathLike, spots_dir: str | os.PathLike, out: str | os.PathLike,
              sampling: str = "cell", min_separation: float = 2.0, lit_fraction: float = 1e-4,
              max_cell_radius: float | None = None, executor=None, workers: int | None = None,
              chunk: int = 16, progress=None, force: bool = False, frame_cache=None,
              fine_degree: int | None = DEFAULT_DEGREE, spill: bool = True, lambertian: bool = True,
              keep_covered: str | os.PathLike | None = None, fold_cells: bool = True,
              fold_transfer: str = "all") -> dict:
    """Build the ISF directory ``out`` from ``hdr_dir`` frames and ``spots_dir`` centroids.

    Writes T.npy (m, m) float64 unit columns, scales.npy (m,) float64 column 2-norms of
    the raw T (frame units x frame pixels), samples.csv (plan beam, centroid x, y in
    full-frame pixels), cells.exr ((H, W) row of T per pixel of the frame grid, -1
    outside, with the grid's pixel mapping; cell sampling only), T.png and
    manifest.json (plan layout, frame shape, pixel mapping, kept beams, every drop with
    its reason). ``frame_cache``: the scratch directory in which a preceding centroids
    run over the same HDR directory kept its decoded frames (:func:`centroids_and_isf`,
    :class:`ilt.io.frames.FrameScratch`); those it recorded are read instead of the EXR
    files, and the frames file is removed once read. The caller removes the directory.
    ``min_separation`` is in full-frame pixels; ``max_cell_radius`` in frame-grid
    pixels, by default None: cells end where the lit mask does (:func:`lit_mask`), so
    their extent follows the scan's light, not the spacing of its spots.
    ``fine_degree`` (cell sampling): also write ``fine/``, the fine operator of
    full-resolution bounce images (:mod:`ilt.isf.fine`), fitted in the same pass over the
    frames; None skips it. ``spill`` (cell sampling): also write ``spill.npz``, each
    spot's direct light in the other cells (:mod:`ilt.isf.spill`), measured in the same pass.
    ``lambertian``: also write ``lambertian.json`` and ``lambertian.png``, the reciprocity
    verdict on T (:mod:`ilt.isf.lambertian`); False only to time build-isf without it.
    ``keep_covered``: an earlier build of the same scene (its ISF directory, a directory
    holding its ``cells.exr``, or that file): every pixel its cells covered stays covered
    (:func:`earlier_coverage`), so that a denser scan covers at least what it did.
    ``fold_cells`` (cell sampling, frames with a noise model): the cells end at the concave
    folds the frames show (:mod:`ilt.isf.folds`), at the cost of reading each frame's rows
    about its spot again. ``fold_transfer`` (with fold cells): also write ``fold_transfer.npz``,
    the light the cells beside each fold send across it, spread over the cell rather than
    at its spot (:mod:`ilt.isf.fold_transfer`), reading the frames of the beams beside the
    folds again: ``"all"`` at every fold, ``"flatland"`` only at those a flatland scene's
    frames show, ``"off"`` (docs/fullres.md, "Across a fold").
    """
    if sampling not in SAMPLINGS:
        raise BuildError(f"sampling must be one of {SAMPLINGS}, got {sampling!r}")
    if keep_covered is not None:
        if sampling != "cell":
            raise BuildError("keeping an earlier scan's coverage (--keep-covered) needs cell sampling: "
                             "point sampling has no cells")
        if Path(keep_covered).resolve().is_relative_to(Path(out).resolve()):
            raise BuildError(f"{keep_covered}: this build replaces it; --keep-covered takes an earlier build "
                             f"kept elsewhere (copy its {CELLS_FILE} out first)")
    spots_dir = Path(spots_dir)
    hdr = open_hdr_directory(hdr_dir)
    beams, spots = read_spots(spots_dir / SPOTS_FILE)
    for b in beams:
        if b >= hdr.m:
            raise BuildError(f"{spots_dir / SPOTS_FILE}: beam {b} has no image in {hdr.path} ({hdr.m} beams)")
    kept, drops = select_beams(beams, spots, min_separation)
    for d in drops:   # flagged beams were reported by centroids, as was what to do about them
        log.log(logging.INFO if d["reason"].startswith("flagged") else logging.WARNING,
                "dropping beam %d: %s", d["beam"], d["reason"])
    if len(kept) < 2:
        raise BuildError(f"{spots_dir / SPOTS_FILE}: {len(kept)} usable spots; an ISF needs at least 2")
    plan = [beams[i] for i in kept]
    centroids = np.array([[spots[i].x, spots[i].y] for i in kept])
    on_grid = hdr.mapping.to_grid(centroids)
    m = len(plan)
    # each spot's own disc, on the grid, left alone by the outlier test (ilt.isf.outliers)
    grid_px = float(np.linalg.norm(np.diff(hdr.mapping.to_grid(np.array([[0.0, 0.0], [1.0, 0.0]])), axis=0)))
    discs = np.array([spot_radius(spots[i].area) for i in kept]) * grid_px
    labels = None
    noise = None
    fold_valleys = None
    if sampling == "cell":
        # the frames' noise against their level, from a sample of them (ilt.isf.noise): the
        # lit test's noise, each entry's variance (T_var.npy) and the fine fit's test take it
        sample = np.unique(np.round(np.linspace(0, m - 1, min(SAMPLE_FRAMES, m))).astype(int))
        try:
            frames = [load_frame(hdr.files[plan[i]], hdr.frame_shape) for i in sample]
        except FrameError as exc:
            raise BuildError(str(exc)) from None
        noise = fit_frame_noise(frames, on_grid[sample])
        # isolated outliers (fireflies) inflate the fit, and an inflated model lets them
        # through: fitted again on the frames without those that its faint knots find
        # (ilt.isf.outliers.screening_model), then without those the new fit finds
        replaced: list[list[int]] = [[] for _ in sample]     # each sample frame's outliers, flat indices
        for model in (screening_model, lambda fitted: fitted):
            if noise is None or not sum(clamp_isolated(f, model(noise), on_grid[i], discs[i], replaced=r)
                                        for f, i, r in zip(frames, sample, replaced)):
                break
            noise = fit_frame_noise(frames, on_grid[sample])
        fresh = fresh_outliers(replaced, frames[0].size)
        del frames
        frame_sum = _read_sum(spots_dir, hdr.frame_shape, hdr.mapping)
        peak = _read_sum(spots_dir, hdr.frame_shape, hdr.mapping, PEAK_FILE) if frame_sum is not None else None
        indirect = _read_sum(spots_dir, hdr.frame_shape, hdr.mapping, INDIRECT_SUM_FILE) \
            if frame_sum is not None else None
        dark = None if noise is None else (float(noise.pixel_variance(np.zeros(1))[0]), hdr.m)
        lit, lit_info = (None, None) if frame_sum is None else lit_mask(frame_sum, on_grid, lit_fraction,
                                                                        dark_noise=dark, frame_peak=peak,
                                                                        beams=hdr.m, indirect=indirect)
        if keep_covered is not None:
            if lit is None:
                raise BuildError(f"{spots_dir / SUM_FILE}: missing, and keeping an earlier scan's coverage needs "
                                 f"this scan's lit mask from it: run 'ilt centroids' again")
            earlier, earlier_cells, earlier_fingerprint = earlier_coverage(keep_covered, hdr.frame_shape,
                                                                           hdr.mapping)
            added = int(np.count_nonzero(earlier & ~lit))
            lit = lit | earlier
            lit_info["kept_from"] = {"cells": str(earlier_cells), "pixels": int(earlier.sum()), "added": added}
            log.info("kept %d pixels that %s covered and this scan's lit test leaves out (its noise at the rim "
                     "of the light)", added, earlier_cells)
        # cells end where the scan's light ends (the lit mask), not at a multiple of the
        # spot spacing: a denser scan covers at least what a sparser one did (issue 21).
        # Without the frames' sum there is no lit mask: then 2 spot spacings, as before
        if lit is None:
            if max_cell_radius is None:
                max_cell_radius = 2.0 * spacing_of(on_grid)
            log.warning("%s: missing, so no lit mask: every pixel within %.3g px of a spot joins its cell "
                        "('ilt centroids' writes it)", spots_dir / SUM_FILE, max_cell_radius)
        # the pool idles meanwhile: the queries take its cores
        labels = voronoi_cells(on_grid, hdr.frame_shape, lit, max_cell_radius, threads=workers or -1)
        folds = at_folds = None
        if fold_cells:
            sum_beams = _sum_beams(spots_dir, beams) if frame_sum is not None else None
            # noise-free frames' folds are judged against a nominal noise of their brightest pixel
            brightest = None if noise is not None or frame_sum is None else \
                float(np.max(peak if peak is not None else frame_sum))
            labels, folds, at_folds, fold_valleys = _fold_cells(hdr, plan, on_grid, labels, noise, discs, executor,
                                                           workers, chunk, frame_sum, sum_beams, fresh, brightest)
        empty = np.flatnonzero(np.bincount(labels[labels >= 0], minlength=m) == 0)
        if empty.size:
            raise BuildError(f"beam {plan[empty[0]]}: its cell holds no lit pixel (spot at "
                             f"{centroids[empty[0]].round(2).tolist()}); lower --lit-fraction")
    else:
        px = np.floor(on_grid + 0.5).astype(np.int64)
        outside = np.flatnonzero((px < 0).any(axis=1) | (px[:, 0] >= hdr.frame_shape[1]) | (px[:, 1] >= hdr.frame_shape[0]))
        if outside.size:
            raise BuildError(f"beam {plan[outside[0]]}: spot at {centroids[outside[0]].round(2).tolist()} "
                             f"is outside the {hdr.frame_shape[1]} x {hdr.frame_shape[0]} frame")
        sampler = px[:, 1] * hdr.frame_shape[1] + px[:, 0]
        fine_degree = None
    if fine_degree is not None:
        terms = basis_terms(fine_degree)
    with staged_directory(out, force=force) as tmp:
        if labels is not None:
            write_exr(tmp / CELLS_FILE, labels.astype(np.float32), channels=["label"],
                      attributes={"ilt:quantity": "row of T per pixel, -1 outside every cell",
                                  **hdr.mapping.attributes()})
            sampler = str(tmp / CELLS_FILE)
        # a frame the centroids pass kept when there is one (it may have run out of disk)
        scratch = FrameScratch(Path(frame_cache), hdr.frame_shape) if frame_cache is not None else None
        kept = scratch.kept() if scratch is not None else frozenset()
        row_of = {b: i for i, b in enumerate(plan)}
        radii = spot_windows(on_grid)

        def spill_of(c):
            if labels is None or not spill:
                return None
            rows = np.array([row_of[b] for b in c])
            return rows, on_grid[rows], radii[rows], noise

        def outliers_of(c):
            if noise is None:
                return None
            rows = np.array([row_of[b] for b in c])
            return on_grid[rows], discs[rows], noise

        tasks = [(c, [None if b in kept else hdr.files[b] for b in c], hdr.frame_shape, sampler, m,
                  scratch if kept else None, fine_degree, spill_of(c), outliers_of(c)) for c in chunks(plan, chunk)]
        spill_columns = []
        clamped = np.zeros(m, np.int64)      # isolated outlier pixels replaced, per beam
        # T's columns go straight into the memory-mapped T.npy, divided by their norms as
        # they arrive (elementwise, so the same floats as raw / scales on the whole); the
        # fine coefficients into a float32 memory map, block by block (FineAccumulator):
        # nothing m x m is held in memory (was about 40 m^2 bytes)
        T = np.lib.format.open_memmap(tmp / T_FILE, mode="w+", dtype=np.float64, shape=(m, m))
        scales = np.empty(m)
        accumulator = None
        if fine_degree:
            (tmp / FINE_DIR).mkdir()
            accumulator = FineAccumulator(
                np.lib.format.open_memmap(tmp / FINE_DIR / COEFFICIENTS_FILE, mode="w+", dtype=np.float32,
                                          shape=(terms, m, m)),
                CellGeometry.from_labels(labels, m), fine_degree, noise_aware=noise is not None, keep_flat=at_folds)
        # noise that is a share of each pixel's light (a path tracer's): each spot's own cell
        # gets its variance from its pixels' squares, which the fine fit's pass sums
        light_share = light_share_variance(noise) if noise is not None and fine_degree else 0.0
        entry_noise = None if noise is None else EntryNoise(
            np.lib.format.open_memmap(tmp / T_VAR_FILE, mode="w+", dtype=np.float32, shape=(m, m)))
        area = None if labels is None else np.bincount(labels[labels >= 0], minlength=m).astype(np.float64)
        done = 0
        with beam_executor(executor, workers) as ex:
            for block in run_chunks(_column_chunk, tasks, ex, progress=progress):
                if isinstance(block, tuple):
                    block, extras = block
                    spill_columns.extend(extras["shares"] or [])
                    clamped[done:done + len(extras["clamped"])] = extras["clamped"]
                b = block.shape[1]
                raw = block[:m]
                norms = scales[done:done + b] = _column_norms(raw)
                zero = np.flatnonzero(~(norms > 0))
                if zero.size:
                    j = done + int(zero[0])
                    raise BuildError(f"beam {plan[j]} ({hdr.files[plan[j]]}): its image is zero at every sample")
                T[:, done:done + b] = raw / norms
                # each entry's variance: its cell's pixels at the cell's mean level (ilt.isf.noise)
                variance = None
                if entry_noise is not None:
                    variance = cell_variance(noise, raw, area)
                    entry_noise.add(done, _spot_cells_variance(variance, block, m, done, light_share), norms)
                if accumulator is not None:
                    accumulator.add(done, block[m:-m].reshape(terms, m, b), raw, block[-m:], norms, variance)
                done += b
        if kept:  # every kept frame is read: free its disk while the outputs are written
            _in_background(scratch.path.unlink, missing_ok=True)
        T.flush()
        # T's file hash (the manifest's) and array fingerprint (the fine operator's) from one read
        hashed = {}
        hashed[T_FILE], t_fingerprint = fingerprint_npy(tmp / T_FILE)
        if fine_degree is not None:
            share = None
            if accumulator is not None:
                share = accumulator.finish()
                accumulator.out.flush()
                del accumulator
            hashed.update(write_fine(tmp, fine_degree, m, t_fingerprint, fingerprint_array(labels),
                                     frames_inputs(hdr.path, out), share))
        fields = {"sampling": sampling, "beams": plan, "drops": drops,
                  "pixel_mapping": hdr.mapping.as_dict()}
        if labels is not None:
            fields["coverage"] = {"fraction": float(np.mean(labels >= 0)), "lit": lit_info}
        if entry_noise is not None:
            # the spots' cells as noisy as the share says, or as T's diagonal scatters by if that is less
            spot_cells = None
            if light_share and labels is not None:
                spot_cells = cap_spot_cells(entry_noise.out, T, adjacent_cells(labels))
            if spot_cells is not None and spot_cells["scaled_by"] < 1.0:
                log.info("the spots' own cells: the frames' noise, a share of the light, makes them %.2g%% noisy, but "
                         "T's diagonal scatters by %.2g%% against its neighbours' (spots rendered or exposed with less "
                         "noise than the light about them): their variance in %s taken as that",
                         100 * spot_cells["predicted_sigma"], 100 * spot_cells["scatter_sigma"], T_VAR_FILE)
            entry_noise.out.flush()
            del entry_noise.out
            write_noise(tmp, noise, entry_noise.entry_sigma, f"{noise.frames} of the beam frames, spread over the scan",
                        spot_cells)
            fields["noise"] = {"entry_sigma": entry_noise.entry_sigma, "frames": noise.frames}
        if fold_cells and labels is not None:
            fields["folds"] = folds
        if noise is not None:
            fields["outliers"] = _outlier_record(clamped, plan)
            if clamped.any():
                worst = int(np.argmax(clamped))
                log.info("replaced %d isolated outlier pixels (fireflies, hot pixels: %g sigma above all their "
                         "neighbours) in %d of %d frames, most in beam %d's (%d)", int(clamped.sum()),
                         OUTLIER_SIGMAS, int(np.count_nonzero(clamped)), m, plan[worst], int(clamped[worst]))
        if fold_transfer != "off" and fold_valleys is not None:
            fields["fold_transfer"] = _fold_transfer(tmp, hdr, plan, on_grid, labels, fold_valleys, scales,
                                                     fold_transfer == "all", noise, discs)
        if labels is not None and spill:
            Q = spill_matrix(spill_columns, m)
            scipy.sparse.save_npz(tmp / SPILL_FILE, Q)
            fields["spill"] = {"entries": int(Q.nnz), "mean_share": float(Q.sum() / m),
                               "max_share": float(Q.max()) if Q.nnz else 0.0}
        fields["own_cell"] = own_cell_check(T, plan, spots_dir / "overlay.png")
        if lambertian:
            T_var = np.load(tmp / T_VAR_FILE, mmap_mode="r") if (tmp / T_VAR_FILE).exists() else None
            fields["lambertian"] = check_lambertian(tmp, T, centroids, T_var, plan, hdr.layout, labels)
            del T_var
        manifest_fields = write_isf(tmp, T, centroids, hdr.layout, hdr.frame_shape, beams=plan, t_written=True)
        save_npy(tmp / SCALES_FILE, scales)
        save_png(tmp / "T.png", T, title=f"T ({m} x {m}, {sampling} sampling)", xlabel="beam j", ylabel="pixel i")
        parameters = {"sampling": sampling, "min_separation": min_separation, "lit_fraction": lit_fraction,
                      "max_cell_radius": max_cell_radius, "fine_degree": fine_degree, "lit_sigmas": LIT_SIGMAS}
        if sampling == "cell":
            parameters["fold_cells"] = bool(fold_cells)
            parameters["fold_transfer"] = fold_transfer if fold_cells else "off"
        inputs = {str(spots_dir / SPOTS_FILE): ""}
        if (spots_dir / MANIFEST).exists():   # the spots' manifest by its hash: what `ilt status` knows a stage by
            spots_manifest = read_manifest(spots_dir)
            inputs = {str(spots_dir / SPOTS_FILE): spots_manifest["outputs"].get(SPOTS_FILE, ""),
                      str(spots_dir / MANIFEST): fingerprint_file(spots_dir / MANIFEST),
                      **spots_manifest.get("inputs", {})}
        if keep_covered is not None:
            parameters["keep_covered"] = lit_info["kept_from"]["cells"]
            inputs[lit_info["kept_from"]["cells"]] = earlier_fingerprint
        write_manifest(tmp, "build-isf", parameters, inputs=inputs, extra={**manifest_fields, **fields}, hashed=hashed)
    return {"output": str(out), "m": m, "sampling": sampling, "dropped": len(drops), "drops": drops}


def _fold_transfer(tmp: Path, hdr, plan: list[int], on_grid: np.ndarray, labels: np.ndarray, valleys,
                   scales: np.ndarray, solid: bool, noise=None, discs=None) -> dict:
    """``fold_transfer.npz`` (:mod:`ilt.isf.fold_transfer`) from the fold lines the cells were cut
    at and the far light (``valleys``, :func:`_fold_cells`), at 3D folds too when ``solid``; the manifest's record.
    Each frame read again has its isolated outliers replaced (with the frames' ``noise``, each
    spot's disc of radius ``discs`` left alone), as the pass that built T did: a firefly across
    a fold would read as light the kernel sends."""
    from ilt.isf.fold_transfer import FILE, fold_corrections, write_corrections

    lines, light, spacing = valleys

    def frame_of(k):
        frame = load_frame(hdr.files[plan[k]], hdr.frame_shape)
        if noise is not None:
            clamp_isolated(frame, noise, on_grid[k], float(discs[k]))
        return frame

    rows, cols, values, lines = fold_corrections(labels, on_grid, lines, light, spacing, frame_of, scales, solid)
    write_corrections(tmp / FILE, rows, cols, values, len(plan))
    log.info("fold transfer: %d entries across %d fold lines", len(values), len(lines))
    return {"entries": int(len(values)), "lines": lines}


def _sum_beams(spots_dir: Path, beams: list[int]) -> list[int] | None:
    """The beams whose frames ``sum.exr`` holds as build-isf reads them (every beam of the
    spots table), or None when centroids subtracted a dark frame from them."""
    if not (spots_dir / MANIFEST).exists():
        return None
    return None if read_manifest(spots_dir).get("parameters", {}).get("dark") else list(beams)


def _fold_cells(hdr, plan, on_grid, labels, noise, discs, executor, workers, chunk, frame_sum=None,
                sum_beams=None, fresh: float = 0.0, brightest: float | None = None):
    """``fold_cells``: the cells ended at the concave folds the frames show
    (:mod:`ilt.isf.folds`), and the manifest's record. The far light is the scan's sum
    (``sum.exr``, whose frames are ``sum_beams``) less each frame's disc about its spot,
    read over the disc's rows only; without that sum, or when the frames' outliers that
    are not at the same pixel in every frame (``fresh``: their share of a frame's pixels,
    fireflies) would stand side by side in it, where the sum cannot tell them, one more pass
    over the frames, each frame's replaced first. Noise-free frames (``noise`` None) are
    judged against :func:`ilt.isf.folds.nominal_noise` of ``brightest`` (the frames'
    brightest pixel), their discs tapered (:func:`ilt.isf.folds.near_chunk`), nothing
    replaced; without the sum, as without fold cells. Returns the labels, the record, the
    cells at a barrier, which keep no plane of their own (:func:`ilt.isf.folds.cells_at_barriers`;
    None when not applied), and the fold lines on the far light's valley floor
    (:func:`ilt.isf.fold_transfer.floor_lines`), the far light and the spot spacing, which
    :mod:`ilt.isf.fold_transfer` reads the light across from (None when not applied). The cells
    end at the barriers' regions, then are cut at those lines
    (:func:`ilt.isf.fold_transfer.cut_cells`)."""
    from ilt.isf.folds import FOLD_DEPTH, FOLD_LOW, FOLD_SIGMAS, LONG_DEPTH, LONG_DEPTH_SPACINGS, NOMINAL_ELECTRONS, \
        POCKET_CELLS, cells_at_barriers, far_chunk, far_counts, far_from_sum, fold_cells, near_chunk, nominal_noise, \
        spot_line, valley_barriers
    from ilt.isf.fold_transfer import cut_cells, floor_lines

    judge = noise
    if noise is None:
        if frame_sum is None or sum_beams is None or brightest is None or not brightest > 0:
            log.info("fold cells: noise-free frames and no sum.exr to judge their folds on: cells as without them")
            return labels, {"applied": False, "reason": "noise-free frames and no sum.exr ('ilt centroids' writes it)"}, \
                None, None
        judge = nominal_noise(brightest)
    spacing = spacing_of(on_grid)
    along = spot_line(on_grid)          # a line of spots: each frame's stripe across it, not a disc
    near = "disc" if along is None else "stripe across the spots' line"
    row = {b: i for i, b in enumerate(plan)}
    light = np.zeros(hdr.frame_shape)
    crowded = sum_beams is not None and fresh * len(sum_beams) > SUM_OUTLIER_SHARE
    if frame_sum is not None and sum_beams is not None and not crowded:
        # the beams the sum holds that build-isf dropped: their whole frames (centre NaN)
        dropped = np.array([np.nan, np.nan])
        tasks = [([hdr.files[b] for b in c], hdr.frame_shape,
                  np.array([on_grid[row[b]] if b in row else dropped for b in c]).reshape(-1, 2), spacing,
                  noise is None, along)
                 for c in chunks(sum_beams, chunk)]
        with beam_executor(executor, workers) as ex:
            for part in run_chunks(near_chunk, tasks, ex):
                light += part
        light = far_from_sum(frame_sum, light, noise, len(sum_beams))
        source = f"sum.exr less each frame's {near}"
    else:
        tasks = []
        for c in chunks(plan, chunk):
            rows = [row[b] for b in c]
            tasks.append(([hdr.files[b] for b in c], hdr.frame_shape, on_grid[rows], spacing, noise, discs[rows],
                          along))
        with beam_executor(executor, workers) as ex:
            for part in run_chunks(far_chunk, tasks, ex):
                light += part
        source = "a pass over the frames" + (f" (outliers in {fresh:.2g} of each frame's pixels)" if crowded else "") \
            + ("" if along is None else f", each frame's {near} left out")
    valleys = {}
    barriers = valley_barriers(light, far_counts(on_grid, hdr.frame_shape, spacing, along), judge, labels >= 0, spacing,
                               valleys)
    labels, record = fold_cells(labels, on_grid, barriers, spacing)
    lines = floor_lines(barriers, light, spacing)
    labels, record["cut_pixels"] = cut_cells(labels, on_grid, [line for line, _ in lines], spacing)
    at_folds = cells_at_barriers(labels, barriers)
    log.info("fold cells: %d pixels moved to the cell on their side of %d barrier pixels, %d cut at %d fold lines",
             record["moved_pixels"], record["barrier_pixels"], record["cut_pixels"], len(lines))
    if noise is None:
        source += ", tapered from 1 to 2 spacings"
    return labels, {"applied": True, "spacing": spacing, "sigmas": FOLD_SIGMAS, "low_sigmas": FOLD_LOW,
                    "depth": FOLD_DEPTH, "long_depth": {"depth": LONG_DEPTH, "spacings": LONG_DEPTH_SPACINGS},
                    "pocket_cells": POCKET_CELLS,
                    **valleys, "far_light": source, **record, "flat_cells": int(at_folds.size),
                    **({} if noise is not None else {"noise": f"nominal: noise-free frames judged as with photon "
                                                              f"noise of {NOMINAL_ELECTRONS:g} e- at their "
                                                              f"brightest pixel"})}, at_folds, (lines, light, spacing)


def _outlier_record(clamped: np.ndarray, plan: list[int]) -> dict:
    """The manifest's ``outliers``: the pixels :func:`ilt.isf.outliers.clamp_isolated`
    replaced, in all and in the frames that had most."""
    order = np.argsort(-clamped, kind="stable")[:5]
    return {"sigmas": OUTLIER_SIGMAS, "pixels": int(clamped.sum()), "frames": int(np.count_nonzero(clamped)),
            "most": [{"beam": int(plan[i]), "pixels": int(clamped[i])} for i in order if clamped[i]]}


def own_cell_check(T: np.ndarray, plan: list[int], overlay: Path, block: int = 1024) -> dict:
    """The beams whose light is brightest in another beam's cell (or sample) than in their
    own: a spot's direct light dwarfs what the scene sends back (2.8-5.3x on the
    simulated scans), so such a column says the spot was assigned to the wrong beam (a
    swap, a reflection taken for the spot); one WARNING naming them, and the record."""
    m = T.shape[0]
    wrong = []
    for j0 in range(0, m, block):
        cols = np.asarray(T[:, j0:j0 + block])
        brightest = np.argmax(cols, axis=0)
        wrong += [(j0 + k, int(i)) for k, i in enumerate(brightest) if i != j0 + k]
    if wrong:
        shown = ", ".join(f"{plan[j]} -> {plan[i]}" for j, i in wrong[:8]) + (" ..." if len(wrong) > 8 else "")
        log.warning("%d beam%s light another beam's cell more than their own (beam -> brightest cell's beam: %s): "
                    "spots assigned to the wrong beams (swapped, or a reflection taken for the spot); ilt decompose "
                    "refuses such a T when its bounce series diverges: look at %s", len(wrong),
                    "" if len(wrong) == 1 else "s", shown, overlay)
    return {"wrong_beams": [{"beam": plan[j], "brightest_in": plan[i]} for j, i in wrong]}


def _column_norms(raw: np.ndarray) -> np.ndarray:
    """(b,) 2-norms of the columns of an (m, b) block, the same floats as
    ``np.linalg.norm`` of the whole (m, m) raw T along axis 0 gives: that sums each
    column's squares in row order, one row after another, which a running sum along
    the rows (cumsum) does for any block, where norm on a narrow block sums pairwise."""
    return np.sqrt(np.cumsum(np.square(raw), axis=0)[-1])


def _in_background(function, **kwargs) -> None:
    """Run ``function(**kwargs)`` in a daemon thread and go on (for a system call that
    releases the GIL: removing a file of m frames takes the kernel some 0.1 s)."""
    threading.Thread(target=function, kwargs=kwargs, daemon=True).start()


def centroids_and_isf(hdr_dir: str | os.PathLike, spots_out: str | os.PathLike, isf_out: str | os.PathLike,
                      params=None, dark=None, executor=None, workers: int | None = None, progress=None,
                      force: bool = False, **options) -> tuple[dict, dict]:
    """``ilt centroids`` then ``ilt build-isf`` on one HDR directory, decoding every EXR
    once: the centroids pass keeps each decoded frame (raw float32,
    :class:`ilt.io.frames.FrameScratch`) in a scratch directory beside ``isf_out``
    (m x H x W x 4 bytes of disk, removed at the end; memory still holds a few frames
    per worker), which build-isf reads back. With a
    ``dark`` frame (subtracted for centroids only) the frames are read twice.
    ``options``: :func:`build_isf`'s. Returns both stages' summaries.
    """
    import tempfile

    from ilt.spots.find import SpotParameters
    from ilt.spots.stage import run_centroids

    parent = Path(isf_out).absolute().parent
    parent.mkdir(parents=True, exist_ok=True)
    hdr = open_hdr_directory(hdr_dir)  # headers read once, for both stages
    with tempfile.TemporaryDirectory(dir=parent, prefix=".frames-") as scratch:
        cache = scratch if dark is None else None
        with beam_executor(executor, workers) as pool:  # one pool for both stages
            spots = run_centroids(hdr, spots_out, params or SpotParameters(), dark=dark, executor=pool,
                                  workers=workers, progress=progress, force=force, frame_cache=cache)
            isf = build_isf(hdr, spots_out, isf_out, executor=pool, workers=workers, progress=progress,
                            force=force, frame_cache=cache, **options)
    return spots, isf


def _read_sum(spots_dir: Path, shape, mapping, name: str = SUM_FILE) -> np.ndarray | None:
    from ilt.io.frames import read_frame_with_mapping

    path = spots_dir / name
    if not path.exists():   # build_isf says what it does instead
        return None
    try:
        image, own = read_frame_with_mapping(path, shape)
    except FrameError as exc:
        raise BuildError(str(exc)) from None
    if own is not None and own != mapping:
        raise BuildError(f"{path}: spots were found on frames mapped as {own.as_dict()}, these frames are "
                         f"{mapping.as_dict()}; run 'ilt centroids' on the same HDR directory")
    return image.astype(np.float64)


__all__ = ["SAMPLINGS", "BuildError", "build_isf", "centroids_and_isf", "lit_mask", "sample_like", "select_beams"]


def sample_like(isf, frames: np.ndarray) -> np.ndarray:
    """Read frames the way the ISF reads photos: integrated over its cells, or at its samples.

    frames: (H, W) or (N, H, W). Returns (m,) or (N, m) float64. Used to turn a
    simulator's true n-bounce frames into the truth a decomposition is measured against.
    """
    from ilt.isf.cells import integrate
    from ilt.isf.layout import sample_frame

    frames = np.asarray(frames)
    stack = frames[None] if frames.ndim == 2 else frames
    if isf.cells is not None:
        out = np.stack([integrate(f, isf.cells, isf.m) for f in stack])
    else:
        out = np.stack([sample_frame(f, isf.grid_samples) for f in stack])
    return out[0] if frames.ndim == 2 else out
