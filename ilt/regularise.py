"""Regularisation of a noisy ISF matrix before inversion.

T is well conditioned (cond 3-4 for the scenes here), so plain inversion does not
amplify noise much: the error of ``Cn T`` is the noise in T carried through. What
helps is removing noise from T itself, using what light transport guarantees:
the indirect light a beam produces varies smoothly between neighbouring sample
pixels, and between neighbouring beams. ``smooth_isf`` filters the off-diagonal
entries of the unit-column T with a Gaussian of width w (in plan-layout steps)
along both the pixel and the beam index (normalised convolution that leaves the
directly lit entry out and puts it back untouched). ``regularise_isf`` picks w by
Morozov's discrepancy principle: the widest filter whose change to T is no larger
than the noise, ``||T_w - T||_F <= sigma sqrt(m (m - 1))``. Larger w lowers the
variance and raises the bias (edges between facets are blurred); the discrepancy
principle stops where the change would exceed what noise can explain.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter

from ilt.transport import prepare_isf

#: filter widths tried, in plan-layout steps (0: no filtering)
WIDTHS = (0.0, 0.25, 0.35, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0)


def _smooth_columns(T: np.ndarray, layout: tuple[int, int], width: float) -> np.ndarray:
    """Filter each column of T as an image in the plan layout, leaving out the diagonal."""
    m = T.shape[0]
    idx = np.arange(m)
    mask = np.ones((m, m))
    mask[idx, idx] = 0.0
    shape = (*layout, m)
    num = gaussian_filter((T * mask).reshape(shape), sigma=(width, width, 0), mode="nearest")
    den = gaussian_filter(mask.reshape(shape), sigma=(width, width, 0), mode="nearest")
    out = (num / den).reshape(m, m)
    out[idx, idx] = T[idx, idx]
    return out


def smooth_isf(T: np.ndarray, layout: tuple[int, int], width: float) -> np.ndarray:
    """T (m, m) with its off-diagonal entries filtered along pixels and beams.

    ``layout`` (rows, cols) is the plan's layout (rows * cols = m); ``width`` is the
    Gaussian's standard deviation in layout steps. Returns a new float64 array.
    """
    T = np.asarray(T, dtype=np.float64)
    if width <= 0:
        return T.copy()
    return _smooth_columns(_smooth_columns(T, layout, width).T, layout, width).T


@dataclass(frozen=True)
class Regularisation:
    """What ``regularise_isf`` chose and why.

    width: the filter width (0 = T left as measured); change: ``||T_w - T||_F`` of
    the unit-column T; noise_norm: ``sigma sqrt(m (m - 1))``, the change noise
    explains; tried: (width, change) for every candidate.
    """

    width: float
    change: float
    noise_norm: float
    tried: list

    def describe(self) -> str:
        if self.width == 0:
            return (f"T left as measured: even the narrowest filter changes it by more than the noise "
                    f"({self.tried[1][1]:.3g} > {self.noise_norm:.3g})" if len(self.tried) > 1 else "T left as measured")
        return (f"T filtered with width {self.width:g} (layout steps): change {self.change:.3g} <= noise "
                f"{self.noise_norm:.3g} (discrepancy principle)")


def regularise_isf(T: np.ndarray, layout: tuple[int, int], noise: float,
                   widths=WIDTHS) -> tuple[np.ndarray, Regularisation]:
    """Denoise T by the widest filter the noise allows (Morozov's discrepancy principle).

    Parameters
    ----------
    T : (m, m) measured ISF (any column scaling; filtered with unit columns).
    layout : (rows, cols) of the beam plan.
    noise : sigma of the noise per entry, relative to the unit-column T.

    Returns the filtered unit-column T (m, m) float64 and the :class:`Regularisation`.
    """
    T, norms = prepare_isf(T)
    unit = T / norms
    m = unit.shape[0]
    if layout[0] * layout[1] != m:
        raise ValueError(f"layout {layout} does not hold m = {m} samples")
    noise_norm = noise * np.sqrt(m * (m - 1.0))
    best, chosen, tried = unit, (0.0, 0.0), [(0.0, 0.0)]
    for w in sorted(w for w in widths if w > 0):
        candidate = smooth_isf(unit, layout, w)
        change = float(np.linalg.norm(candidate - unit))
        tried.append((w, change))
        if change > noise_norm:
            break
        best, chosen = candidate, (w, change)
    return best, Regularisation(width=chosen[0], change=chosen[1], noise_norm=float(noise_norm), tried=tried)


def discrepancy_choice(changes: list[tuple[float, float]], noise_norm: float) -> float:
    """The width :func:`regularise_isf` picks from ``(width, change)`` pairs in
    increasing width: the widest before the first change the noise cannot explain."""
    chosen = 0.0
    for w, change in sorted(changes):
        if w > 0 and change > noise_norm:
            break
        chosen = w
    return chosen


@dataclass(frozen=True)
class BiasVariance:
    """Bias against variance of the bounce images at one filter width, over noise draws.

    Per bounce n, relative to ``||Ln*||`` (the truth): ``bias`` = distance of the
    expected estimate from the truth, ``spread`` = the estimates' standard deviation
    (root of the summed variances), both unbiased estimates from the draws (the mean of
    d draws is off its expectation by spread / sqrt(d): that part is not counted as
    bias); ``error`` = root-mean-square distance of the draws from the truth.
    ``error^2 = bias^2 + spread^2`` for every bounce (while the bias estimate is
    positive; it is clipped at 0).
    ``pooled_*``: the same over all bounces stacked. ``chosen``: in how many draws the
    discrepancy principle picked this width.
    """

    width: float
    chosen: int
    bias: list
    spread: list
    error: list
    pooled_bias: float
    pooled_spread: float
    pooled_error: float


def bias_variance(T: np.ndarray, layout: tuple[int, int], photos: np.ndarray, truth: np.ndarray,
                  sigma: float, draws: int = 8, widths=WIDTHS, seed: int = 0) -> list[BiasVariance]:
    """Bias and variance of the bounce images from a noisy T, plain (width 0) and
    filtered at each width, measured over ``draws`` independent noise draws.

    T: (m, m) noise-free ISF; photos: (m, k) photos; truth: (N, m, k) their true
    bounces; sigma: noise per entry, relative to the unit-column T. Each draw adds
    Gaussian noise to the unit-column T, filters it at every width (:func:`smooth_isf`)
    and splits the photos with the dense solver. Returns one :class:`BiasVariance`
    per width, in increasing width.
    """
    from ilt.solvers import build_operator
    from ilt.transport import bounce_images

    T, norms = prepare_isf(T)
    unit = T / norms
    m = unit.shape[0]
    widths = sorted({0.0, *widths})
    n_bounces = truth.shape[0]
    noise_norm = sigma * np.sqrt(m * (m - 1.0))
    rng = np.random.default_rng(seed)
    estimates = {w: np.empty((draws, *truth.shape)) for w in widths}
    chosen = {w: 0 for w in widths}
    for k in range(draws):
        noisy = unit + sigma * rng.normal(size=unit.shape)
        noisy /= np.linalg.norm(noisy, axis=0)  # unit columns, as regularise_isf filters them
        changes = []
        for w in widths:
            filtered = smooth_isf(noisy, layout, w)
            changes.append((w, float(np.linalg.norm(filtered - noisy))))
            estimates[w][k] = bounce_images(build_operator(filtered, "dense")[0], photos, n_bounces).bounces
        chosen[discrepancy_choice(changes, noise_norm)] += 1
    scale = np.sqrt((truth ** 2).reshape(n_bounces, -1).sum(axis=1))
    pooled_scale = float(np.sqrt((scale ** 2).sum()))
    rows = []
    for w in widths:
        est = estimates[w]
        mean = est.mean(axis=0)
        # unbiased estimates: the mean of the draws is itself off the expectation by
        # spread / sqrt(draws), which would otherwise count as bias
        spread_sq = ((est - mean) ** 2).reshape(draws, n_bounces, -1).sum(axis=2).sum(axis=0) / max(draws - 1, 1)
        bias_sq = np.maximum(((mean - truth) ** 2).reshape(n_bounces, -1).sum(axis=1) - spread_sq / draws, 0.0)
        error_sq = ((est - truth) ** 2).reshape(draws, n_bounces, -1).sum(axis=2).mean(axis=0)
        rows.append(BiasVariance(
            width=w, chosen=chosen[w],
            bias=(np.sqrt(bias_sq) / scale).tolist(), spread=(np.sqrt(spread_sq) / scale).tolist(),
            error=(np.sqrt(error_sq) / scale).tolist(),
            pooled_bias=float(np.sqrt(bias_sq.sum()) / pooled_scale),
            pooled_spread=float(np.sqrt(spread_sq.sum()) / pooled_scale),
            pooled_error=float(np.sqrt(error_sq.sum()) / pooled_scale)))
    return rows
