"""Mitsunaga & Nayar radiometric self-calibration (CVPR 1999, "Radiometric self calibration").

The inverse response is a polynomial on normalised measurements M in [0, 1]
(Mitsunaga & Nayar 1999, Eq. 3):

    I = f(M) = sum_{n=0}^{N} c_n M^n,   with f(1) = 1, i.e. c_N = 1 - sum_{n<N} c_n.

For two exposures q, q+1 of the same pixel p with exposure ratio R_q = e_{q+1} / e_q,
f(M_{p,q+1}) = R_q f(M_{p,q}); the coefficients minimise the error (their Eq. 4)

    eps = sum_q sum_p [f(M_{p,q+1}) - R_q f(M_{p,q})]^2,

a linear least-squares problem in c once c_N is eliminated (their Eqs. 5-6). The ratios
are then re-estimated from the new f (their Eq. 7) and the two steps repeat until f
changes by less than a tolerance at every M (their Eq. 8). Exposures here are sorted
from shortest to longest, so every R_q > 1 (the paper writes the inverse ratios).

Differences from the paper, each for a reason:
- ratios are not re-estimated as means of per-pixel ratios, which noise in the
  denominator biases upward. With the intercept fixed at 0 (RAW: f is close to linear)
  they are ratios of sums, sum_p f(M_{p,q+1}) / sum_p f(M_{p,q}), unbiased under
  zero-mean noise; otherwise the R_q that minimise eps at fixed f,
  sum_p f(M_{p,q+1}) f(M_{p,q}) / sum_p f(M_{p,q})^2, so each step lowers eps;
- the order N is chosen on held-out pixels (the training error never rises with N);
- f^gamma with R^gamma fits as well as f with R. For RAW data the constant term is
  fixed at 0 and the order kept low; for non-linear data the product of the ratios
  (the bracket's span) can be pinned to the nominal one (``pin_span``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

_GRID = np.linspace(0.0, 1.0, 1001)


class CalibrationError(ValueError):
    """Too little usable data to calibrate, or a fit that did not converge."""


@dataclass(frozen=True)
class ResponseFit:
    """A fitted inverse response and the bracket's measured exposure ratios.

    coefficients: (N+1,) float64 c_0 ... c_N, f(M) = sum c_n M^n, f(1) = 1.
    ratios: (Q-1,) float64 measured e_{q+1} / e_q, exposures sorted shortest first.
    nominal_ratios: (Q-1,) the ratios the exposure facts claimed.
    residual: RMS of f(M_{q+1}) - R_q f(M_q) over all sample pairs (normalised units).
    held_out: {order: held-out RMS residual} for every order tried.
    iterations: alternations of the last fit; pairs: sample pairs used;
    converged: f changed by less than the tolerance everywhere in the last iteration.
    """

    coefficients: np.ndarray
    ratios: np.ndarray
    nominal_ratios: np.ndarray
    residual: float
    held_out: dict[int, float] = field(default_factory=dict)
    iterations: int = 0
    pairs: int = 0
    converged: bool = True

    @property
    def order(self) -> int:
        return len(self.coefficients) - 1

    def __call__(self, m: np.ndarray) -> np.ndarray:
        """f(M): normalised measurement -> normalised linear irradiance, same shape."""
        return _polyval(self.coefficients, m)

    def linearity_error(self) -> float:
        """max over M in [0, 1] of |f(M) - M|: how far from a linear sensor."""
        return float(np.max(np.abs(self(_GRID) - _GRID)))

    def relative_exposures(self) -> np.ndarray:
        """(Q,) measured exposures relative to the shortest (1, R_0, R_0 R_1, ...)."""
        return np.concatenate([[1.0], np.cumprod(self.ratios)])


def fit_response(
    images: list[np.ndarray],
    exposures: np.ndarray,
    valid: list[np.ndarray] | None = None,
    *,
    order: int | None = None,
    max_order: int = 6,
    zero_intercept: bool = False,
    estimate_ratios: bool = True,
    pin_span: bool = False,
    tolerance: float = 1e-6,
    max_iterations: int = 200,
    held_out_fraction: float = 0.3,
    rng: np.random.Generator | None = None,
) -> ResponseFit:
    """Fit the inverse response of a camera from a bracket of one static scene.

    Parameters
    ----------
    images : Q arrays of the same shape (any), normalised measurements M in [0, 1],
        sorted by exposure, shortest first. Several scenes: concatenate their pixels.
    exposures : (Q,) nominal exposures (t / N^2), increasing; only their ratios matter.
    valid : Q bool masks, True where M is usable (not clipped, above the noise floor);
        default: 0 < M < 1.
    order : polynomial order N; None chooses 1..max_order on held-out pixels.
    zero_intercept : fix c_0 = 0 (RAW data: f(0) = 0 is known).
    estimate_ratios : re-estimate the exposure ratios (else trust the nominal ones).
    pin_span : keep the product of the ratios at its nominal value (breaks the
        f^gamma, R^gamma ambiguity when the nominal span is trusted).

    Returns a ResponseFit. Raises CalibrationError with too few usable pairs.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    e = np.asarray(exposures, dtype=np.float64)
    Q = len(images)
    if Q < 2 or e.shape != (Q,):
        raise CalibrationError(f"need at least two exposures with one exposure value each (got {Q})")
    if np.any(np.diff(e) <= 0):
        raise CalibrationError("exposures must be sorted shortest first and distinct")
    m = np.stack([np.ravel(np.asarray(im, dtype=np.float64)) for im in images])
    ok = (m > 0) & (m < 1) if valid is None else np.stack([np.ravel(v) for v in valid])
    pair_ok = ok[:-1] & ok[1:]  # (Q-1, P)
    usable = pair_ok.any(axis=0)
    if pair_ok.sum() < 20:
        raise CalibrationError(f"only {int(pair_ok.sum())} usable pixel pairs between consecutive "
                               "exposures; need brighter, unclipped overlap")
    m, pair_ok = m[:, usable], pair_ok[:, usable]
    nominal = e[1:] / e[:-1]
    lowest = 1 if zero_intercept else 0
    orders = [order] if order else list(range(max(lowest, 1), max_order + 1))
    held_out = {}
    if len(orders) > 1:
        test = rng.random(m.shape[1]) < held_out_fraction
        for n in orders:
            try:
                fit = _alternate(m[:, ~test], pair_ok[:, ~test], nominal, n, zero_intercept,
                                 estimate_ratios, pin_span, tolerance, max_iterations)
            except CalibrationError:  # an order that degenerates is simply not chosen
                held_out[n] = float("inf")
                continue
            held_out[n] = _rms(fit[0], fit[1], m[:, test], pair_ok[:, test])
        best = min(held_out.values())
        # the lowest order within 1 % of the best held-out error: higher orders only chase noise
        orders = [min(n for n, err in held_out.items() if err <= best * 1.01)]
    c, ratios, iterations, converged = _alternate(m, pair_ok, nominal, orders[0], zero_intercept,
                                       estimate_ratios, pin_span, tolerance, max_iterations)
    return ResponseFit(c, ratios, nominal, _rms(c, ratios, m, pair_ok), held_out, iterations,
                       int(pair_ok.sum()), converged)


class _Moments:
    """Sums over the sample pairs of products of powers, so that each iteration costs
    O(Q N^2) whatever the number of pixels: for pair q, ``G[q][i, j]`` is the sum of
    u_i u_j over u = (hi^0 .. hi^N, lo^0 .. lo^N)."""

    def __init__(self, m, pair_ok, order):
        self.order = order
        self.G = []
        for q in range(m.shape[0] - 1):
            sel = pair_ok[q]
            u = np.concatenate([np.vander(m[q + 1, sel], order + 1, increasing=True),
                                np.vander(m[q, sel], order + 1, increasing=True)], axis=1)
            self.G.append(u.T @ u)
        self.count = int(pair_ok.sum())

    def blocks(self, q):
        n = self.order + 1
        G = self.G[q]
        return G[:n, :n], G[:n, n:], G[n:, n:]

    def power_sums(self, q):
        n = self.order + 1
        return self.G[q][0, :n], self.G[q][0, n:]  # sum hi^j, sum lo^j (u_0 = 1)

    def sum_squared_residual(self, c, ratios) -> float:
        total = 0.0
        for q in range(len(self.G)):
            hh, hl, ll = self.blocks(q)
            r = ratios[q]
            total += c @ (hh - r * (hl + hl.T) + r * r * ll) @ c
        return max(total, 0.0)


def _alternate(m, pair_ok, ratios, order, zero_intercept, estimate_ratios, pin_span, tol, max_it):
    method = "sum" if zero_intercept else "lsq"
    """Solve for c at fixed ratios, then ratios at fixed c, until f stops changing."""
    mom = _Moments(m, pair_ok, order)
    ratios = ratios.copy()
    span = np.sum(np.log(ratios))
    previous = None
    c = None
    for iteration in range(1, max_it + 1):
        c = _solve_coefficients(mom, ratios, zero_intercept)
        if estimate_ratios:
            ratios = _estimate_ratios(c, mom, method)
            if pin_span:
                logs = np.log(ratios)
                ratios = np.exp(logs * (span / logs.sum()))
        f = _polyval(c, _GRID)
        if previous is not None and np.max(np.abs(f - previous)) < tol:
            return c, ratios, iteration, True
        previous = f
    return c, ratios, max_it, not estimate_ratios


def _solve_coefficients(mom: _Moments, ratios, zero_intercept) -> np.ndarray:
    """Least squares for c_lowest..c_{N-1} with c_N = 1 - sum c_n (f(1) = 1).

    With d_n = hi^n - R lo^n the error is c^T D c, D = sum over pairs of d d^T; writing
    c = B a + e_N (B maps the free coefficients, c_N = 1 - sum of them) gives the normal
    equations B^T D B a = -B^T D e_N.
    """
    order = mom.order
    lowest = 1 if zero_intercept else 0
    c = np.zeros(order + 1)
    c[order] = 1.0
    if order == lowest:
        return c
    D = np.zeros((order + 1, order + 1))
    for q in range(len(mom.G)):
        hh, hl, ll = mom.blocks(q)
        r = ratios[q]
        D += hh - r * (hl + hl.T) + r * r * ll
    free = list(range(lowest, order))
    B = np.zeros((order + 1, len(free)))
    B[free, range(len(free))] = 1.0
    B[order, :] = -1.0
    lhs, rhs = B.T @ D @ B, -B.T @ D[:, order]
    scale = np.sqrt(np.diag(lhs))
    scale[scale == 0] = 1.0
    a = np.linalg.lstsq(lhs / np.outer(scale, scale), rhs / scale, rcond=None)[0] / scale
    c[free] = a
    c[order] = 1.0 - a.sum()
    return c


def _estimate_ratios(c, mom: _Moments, method: str) -> np.ndarray:
    """R_q given f: "sum" = sum f(hi) / sum f(lo); "lsq" = the R_q minimising eps,
    sum f(hi) f(lo) / sum f(lo)^2."""
    out = np.empty(len(mom.G))
    for q in range(len(out)):
        if method == "sum":
            hi, lo = mom.power_sums(q)
            num, den = c @ hi, c @ lo
        else:
            _, hl, ll = mom.blocks(q)
            num, den = c @ hl @ c, c @ ll @ c
        if den <= 0 or num <= 0:
            raise CalibrationError(f"exposure pair {q}: the response maps the samples to <= 0")
        out[q] = num / den
    return out


def _rms(c, ratios, m, pair_ok) -> float:
    mom = _Moments(m, pair_ok, len(c) - 1)
    return float(np.sqrt(mom.sum_squared_residual(c, ratios) / max(mom.count, 1)))


def _polyval(c: np.ndarray, m) -> np.ndarray:
    return np.polynomial.polynomial.polyval(np.asarray(m, dtype=np.float64), c)


def usable_samples(images: list[np.ndarray], low: float, high: float, clip: float = 1.0) -> list[np.ndarray]:
    """Q bool masks of samples to calibrate with, chosen without looking at their own noise.

    A sample is used where the mean of its 8 neighbours lies in [low, high] and the sample
    itself is below ``clip``. Choosing by a sample's own value biases the pairs near the
    thresholds (a sample just above the floor is there because its noise was positive);
    the neighbours' noise is independent of it. ``images``: (h, w) normalised M.
    """
    from scipy.ndimage import uniform_filter

    masks = []
    for im in images:
        im = np.asarray(im, dtype=np.float64)
        if im.ndim != 2 or min(im.shape) < 3:
            masks.append((im > low) & (im < high))
            continue
        neighbours = (uniform_filter(im, size=3, mode="nearest") * 9 - im) / 8
        masks.append((neighbours >= low) & (neighbours <= high) & (im < clip))
    return masks
