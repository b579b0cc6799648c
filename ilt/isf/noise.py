"""The noise of the beam frames, and of T's entries, measured from the frames themselves.

A beam frame's pixel X carries photon noise, which grows with its signal, and read
noise, which does not: to first order ``Var[X] = a + b max(E[X], 0)`` (frame units^2),
whatever made the frame (ilt merge, another lab's HDR tool, a simulator). The sum of the
scan's m frames (``spots/sum.exr``, written by ``ilt centroids``) then has
``Var[S] = m a + b S``: both numbers are read off that one image, with no extra pass over
the frames and no knowledge of the camera, by :func:`fit_frame_noise`:

- the residual ``d = S - mean of its 4 neighbours`` removes the smooth light (the
  indirect part, flat and linear ramps exactly) and keeps the noise, with
  ``Var[d] = 1.25 Var[S]`` for independent pixels;
- pixels are binned by a 5 x 5 mean of S (not by S itself, whose noise would sort them)
  and each bin's variance is the squared MAD of d (a robust sigma: spot flanks, folds and
  occluding edges, where the light has curvature, are a minority in every bin but the
  brightest); pixels within 3 px of a spot's centroid are left out;
- a line ``v = m a + b s`` is fitted over the bins, weighted by their pixel counts over
  ``v^2``, with bins more than 1.5 x above the line (curvature) dropped and the line
  refitted.

An entry of T is a cell sum of n_i pixels of one frame, so its variance is the sum of
theirs: ``Var[T_ij] = a n_i + b max(T_ij, 0)`` in raw units (:func:`cell_variance`),
divided by the column's squared norm for T's unit columns. A merged HDR frame's bright
pixels, taken from shorter exposures, are noisier than the line says (its slope steps up
where the longest exposure clips): the line is fitted where most pixels are, the indirect
light, which is what the inversion amplifies. Noise-free frames give ``a`` and ``b`` at
the level of their curvature (on a dense lattice's sum, a fifth of a 2e4 e- sensor's
slope): frames with no negative pixel, as noise-free frames are (black-subtracted noise
reads below zero half the time), get no noise model, as :func:`ilt.isf.build.lit_mask`
takes them.

Written as ``noise.json`` in the ISF (:func:`write_noise`): the two numbers, how they were
measured, and ``entry_sigma``, the RMS noise of T's unit-column entries (the noise level
``ilt decompose`` regularises and compresses to, instead of guessing it from T's negative
entries). Checked in tests against repeated noise draws of simulated frames.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

NOISE_FILE = "noise.json"
#: bins of the fit (equal pixel counts) and the fewest pixels a bin needs
BINS = 48
MIN_BIN_PIXELS = 64
#: pixels binned at most (evenly strided): sorting them is the fit's cost
MAX_PIXELS = 1_000_000
#: pixels this close to a spot's centroid (frame-grid px) are left out of the fit
SPOT_RADIUS = 3.0
#: a bin this many times above the line is curvature, not noise: dropped and the line refitted
REJECT = 1.5
#: normal sigma per MAD
MAD_SIGMA = 1.4826


@dataclass(frozen=True)
class FrameNoise:
    """Per-pixel variance of one beam frame, ``a + b max(X, 0)`` (frame units^2).

    beams: frames in the sum it was fitted on; pixels / bins: used by the fit."""

    a: float
    b: float
    beams: int
    pixels: int
    bins: int

    def pixel_variance(self, signal: np.ndarray) -> np.ndarray:
        return self.a + self.b * np.maximum(signal, 0.0)

    def cell_variance(self, raw: np.ndarray, area: np.ndarray) -> np.ndarray:
        """Var of raw cell sums ``raw`` (m, b) over cells of ``area`` (m,) pixels."""
        return self.a * area[:, None] + self.b * np.maximum(raw, 0.0)


def fit_frame_noise(frame_sum: np.ndarray, beams: int, centroids: np.ndarray | None = None,
                    where: np.ndarray | None = None) -> FrameNoise | None:
    """Fit :class:`FrameNoise` to the sum of ``beams`` frames (module doc). ``centroids``:
    (k, 2) spot positions x, y on the frame's grid, left out with a margin;
    ``where``: (H, W) bool, the pixels to use (default all). None when fewer than
    4 bins' worth of pixels remain, or when the sum has fewer than 16 negative pixels."""
    from scipy.ndimage import convolve, distance_transform_edt, uniform_filter

    S = np.asarray(frame_sum, dtype=np.float64)
    if S.ndim != 2 or min(S.shape) < 8 or np.count_nonzero(S < 0) < 16:
        return None   # no negatives: noise-free frames (or clipped at zero by their maker), as lit_mask takes them
    kernel = np.array([[0, -0.25, 0], [-0.25, 1.0, -0.25], [0, -0.25, 0]])
    d = convolve(S, kernel, mode="nearest")
    level = uniform_filter(S, size=5, mode="nearest")
    use = np.ones(S.shape, bool) if where is None else np.asarray(where, bool).copy()
    use[[0, -1], :] = False
    use[:, [0, -1]] = False
    if centroids is not None and len(centroids):
        spots = np.ones(S.shape, bool)
        c = np.floor(np.asarray(centroids, dtype=np.float64) + 0.5).astype(np.int64)
        inside = (c[:, 0] >= 0) & (c[:, 0] < S.shape[1]) & (c[:, 1] >= 0) & (c[:, 1] < S.shape[0])
        spots[c[inside, 1], c[inside, 0]] = False
        use &= distance_transform_edt(spots) > SPOT_RADIUS
    s, r = level[use], d[use]
    if s.size < 4 * MIN_BIN_PIXELS:
        return None
    if s.size > MAX_PIXELS:   # a full-resolution sum: every k-th pixel is plenty for 48 bins
        step = -(-s.size // MAX_PIXELS)
        s, r = s[::step], r[::step]
    order = np.argsort(s, kind="stable")
    n_bins = int(min(BINS, s.size // MIN_BIN_PIXELS))
    levels, variances, counts = [], [], []
    for part in np.array_split(order, n_bins):
        rs = r[part]
        mad = float(np.median(np.abs(rs - np.median(rs))))
        levels.append(float(np.median(s[part])))
        variances.append((MAD_SIGMA * mad) ** 2 / 1.25)
        counts.append(part.size)
    x, v, n = np.array(levels), np.array(variances), np.array(counts, dtype=np.float64)
    keep = v > 0
    line = None
    for _ in range(8):
        if keep.sum() < 2:
            break
        w = n[keep] / np.maximum(v[keep], 1e-300) ** 2   # relative errors alike: sd(v) ~ v / sqrt(n)
        A = np.stack([np.ones(keep.sum()), np.maximum(x[keep], 0.0)], axis=1)
        line = np.linalg.lstsq(A * np.sqrt(w)[:, None], v[keep] * np.sqrt(w), rcond=None)[0]
        predicted = line[0] + line[1] * np.maximum(x, 0.0)
        again = keep & (v <= REJECT * np.maximum(predicted, 1e-300))
        if (again == keep).all():
            break
        keep = again
    if line is None:
        return None
    intercept, slope = max(float(line[0]), 0.0), max(float(line[1]), 0.0)
    return FrameNoise(a=intercept / max(beams, 1), b=slope, beams=int(beams), pixels=int(s.size),
                      bins=int(keep.sum()))


class EntryNoise:
    """The sum of T's unit-column entries' variances, a block of columns at a time as
    build-isf makes them: ``entry_sigma`` is their RMS."""

    def __init__(self, noise: FrameNoise, area: np.ndarray):
        self.noise, self.area = noise, np.asarray(area, dtype=np.float64)
        self.total, self.count = 0.0, 0

    def add(self, raw: np.ndarray, norms: np.ndarray) -> None:
        var = self.noise.cell_variance(raw, self.area) / (norms[None, :] ** 2)
        self.total += float(var.sum())
        self.count += var.size

    @property
    def entry_sigma(self) -> float:
        return float(np.sqrt(self.total / max(self.count, 1)))


def write_noise(directory: Path, noise: FrameNoise, entry_sigma: float, source: str) -> None:
    (Path(directory) / NOISE_FILE).write_text(json.dumps(
        {"model": "Var[pixel] = a + b max(X, 0), frame units", **asdict(noise),
         "entry_sigma": entry_sigma, "fitted_on": source}, indent=2) + "\n")


def read_noise(directory: str | Path) -> dict | None:
    """The ISF's ``noise.json`` as a dict, or None when the build could not measure it."""
    path = Path(directory) / NOISE_FILE
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text())
        float(data["entry_sigma"]), float(data["a"]), float(data["b"])
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not an ilt noise record ({exc})") from None
    return data


def entry_variance(T: np.ndarray, scales: np.ndarray, area: np.ndarray, noise: FrameNoise) -> np.ndarray:
    """(m, m) variance of T's unit-column entries from the frames' noise."""
    scales = np.asarray(scales, dtype=np.float64)
    return noise.cell_variance(np.asarray(T, dtype=np.float64) * scales[None, :], np.asarray(area, float)) \
        / scales[None, :] ** 2


__all__ = ["FrameNoise", "fit_frame_noise", "EntryNoise", "write_noise", "read_noise", "entry_variance", "NOISE_FILE"]
