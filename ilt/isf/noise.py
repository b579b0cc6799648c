"""The noise of the beam frames, and of T's entries, measured from the frames themselves.

A beam frame's pixel X carries photon noise, which grows with its signal, and read noise,
which does not; a merged bracket adds steps (a bright pixel comes from shorter exposures,
so its variance per unit of signal is larger). build-isf measures ``Var[X]`` as a
function of the pixel's level, whatever made the frames (ilt merge, another lab's HDR
tool, a simulator), from a sample of the beam frames (:data:`SAMPLE_FRAMES`, 8, evenly spread
over the scan), by :func:`fit_frame_noise`:

- the residual ``d = X - mean of its 4 neighbours`` removes the smooth light (the
  indirect part; flat and linear ramps exactly) and keeps the noise, with
  ``Var[d] = 1.25 Var[X]`` for independent pixels of like variance;
- pixels are binned by their 5 x 5 mean (not by X itself, whose noise would sort them),
  equal counts a bin, and each bin's variance is the squared MAD of d (a robust sigma:
  folds and occluding edges, where the light has curvature, are a minority in every bin);
  pixels within :data:`SPOT_RADIUS` px of the frame's own spot are left out;
- the bins' variances, made non-decreasing in the level (isotonic regression, weighted by
  the bins' counts: noise never falls as light grows), are the knots of a piecewise-linear
  ``v(X)``; below the first knot, the first knot's value; above the last, a line with the
  slope of the upper half of the knots (photon noise: proportional extrapolation read the
  read noise as photon noise too, 67% high on the box's spot flanks).

An entry of T is a cell sum of one frame's pixels, so its variance is the cell sum of
``v(X)``, taken with every pixel at the cell's mean level (:func:`cell_variance`: no pass
over the pixels; the interreflected light varies little inside a cell, and a per-pixel
integral cost 2.4x build-isf's time), written as ``T_var.npy``
(float32, the variance of T's unit-column entries), and ``noise.json`` records the knots
and ``entry_sigma``, the RMS noise of T's entries off its diagonal (the interreflected
light that the inversion amplifies and that regularisation smooths; the diagonal, a
spot's own cell, holds the brightest pixels, whose bins carry their flanks' curvature).
Frames with no negative pixel (noise-free, or clipped at zero by their maker: black-
subtracted noise reads below zero half the time) get no noise model, unless their noise
is plain in them (:func:`_noise_without_negatives`): photon counts without read noise and
a path tracer's Monte Carlo noise never go below zero, and without a model a scan of a
Lambertian scene with them failed the reciprocity check (no noise floor) and was refused.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: the side of the square about a pixel its level is read from (module doc: the fit bins
#: pixels by its mean; decompose reads a photo's model at its median)
LEVEL_WINDOW = 5

NOISE_FILE = "noise.json"
T_VAR_FILE = "T_var.npy"
#: beam frames the fit reads, evenly spread over the scan
SAMPLE_FRAMES = 8
#: bins of the fit (equal pixel counts) and the fewest pixels a bin needs
BINS = 48
MIN_BIN_PIXELS = 64
#: pixels binned at most (evenly strided): sorting them is the fit's cost
MAX_PIXELS = 250_000
#: pixels this close to a frame's spot centroid (frame-grid px) are left out of the fit
SPOT_RADIUS = 6.0
#: normal sigma per MAD
MAD_SIGMA = 1.4826
#: frames with no negative pixel get a noise model where their noise is at least this share
#: of the light, in the median bin, and independent from pixel to pixel
#: (:func:`_noise_without_negatives`)
MIN_RELATIVE_NOISE = 0.02
MAX_WIDE_RATIO = 1.5
#: such frames' bins: the mean of the residuals' squares, this share of the smallest kept
#: (fireflies and edges left out) ...
TRIM_KEEP = 0.98


def _trim_consistency(keep: float = TRIM_KEEP) -> float:
    """... over which a normal variable's mean square is this share of its variance:
    ``(keep - 2 z phi(z)) / keep`` with ``P(|x| < z) = keep`` (0.8735 for 98%). The knots
    keep the trimmed mean squares, which the thresholds that read them were measured with
    (divided by it, the photon-only sweep's fine fit sloped 73 of the M's 96 cells where it
    had kept all flat, and its 96- and 192-beam scans were 16% and 8% worse); the share of
    the light read off them, taken as the spots' cells' own variance, is divided by it
    (:func:`light_share_variance`: 13% low at 16 samples, 17% at 4)."""
    from statistics import NormalDist

    z = NormalDist().inv_cdf(0.5 + keep / 2)
    return (keep - 2.0 * z * NormalDist().pdf(z)) / keep


TRIM_CONSISTENCY = _trim_consistency()


@dataclass(frozen=True)
class FrameNoise:
    """Per-pixel variance of a beam frame against its level, piecewise linear through
    ``levels`` (increasing) and ``variances`` (non-decreasing), frame units^2.

    frames / pixels / bins: what the fit used; trimmed: the knots are trimmed mean squares
    (frames with no negative pixel), else squared MADs (:data:`TRIM_KEEP`)."""

    levels: tuple[float, ...]
    variances: tuple[float, ...]
    frames: int
    pixels: int
    bins: int
    slope: float = 0.0
    trimmed: bool = False

    def pixel_variance(self, signal: np.ndarray) -> np.ndarray:
        x, v = np.asarray(self.levels), np.asarray(self.variances)
        signal = np.asarray(signal, dtype=np.float64)
        out = np.interp(signal, x, v)
        above = signal > x[-1]
        if above.any():
            out[above] = v[-1] + self.slope * (signal[above] - x[-1])
        return out

    @classmethod
    def from_record(cls, data: dict) -> FrameNoise:
        """The model of a ``noise.json`` record (:func:`read_noise`)."""
        return cls(tuple(data["levels"]), tuple(data["variances"]), data["frames"], data["pixels"], data["bins"],
                   float(data["slope"]), bool(data.get("trimmed", False)))

    def as_dict(self) -> dict:
        return {"levels": list(self.levels), "variances": list(self.variances), "slope": self.slope,
                "frames": self.frames, "pixels": self.pixels, "bins": self.bins, "trimmed": self.trimmed}


def frame_residuals(frame: np.ndarray, spot: np.ndarray | None = None, step: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(levels, residuals) of one frame's usable pixels (module doc); ``step`` 2: the
    residual against the 4 pixels 2 px away (:func:`_noise_without_negatives`)."""
    from scipy.ndimage import convolve, uniform_filter

    X = np.asarray(frame, dtype=np.float64)
    if X.ndim != 2 or min(X.shape) < 8:
        return np.empty(0), np.empty(0)
    kernel = np.zeros((2 * step + 1, 2 * step + 1))
    kernel[step, step] = 1.0
    kernel[0, step] = kernel[-1, step] = kernel[step, 0] = kernel[step, -1] = -0.25
    d = convolve(X, kernel, mode="nearest")
    level = uniform_filter(X, size=LEVEL_WINDOW, mode="nearest")
    use = np.ones(X.shape, bool)
    use[[0, -1], :] = False
    use[:, [0, -1]] = False
    if spot is not None and np.all(np.isfinite(spot)):
        yy, xx = np.ogrid[:X.shape[0], :X.shape[1]]
        use &= (xx - spot[0]) ** 2 + (yy - spot[1]) ** 2 > SPOT_RADIUS**2
    return level[use], d[use]


def fit_frame_noise(frames, spots=None) -> FrameNoise | None:
    """Fit :class:`FrameNoise` to beam frames (a list of (H, W) arrays; module doc).
    ``spots``: each frame's spot centroid (x, y) on its grid, left out with a margin.
    None when the frames have fewer than 16 negative pixels and no plain noise (noise-free:
    :func:`_noise_without_negatives`) or too few pixels for 4 bins."""
    from scipy.optimize import isotonic_regression

    frames = list(frames)
    signed = sum(int(np.count_nonzero(np.asarray(f) < 0)) for f in frames) >= 16
    parts = [frame_residuals(f, None if spots is None else spots[k]) for k, f in enumerate(frames)]
    s = np.concatenate([p[0] for p in parts])
    r = np.concatenate([p[1] for p in parts])
    if s.size < 4 * MIN_BIN_PIXELS:
        return None
    if s.size > MAX_PIXELS:
        step = -(-s.size // MAX_PIXELS)
        s, r = s[::step], r[::step]
    order = np.argsort(s, kind="stable")
    n_bins = int(min(BINS, s.size // MIN_BIN_PIXELS))
    levels, variances, robust, counts = [], [], [], []
    for part in np.array_split(order, n_bins):
        rs = r[part]
        levels.append(float(np.median(s[part])))
        mad = float(np.median(np.abs(rs - np.median(rs))))
        robust.append((MAD_SIGMA * mad) ** 2 / 1.25)
        if not signed:   # mostly zeros where the light is faint: a MAD of 0; the mean square, its 2% largest out
            squares = np.sort(rs * rs)
            variances.append(float(np.mean(squares[:max(1, int(np.ceil(TRIM_KEEP * squares.size)))])) / 1.25)
        counts.append(float(part.size))
    x, v = np.array(levels), np.array(robust if signed else variances)
    if not signed and not _noise_without_negatives(x, v, parts, frames, spots):
        return None
    v = isotonic_regression(v, weights=np.array(counts)).x
    x, keep = np.unique(x, return_index=True)        # knots at distinct levels
    v = v[keep]
    upper = slice(x.size // 2, None)                 # above the last knot: the upper half's slope
    slope = float(np.polyfit(x[upper], v[upper], 1)[0]) if x[upper].size >= 2 and np.ptp(x[upper]) > 0 else 0.0
    return FrameNoise(levels=tuple(float(a) for a in x), variances=tuple(float(b) for b in v),
                      frames=len(frames), pixels=int(s.size), bins=int(x.size), slope=max(slope, 0.0),
                      trimmed=not signed)


def _noise_without_negatives(levels: np.ndarray, variances: np.ndarray, parts, frames, spots) -> bool:
    """Frames with no negative pixel: noise-free, clipped at zero by their maker, or with a
    noise that cannot go below zero (photon counts without read noise, a path tracer's
    Monte Carlo). True where their residuals are noise: as large against the pixels 2 px
    away as against the next ones (the light's own curvature makes the wider residual 4x
    the narrower; noise, independent from pixel to pixel, the same: the mean squares'
    ratio is under :data:`MAX_WIDE_RATIO`), and at least :data:`MIN_RELATIVE_NOISE` of the
    light in the median bin. Measured, ratio and share: noise-free renders of the
    simulator's M 21 and 0, box 2.5 and 1.4%, a textured albedo 1.15 (its texture is as
    fine as noise) and 1.0%, the emulated rig's noise-free 11 x 137 frames 9.7 and 21%;
    photon noise alone 0.99-1.01 and 140-170% (2e4 e- at the brightest spot pixel, the
    noisy sweep's lattices), 1.04 and 2.9% (500-2000 e- a pixel, tests/isf/test_noise.py)."""
    lit = levels > 0
    if np.count_nonzero(lit) < 16 or float(np.median(np.sqrt(variances[lit]) / levels[lit])) < MIN_RELATIVE_NOISE:
        return False
    def trimmed(level, d):   # the sum of squares of the lit pixels' residuals, the 2% largest left out
        squares = np.sort((d * d)[level > 0])
        return float(np.sum(squares[:int(np.ceil(TRIM_KEEP * squares.size))]))

    # ``parts``: the fit's own (levels, residuals) of each frame, against the next pixels
    narrow = sum(trimmed(*part) for part in parts)
    wide = sum(trimmed(*frame_residuals(frame, None if spots is None else spots[k], 2))
               for k, frame in enumerate(frames))
    return narrow > 0 and wide / narrow < MAX_WIDE_RATIO


#: the knots' variance grows at least as the level to this power for the noise to be read
#: as a share of each pixel's light (a path tracer's Monte Carlo noise: 2; photon noise: 1)
SHARE_EXPONENT = 1.5


def light_share_variance(noise: FrameNoise) -> float:
    """Var[pixel] / level^2 when the frames' noise is a share of each pixel's light (the
    log-log slope of the upper half of the knots' variances at least
    :data:`SHARE_EXPONENT`: the median ratio there), else 0 (photon and read noise). A
    spot's own cell then has the variance ``share * sum of its pixels' squares``, where
    :func:`cell_variance`, each pixel at the cell's mean level and the curve carried on as
    photon noise's line past the knots, put a spot's cell 60x low (docs/fullres.md). Knots
    that are trimmed mean squares are taken at their normal consistency (:func:`_trim_consistency`)."""
    x, v = np.asarray(noise.levels), np.asarray(noise.variances)
    upper = slice(x.size // 2, None)
    use = (x[upper] > 0) & (v[upper] > 0)
    if np.count_nonzero(use) < 3:
        return 0.0
    lx, lv = np.log(x[upper][use]), np.log(v[upper][use])
    if np.ptp(lx) <= 0 or np.polyfit(lx, lv, 1)[0] < SHARE_EXPONENT:
        return 0.0
    share = float(np.median(v[upper][use] / x[upper][use] ** 2))
    return share / TRIM_CONSISTENCY if noise.trimmed else share


#: beams with at least 2 neighbouring cells that :func:`diagonal_scatter` needs
MIN_SCATTER_BEAMS = 16
#: the median of a chi-square variable of 1 degree of freedom (a squared normal's median)
CHI2_MEDIAN = 0.4549
#: the relative standard error of a variance read as a median of n squares over CHI2_MEDIAN,
#: times sqrt(n) (simulated: 2.28-2.34 for n = 50 ... 800)
MEDIAN_VARIANCE_SE = 2.3


def diagonal_scatter(T: np.ndarray, pairs: np.ndarray, block: int = 1024) -> tuple[float, int] | None:
    """The relative sigma of T's diagonal that its neighbours' do not share: an upper
    bound of its noise, read off T itself. Each beam's indirect light over its own cell's,
    ``q_j = (column sum - T_jj) / T_jj``, does not depend on the albedo where the beam
    lands (both carry it) and changes smoothly from a cell to the next but at a fold or an
    edge; the diagonal's noise makes each ``q_j`` scatter about its neighbours' mean by as
    much (relative), the off-diagonal sums' noise little (hundreds of pixels). So the
    median over the beams of ``((q_j - mean of its neighbours' q) / that mean)^2 / (1 +
    1/n_j)`` (n_j neighbours, cells that share a pixel edge: ``pairs``), over the median of a
    squared normal, is the diagonal's relative variance plus the true change of q between
    neighbours (measured with photon noise, whose diagonal is 0.3% noisy: 4-5% on the M,
    4-23% on the box, where the off-diagonal sums carry the read noise of every pixel;
    a path tracer's noise with noise-free spots: 0.15-0.5% on the M). Returns (that sigma,
    the beams it was read on), or None with fewer than :data:`MIN_SCATTER_BEAMS` beams with
    two neighbours or more, or a diagonal not positive."""
    from scipy.sparse import coo_matrix

    m = T.shape[0]
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    d = np.asarray(np.diagonal(T), dtype=np.float64)
    if pairs.size == 0 or not np.all(d > 0):
        return None
    sums = np.zeros(m)
    for j0 in range(0, m, block):        # a memory-mapped T, a block of columns at a time
        sums[j0:j0 + block] = np.asarray(T[:, j0:j0 + block], dtype=np.float64).sum(axis=0)
    q = (sums - d) / d
    A = coo_matrix((np.ones(2 * len(pairs)), (np.r_[pairs[:, 0], pairs[:, 1]], np.r_[pairs[:, 1], pairs[:, 0]])),
                   shape=(m, m)).tocsr()
    A.data[:] = 1.0                       # a pair listed twice counts once
    n = np.asarray(A.sum(axis=1)).ravel()
    mean = (A @ q) / np.maximum(n, 1)
    use = (n >= 2) & (mean > 0)
    if np.count_nonzero(use) < MIN_SCATTER_BEAMS:
        return None
    residual = (q[use] - mean[use]) / mean[use]
    return float(np.sqrt(np.median(residual**2 / (1.0 + 1.0 / n[use])) / CHI2_MEDIAN)), int(residual.size)


def cap_spot_cells(variance: np.ndarray, T: np.ndarray, pairs: np.ndarray) -> dict | None:
    """Scale T_var's diagonal (``variance``, (m, m), in place) down to what T's diagonal
    scatters by (:func:`diagonal_scatter`, taken 2 standard errors high) when the frames'
    share of the light put it above that: the share is measured on the indirect light, and
    a path tracer that samples its light source at every hit renders a spotlight's spot
    noise-free while the light around it is noisy (the M, 16 samples: predicted 9.7%,
    scatter 0.15%; decompose's raise of the diagonal by 9.7%^2 then cost 1-4%). The
    record (for ``noise.json``), or None when there is nothing to measure."""
    d = np.asarray(np.diagonal(T), dtype=np.float64)
    diagonal = np.asarray(np.diagonal(variance), dtype=np.float64)
    positive = d > 0
    if not positive.any():
        return None
    predicted = float(np.median(diagonal[positive] / d[positive] ** 2))
    scatter = diagonal_scatter(T, pairs)
    if scatter is None or not predicted > 0:
        return None
    measured, beams = scatter
    bound = measured**2 * (1.0 + 2.0 * MEDIAN_VARIANCE_SE / np.sqrt(beams))
    scale = min(1.0, bound / predicted)
    if scale < 1.0:
        variance[np.diag_indices(variance.shape[0])] = diagonal * scale
    return {"predicted_sigma": float(np.sqrt(predicted)), "scatter_sigma": measured, "beams": beams,
            "scaled_by": scale}


def cell_variance(noise: FrameNoise, raw: np.ndarray, area: np.ndarray) -> np.ndarray:
    """(m, b) variance of raw cell sums ``raw`` over cells of ``area`` pixels: each pixel at
    its cell's mean level, ``n v(raw / n)``. The curve is convex, so this is the sum of
    the pixels' variances to within the light's variation inside the cell (small for the
    interreflected light; a spot's own cell, whose pixels span decades, gets less)."""
    n = np.maximum(np.asarray(area, dtype=np.float64), 1.0)[:, None]
    return n * noise.pixel_variance(raw / n)


class EntryNoise:
    """T's unit-column entry variances, a block of columns at a time as build-isf makes
    them, into ``out`` ((m, m) float32, a memory map of T_var.npy); ``entry_sigma`` is the
    RMS of the entries off the diagonal."""

    def __init__(self, out: np.ndarray):
        self.out = out
        self.total, self.count = 0.0, 0

    def add(self, j0: int, variance: np.ndarray, norms: np.ndarray) -> None:
        """Columns j0 .. j0 + b - 1: ``variance`` (m, b) raw cell sums of the frames' variance images."""
        unit = variance / norms[None, :] ** 2
        self.out[:, j0:j0 + unit.shape[1]] = unit
        k = np.arange(unit.shape[1])
        diagonal = unit[j0 + k, k]
        self.total += float(unit.sum() - diagonal.sum())
        self.count += unit.size - unit.shape[1]

    @property
    def entry_sigma(self) -> float:
        return float(np.sqrt(max(self.total, 0.0) / max(self.count, 1)))


def write_noise(directory: Path, noise: FrameNoise, entry_sigma: float, source: str,
                spot_cells: dict | None = None) -> None:
    """``noise.json``; ``spot_cells``: what :func:`cap_spot_cells` measured, when it ran."""
    record = {"model": "Var[pixel] piecewise linear in its level through levels/variances (frame units)",
              **noise.as_dict(), "entry_sigma": entry_sigma, "T_var": T_VAR_FILE, "fitted_on": source}
    if spot_cells is not None:
        record["spot_cells"] = spot_cells
    (Path(directory) / NOISE_FILE).write_text(json.dumps(record, indent=2) + "\n")


def read_noise(directory: str | Path) -> dict | None:
    """The ISF's ``noise.json`` as a dict, or None when the build could not measure it."""
    path = Path(directory) / NOISE_FILE
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text())
        float(data["entry_sigma"])
        FrameNoise.from_record(data)
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not an ilt noise record ({exc})") from None
    return data


def read_entry_variance(directory, m: int) -> np.ndarray | None:
    """(m, m) the variance of each unit-column entry of T as build-isf measured it from the
    frames (``directory / T_var.npy``, memory-mapped), or None: no file, or another T's shape."""
    path = Path(directory) / T_VAR_FILE
    if not path.is_file():
        return None
    variance = np.load(path, mmap_mode="r")
    return variance if variance.shape == (m, m) else None

__all__ = ["NOISE_FILE", "T_VAR_FILE", "EntryNoise", "FrameNoise", "cap_spot_cells", "cell_variance", "diagonal_scatter",
           "read_entry_variance",
           "fit_frame_noise", "frame_residuals", "read_noise", "write_noise"]
