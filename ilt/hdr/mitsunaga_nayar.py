"""Mitsunaga & Nayar radiometric self-calibration (CVPR 1999, "Radiometric self calibration"),
made to hold on real brackets.

The inverse response is a polynomial on normalised measurements M in [0, 1]
(Mitsunaga & Nayar 1999, Eq. 3). For two exposures q, q+1 of the same pixel p with
exposure ratio R_q = e_{q+1} / e_q, f(M_{p,q+1}) = R_q f(M_{p,q}); the paper fits the
coefficients by least squares on ``f(M_{p,q+1}) - R_q f(M_{p,q})`` (their Eq. 4), then
re-estimates the ratios from f (their Eq. 7), and repeats until f stops changing (their
Eq. 8). Exposures here are sorted shortest first, so every R_q > 1.

On real brackets the paper's form fails (issue 20: the Memorial Church sequence, a
Canon 5D Mark II JPEG bracket): the free polynomial goes negative and non-monotone, the
ratios drift by stops, and an absolute residual favours an f that squashes everything
below M = 1 towards 0 (those residuals are small because f is). What is done instead:

- **Monotone by construction, f(0) = 0, f(1) = 1.** f is a polynomial of degree N in
  Bernstein form with non-decreasing coefficients 0 = b_0 <= b_1 <= ... <= b_N = 1,
  i.e. ``f = sum_j d_j phi_j`` with ``d_j >= 0``, ``sum d_j = 1`` and
  ``phi_j(M) = sum_{k >= j} B_{k,N}(M)``, the regularised incomplete beta function
  I_M(j, N - j + 1): a mixture of N beta CDFs. Every such f is a non-decreasing
  polynomial, and linear f is d_j = 1/N. Each step is a least-squares problem in d
  with d >= 0 and sum d = 1 (NNLS with the sum as a heavy row).
- **Relative, noise-weighted residuals.** The residual is read in log units,
  ``log f(M_hi) - log f(M_lo) - log R`` (what a merge's consistency is; Debevec & Malik
  fit in the same units), as iteratively reweighted least squares: the absolute
  residual divided by ``(f(M_hi) + R f(M_lo)) / 2`` of the previous step. Each pair is
  weighted by the inverse variance of that log residual under measurement noise s in
  M (``s^2 [(f'/f)(M_hi)^2 + (f'/f)(M_lo)^2]``, plus a floor ``kappa^2`` for the model's own
  error): dark pixels, where quantisation and read noise are a large part of the value,
  and the compressed shoulder near clipping count for little.
- **Robust.** Pairs whose normalised residual is far out (moving pixels, JPEG block
  artefacts, a clipped channel) are down-weighted by Cauchy weights
  ``1 / (1 + (u / 2.385 scale)^2)``, scale the MAD of the normalised residuals.
- **Ratios are trusted unless asked for** (``estimate_ratios``, the default for RAW
  data): with f free, f and the ratios are ambiguous (Grossberg & Nayar, "What can be
  known about the radiometric response from images?", ECCV 2002): on the Memorial
  sequence a straight f with ratios from 2.7 down to 1.4 explains the 1-stop bracket as
  well as the true curve with ratios of 2, and on a simulated 8-bit camera with ratios
  from 14 to 1.4.
- **Ratios, with f, not in turn.** f and log R_q are one Gauss-Newton problem, with a
  prior of a quarter stop on each ratio (:data:`RATIO_PRIOR_STOPS`): a ratio and f's
  slope over the pixels that exposure sees trade off, and the paper's alternation walks
  along that valley (see :func:`_fit`). f^gamma with R^gamma fits as well as f with R:
  with ``pin_span`` the sum of log R_q is kept at the nominal one (the bracket's span),
  which fixes gamma; an estimated ratio more than a stop from its nominal one is reported.
- **Order on held-out pixels**: the lowest degree within 2 % of the best median
  |log residual| on a held-out 30 % of the pixels (the training error never rises with N).
- **Convergence judged honestly**: f must change by less than ``tolerance`` at every M
  and every log R_q by less than ``tolerance``; else ``converged`` is False.
- At most ``max_pairs`` pixel pairs (a random subset, the same for every order) enter
  the fit: the cost is O(pairs N^2) an iteration, whatever the images' size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

_GRID = np.linspace(0.0, 1.0, 1001)

#: the floor of the log residual's standard deviation: how well a degree-N polynomial
#: can follow a camera's curve (a JPEG's tone curve is not a polynomial)
MODEL_FLOOR = 0.002
#: Cauchy weights: the usual constant for 95 % efficiency under Gaussian residuals
CAUCHY = 2.385
#: the order chosen is the lowest whose held-out error is within this fraction of the
#: best: differences of 1 % are noise (a linear RAW bracket: 0.01082 at order 1 against
#: 0.01068 at order 3, whose ratios were then 0.7 % off against 0.08 %)
ORDER_SLACK = 0.02
#: warps u = M^gamma tried for 8/16-bit data (the polynomial is in u)
GAMMAS = (0.6, 0.8, 1.0, 1.3, 1.6, 2.0, 2.4, 2.8)
#: the degree at which the warps are compared
GAMMA_PROBE_ORDER = 8
#: training pairs of each fit that chooses the warp and the order (the final fit takes all)
SELECTION_PAIRS = 30_000
#: an estimated ratio this many stops from its nominal one is reported
RATIO_WARN_STOPS = 1.0
#: the prior on each exposure ratio: log2(R / nominal) ~ N(0, this^2). Shutters and
#: apertures are within a third of a stop of their marks; the prior holds a ratio the
#: data cannot tell from f's slope, and gives way where they can
RATIO_PRIOR_STOPS = 0.25


class CalibrationError(ValueError):
    """Too little usable data to calibrate, or a fit that did not converge."""


@dataclass(frozen=True)
class ResponseFit:
    """A fitted inverse response and the bracket's measured exposure ratios.

    coefficients: (N+1,) float64 c_0 ... c_N of the power basis in u = M^exponent,
        f(M) = sum c_n u^n, f(0) = c_0 = 0 and f(1) = 1.
    bernstein: (N+1,) float64 Bernstein coefficients b_0 = 0 <= ... <= b_N = 1 of the
        same f in u (monotone by construction).
    exponent: gamma of the warp u = M^gamma (1 for RAW): a camera's f starts like
        M^gamma, which no polynomial in M follows in relative terms near 0.
    ratios: (Q-1,) float64 measured e_{q+1} / e_q, exposures sorted shortest first.
    nominal_ratios: (Q-1,) the ratios the exposure facts claimed.
    residual: robust RMS of the log residual log f(M_hi) - log f(M_lo) - log R over the
        pairs used that are mid-range (0.1 < M < 0.9) in both (1.4826 x median |.|): how
        far two exposures of a pixel disagree after linearisation, in log units.
    held_out: {order: held-out median |log residual|} for every order tried.
    iterations: reweighting steps of the last fit; pairs: pixel pairs used;
    converged: f and the ratios changed by less than the tolerance in the last step.
    """

    coefficients: np.ndarray
    ratios: np.ndarray
    nominal_ratios: np.ndarray
    residual: float
    held_out: dict[int, float] = field(default_factory=dict)
    iterations: int = 0
    pairs: int = 0
    converged: bool = True
    bernstein: np.ndarray | None = None
    exponent: float = 1.0

    @property
    def order(self) -> int:
        return len(self.coefficients) - 1

    def __call__(self, m: np.ndarray) -> np.ndarray:
        """f(M): normalised measurement -> normalised linear irradiance, same shape."""
        return _polyval(self.coefficients, np.asarray(m, dtype=np.float64) ** self.exponent)

    def linearity_error(self) -> float:
        """max over M in [0, 1] of |f(M) - M|: how far from a linear sensor."""
        return float(np.max(np.abs(self(_GRID) - _GRID)))

    def relative_exposures(self) -> np.ndarray:
        """(Q,) measured exposures relative to the shortest (1, R_0, R_0 R_1, ...)."""
        return np.concatenate([[1.0], np.cumprod(self.ratios)])

    def ratio_stops(self) -> np.ndarray:
        """(Q-1,) log2(measured / nominal ratio): how far each measured ratio is from its nominal one."""
        return np.log2(self.ratios / self.nominal_ratios)

    def table(self, samples: int = 1024) -> tuple[np.ndarray, np.ndarray]:
        """f sampled at ``samples`` evenly spaced M in [0, 1]: (M, f(M)), f non-decreasing."""
        m = np.linspace(0.0, 1.0, samples)
        f = np.maximum.accumulate(np.clip(self(m), 0.0, 1.0))
        f[0], f[-1] = 0.0, 1.0  # exact by construction; rounding of the power form aside
        return m, f


def fit_response(
    images: list[np.ndarray],
    exposures: np.ndarray,
    valid: list[np.ndarray] | None = None,
    *,
    order: int | None = None,
    max_order: int = 12,
    zero_intercept: bool = False,
    estimate_ratios: bool = False,
    pin_span: bool = False,
    tolerance: float = 1e-6,
    max_iterations: int = 200,
    held_out_fraction: float = 0.3,
    noise: float = 1 / 255,
    max_pairs: int = 100_000,
    exponent: float | None = None,
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
    order : polynomial degree N; None chooses 1..max_order on held-out pixels.
    zero_intercept : kept for callers of the polynomial form: f(0) = 0 holds for every fit.
    estimate_ratios : estimate the exposure ratios with f (default: trust the nominal
        ones). Only where f is known to be close to linear (RAW): for a free f the
        ratios and f are ambiguous (Grossberg & Nayar 2003), and on the Memorial sequence
        and the simulated 8-bit camera a straight f with ratios from 1.4 to 14 fits the
        1-stop brackets as well as the true f with ratios of 2.
    pin_span : keep the product of the ratios at its nominal value (breaks the
        f^gamma, R^gamma ambiguity when the nominal span is trusted).
    noise : standard deviation of M's noise (normalised units; 1/255: a few 8-bit codes).
    max_pairs : pixel pairs used at most (a random subset).
    exponent : the warp gamma of u = M^gamma (None: chosen among :data:`GAMMAS` on
        held-out pixels; 1 with ``zero_intercept``).

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
    ok = (m > 0) & (m < 1) if valid is None else np.stack([np.ravel(v) for v in valid]) & (m > 0) & (m <= 1)
    pair_ok = ok[:-1] & ok[1:]  # (Q-1, P)
    q_idx, p_idx = np.nonzero(pair_ok)
    if q_idx.size < 20:
        raise CalibrationError(f"only {q_idx.size} usable pixel pairs between consecutive "
                               "exposures; need brighter, unclipped overlap")
    if q_idx.size > max_pairs:
        keep = np.sort(rng.choice(q_idx.size, max_pairs, replace=False))
        q_idx, p_idx = q_idx[keep], p_idx[keep]
    pairs = _Pairs(m[q_idx, p_idx], m[q_idx + 1, p_idx], q_idx)
    missing = np.setdiff1d(np.arange(Q - 1), q_idx)
    if missing.size:
        raise CalibrationError(f"exposures {missing[0]} and {missing[0] + 1} (shortest first) share no usable "
                               "pixel: the bracket's steps are too far apart for this scene")
    nominal = e[1:] / e[:-1]
    settings = (zero_intercept, estimate_ratios, pin_span, tolerance, max_iterations, noise)
    gammas = [1.0] if (zero_intercept or exponent is not None) else list(GAMMAS)
    gamma = 1.0 if zero_intercept else (exponent or 1.0)
    orders = [order] if order else list(range(1, max_order + 1))
    held_out: dict[int, float] = {}
    if len(orders) > 1 or len(gammas) > 1:
        test = rng.random(m.shape[1]) < held_out_fraction
        tested = test[p_idx]
        train, check = pairs.subset(~tested), pairs.subset(tested)
        if train.count > SELECTION_PAIRS:  # the choice needs fewer pairs than the final fit
            train = train.subset(np.sort(rng.choice(train.count, SELECTION_PAIRS, replace=False)))
        # judged where a merge uses the pixels: mid-range in both exposures
        mid = (check.lo > 0.1) & (check.lo < 0.9) & (check.hi > 0.1) & (check.hi < 0.9)
        if mid.sum() < 20:
            mid = np.ones(check.count, bool)

        def judge(n, g, how):
            try:
                d, ratios, *_ = _fit(train, nominal, n, g, *settings)
            except CalibrationError:  # a fit that degenerates is simply not chosen
                return float("inf")
            return _held_out_error(check, d, ratios, n, g, mid, noise, how)

        if len(gammas) > 1:
            # the warp first, at a middle degree: it sets how f starts from 0
            probe = order or min(GAMMA_PROBE_ORDER, max_order)
            scores = {g: judge(probe, g, GAMMA_HELD_OUT) for g in gammas}
            gamma = min(scores, key=scores.get)
        if len(orders) > 1:
            held_out = {n: judge(n, gamma, HELD_OUT) for n in orders}
            best = min(held_out.values())
            if not math.isfinite(best):
                raise CalibrationError("no polynomial degree fits the bracket (every fit degenerated)")
            # the lowest order within ORDER_SLACK of the best held-out error: higher orders only chase noise
            orders = [min(n for n, err in held_out.items() if err <= best * (1 + ORDER_SLACK))]
    d, ratios, iterations, converged = _fit(pairs, nominal, orders[0], gamma, *settings)
    b = np.concatenate([[0.0], np.cumsum(d)])
    b[-1] = 1.0
    r = np.abs(pairs.log_residual(d, ratios, orders[0], gamma))
    middle = (pairs.lo > 0.1) & (pairs.lo < 0.9) & (pairs.hi > 0.1) & (pairs.hi < 0.9)
    residual = 1.4826 * float(np.median(r[middle] if middle.sum() >= 20 else r))
    return ResponseFit(_bernstein_to_power(b), ratios, nominal, residual, held_out, iterations,
                       pairs.count, converged, b, float(gamma))


#: how the order is judged on held-out pairs: "median" |log residual| mid-range, or
#: "normalised": median |log residual| / its noise sigma over every held-out pair
HELD_OUT = "normalised"
#: how the warp is judged: by the median |log residual| mid-range, which does not depend
#: on the noise each warp's own f' implies (the normalised figure would favour a warp
#: that claims more noise)
GAMMA_HELD_OUT = "median"


def _held_out_error(check, d, ratios, n, gamma, mid, noise, how) -> float:
    r = check.log_residual(d, ratios, n, gamma)
    if how == "median":
        return float(np.median(np.abs(r[mid])))
    lo, hi, dlo, dhi = check.basis(n, gamma)
    f_lo, f_hi = np.maximum(lo @ d, 1e-300), np.maximum(hi @ d, 1e-300)
    var = noise**2 * (((dhi @ d) / f_hi) ** 2 + ((dlo @ d) / f_lo) ** 2) + MODEL_FLOOR**2
    return float(np.median(np.abs(r) / np.sqrt(var)))


class _Pairs:
    """Pixel pairs (lo: exposure q, hi: exposure q + 1) and their basis values, per degree."""

    def __init__(self, lo, hi, q):
        self.lo, self.hi, self.q = lo, hi, q
        self._basis: dict[tuple[int, float], tuple] = {}

    @property
    def count(self) -> int:
        return int(self.lo.size)

    def subset(self, mask) -> _Pairs:
        """The pairs at ``mask`` (bool, or indices)."""
        return _Pairs(self.lo[mask], self.hi[mask], self.q[mask])

    def basis(self, n: int, gamma: float = 1.0):
        """(phi(lo), phi(hi), phi'(lo), phi'(hi)), each (pairs, n)."""
        key = (n, gamma)
        if key not in self._basis:
            lo, dlo = _phi(self.lo, n, gamma)
            hi, dhi = _phi(self.hi, n, gamma)
            self._basis = {key: (lo, hi, dlo, dhi)}  # one degree at a time: memory
        return self._basis[key]

    def log_residual(self, d, ratios, n, gamma=1.0) -> np.ndarray:
        lo, hi, _, _ = self.basis(n, gamma)
        f_lo, f_hi = lo @ d, hi @ d
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.log(f_hi) - np.log(f_lo) - np.log(ratios[self.q])
        return np.where(np.isfinite(r), r, 10.0)  # f = 0 at a used pixel: as bad as can be


def _phi(m, n: int, gamma: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """phi_j(M) = I_M(j, n - j + 1) (j = 1..n) and their derivatives, each (len(m), n).

    phi_j is the probability that a binomial (n, M) is >= j, so phi_j - phi_{j+1} is the
    Bernstein polynomial B_{j,n}; d phi_j / dM = n B_{j-1,n-1}(M)."""
    from scipy.special import betainc, binom

    u = m ** gamma
    j = np.arange(1, n + 1)
    phi = betainc(j[None, :], (n - j + 1)[None, :], u[:, None])
    k = j - 1
    dphi = n * binom(n - 1, k)[None, :] * u[:, None] ** k[None, :] * (1 - u[:, None]) ** (n - 1 - k)[None, :]
    if gamma != 1.0:
        dphi *= (gamma * np.maximum(m, 1e-12) ** (gamma - 1))[:, None]
    return phi, dphi


def _fit(pairs: _Pairs, nominal, n, gamma, zero_intercept, estimate_ratios, pin_span, tol, max_it, noise):
    """Fit f and the log ratios together, reweighting each step, until f and log R stop
    changing. Returns (d, ratios, iterations, converged).

    Each step is a Gauss-Newton step on the log residuals
    ``r = log(phi(hi) d) - log(phi(lo) d) - rho_q`` (rho = log R), whose Jacobian in d,
    ``J = phi(hi) / f(hi) - phi(lo) / f(lo)``, has ``J d = 0`` (r does not change with the
    scale of d): the linearised problem is ``min sum w (L + J d' - rho'_q)^2
    + lambda sum (rho' - rho_nominal)^2`` over d' >= 0 with sum d' = 1 (L the measured log
    ratios), and the step towards (d', rho') is halved until the objective falls. f and
    the ratios are solved together, not in turn: on a bracket whose exposures see
    different parts of the curve (short ones the dark pixels), an exposure ratio and f's
    slope where that exposure's pixels lie trade off, and alternating steps walk far
    along that valley (the Memorial sequence's 1-stop ratios went to 1.1 and 6.9). The
    prior on the ratios (:data:`RATIO_PRIOR_STOPS`) holds what the data cannot tell apart
    and gives way wherever they can.
    """
    lo, hi, dlo, dhi = pairs.basis(n, gamma)
    grid = _grid_basis(n, gamma)
    span = float(np.sum(np.log(nominal)))
    rho_nominal = np.log(nominal)
    rho = rho_nominal.copy()
    free = len(rho) if estimate_ratios else 0
    prior = 1.0 / (RATIO_PRIOR_STOPS * math.log(2)) ** 2
    d = np.full(n, 1.0 / n)  # f(M) = M
    previous = (grid @ d, rho.copy())

    def objective(d_, rho_, w):
        f_lo, f_hi = lo @ d_, hi @ d_
        if not (np.all(f_lo > 0) and np.all(f_hi > 0)):
            return math.inf
        r = np.log(f_hi) - np.log(f_lo) - rho_[pairs.q]
        return float(np.sum(w * r * r)) + prior * float(np.sum((rho_ - rho_nominal) ** 2)) * bool(free)

    for iteration in range(1, max_it + 1):
        f_lo, f_hi = lo @ d, hi @ d
        L = np.log(f_hi) - np.log(f_lo)
        w = _weights(L - rho[pairs.q], f_lo, f_hi, dlo @ d, dhi @ d, noise)
        J = hi / f_hi[:, None] - lo / f_lo[:, None]
        d_new, rho_new = _solve_step(J, L, pairs, w, rho if not free else None, rho_nominal, prior,
                                     span if (pin_span and free) else None)
        before = objective(d, rho, w)
        step = 1.0
        while step >= 1e-3:
            d_try, rho_try = d + step * (d_new - d), rho + step * (rho_new - rho)
            if objective(d_try, rho_try, w) <= before:
                d, rho = d_try, rho_try
                break
            step *= 0.5
        now = (grid @ d, rho.copy())
        change = max(np.max(np.abs(now[0] - previous[0])), np.max(np.abs(now[1] - previous[1])))
        previous = now
        if change < tol:
            return d, np.exp(rho), iteration, True
    return d, np.exp(rho), max_it, False


def _solve_step(J, L, pairs, w, fixed_rho, rho_nominal, prior, span):
    """The linearised problem of :func:`_fit`: (d' >= 0 with sum 1, rho'); ``fixed_rho``
    keeps the ratios; ``span`` pins sum rho'."""
    from scipy.optimize import lsq_linear

    n, k = J.shape[1], len(rho_nominal)
    if fixed_rho is not None:
        A, b = J, fixed_rho[pairs.q] - L
    else:
        E = np.zeros((len(L), k))
        E[np.arange(len(L)), pairs.q] = -1.0
        A, b = np.hstack([J, E]), -L
    G = A.T @ (A * w[:, None])
    g = A.T @ (w * b)
    if fixed_rho is None:
        G[n:, n:] += prior * np.eye(k)
        g[n:] += prior * rho_nominal
    vals, vecs = np.linalg.eigh(G)
    keep = vals > vals.max() * 1e-14
    root = np.sqrt(vals[keep])[:, None] * vecs[:, keep].T  # root.T @ root = G on its range
    rhs = (vecs[:, keep].T @ g) / np.sqrt(vals[keep])
    heavy = 1e4 * math.sqrt(float(vals.max()))
    rows, targets = [root], [rhs]
    sum_row = np.zeros(G.shape[0])
    sum_row[:n] = heavy
    rows.append(sum_row[None, :])
    targets.append([heavy])
    if span is not None and fixed_rho is None:
        span_row = np.zeros(G.shape[0])
        span_row[n:] = heavy
        rows.append(span_row[None, :])
        targets.append([heavy * span])
    lower = np.concatenate([np.zeros(n), np.full(G.shape[0] - n, -np.inf)])
    result = lsq_linear(np.vstack(rows), np.concatenate(targets), bounds=(lower, np.inf),
                        method="bvls", lsmr_tol=None)
    d = np.maximum(result.x[:n], 0.0)
    if not d.sum() > 0:
        raise CalibrationError("the response fit degenerated (all its weights are zero)")
    d /= d.sum()
    rho = fixed_rho if fixed_rho is not None else result.x[n:]
    return d, rho


_GRID_CACHE: dict[tuple[int, float], np.ndarray] = {}


def _grid_basis(n: int, gamma: float) -> np.ndarray:
    if (n, gamma) not in _GRID_CACHE:
        _GRID_CACHE[(n, gamma)] = _phi(_GRID, n, gamma)[0]
    return _GRID_CACHE[(n, gamma)]


def _weights(r, f_lo, f_hi, df_lo, df_hi, noise) -> np.ndarray:
    """Inverse variance of each log residual under noise ``noise`` in M (plus the model
    floor), times Cauchy weights of the normalised residual."""
    var = noise**2 * ((df_hi / f_hi) ** 2 + (df_lo / f_lo) ** 2) + MODEL_FLOOR**2
    u = r / np.sqrt(var)
    spread = 1.4826 * float(np.median(np.abs(u)))
    robust = 1.0 / (1.0 + (u / (CAUCHY * max(spread, 1e-12))) ** 2)
    return robust / var


def _bernstein_to_power(b: np.ndarray) -> np.ndarray:
    """Power-basis coefficients c of sum_k b_k B_{k,N}(M)."""
    from scipy.special import binom

    n = len(b) - 1
    c = np.zeros(n + 1)
    for k in range(n + 1):
        # B_{k,n}(M) = C(n,k) M^k (1 - M)^(n-k) = sum_i C(n,k) C(n-k,i) (-1)^i M^(k+i)
        for i in range(n - k + 1):
            c[k + i] += b[k] * binom(n, k) * binom(n - k, i) * (-1) ** i
    return c


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
