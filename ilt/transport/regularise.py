"""Regularisation of a noisy ISF matrix before inversion.

T is well conditioned (cond 3-4 for the scenes here), so plain inversion does not
amplify noise much: the error of ``Cn T`` is the noise in T carried through. What
helps is removing noise from T itself, using what light transport guarantees: the
indirect light a beam produces varies smoothly between neighbouring sample pixels,
and between neighbouring beams, except across the edge between two facets (where
the light one sees can jump: points on one plane exchange no light at all).

``smooth_isf`` filters the off-diagonal entries of the unit-column T along the pixel
index and then the beam index, in the plan layout, by an edge-aware diffusion: each
pass averages an entry with its four layout neighbours, weighted by how alike the two
neighbours' whole rows (pixels) or columns (beams) of T are. Two neighbours whose rows
differ by no more than the noise explains (``||T_p - T_q||^2 <= 2 m sigma^2``) are
averaged fully; the weight falls as ``exp(-excess / (2 m sigma^2 kappa))`` past that, so
a facet edge, where the rows differ by far more, is left sharp (a Gaussian filter
blurred it: its bias near the edges made the direct image T1 20x worse than plain
inversion at m = 972, sigma = 1e-3). The directly lit entry is left out and put back
untouched (normalised convolution). ``width`` is the standard deviation of the
diffusion on a uniform region, in layout steps.

``regularise_isf`` applies the filter at :data:`WIDTH`, measured to lower the error of
every bounce, the pooled bounces and T1 against plain inversion on the simulated
scenes for sigma 1e-4 to 1e-2, and keeps it only when its change to T is no larger
than the noise, ``||T_w - T||_F <= sigma sqrt(m (m - 1))`` (Morozov's discrepancy
principle, as a guard: a change past it removes more than noise). With ``width=None``
(what ``ilt decompose`` runs) it takes the width of :data:`CHOICES` whose estimated
error against the true T is least (:func:`choose_width`: Stein's unbiased risk
estimate, with each entry's own noise): T's noise grows with the beams, and the width
that serves a 48-beam scan leaves noise in a 384-beam one (docs/numerics.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ilt.transport.scan import IsfMatrix, scan_isf

#: filter widths of the bias/variance study, in plan-layout steps (0: no filtering)
WIDTHS = (0.0, 0.25, 0.5, 0.82, 1.0, 1.41, 2.0)
#: the width regularise_isf applies: two passes of the diffusion (measured: docs/numerics.md)
WIDTH = 0.82
#: the widths regularise_isf chooses among when not given one (:func:`choose_width`)
CHOICES = (0.82, 1.0, 1.41)
#: the choice counts the filter's bias^2 this many times its noise (measured on the noisy
#: sweep: docs/numerics.md)
BIAS_WEIGHT = 3.0
#: the filter's diagonal and row norms are measured exactly (the filter of the identity) up
#: to this many samples, else from PROBES random sign vectors (:func:`choose_width`)
PROBE_EXACT_M = 1024
PROBES = 128
#: T's diagonal is raised (:func:`diagonal_raise`) only where some entry's relative variance is past this
DIAGONAL_FLOOR = 1e-4
#: edge sensitivity: the weight of a neighbour pair falls by e for every kappa x the noise's
#: expected squared distance that their rows' distance exceeds it by
KAPPA = 0.25


def _edge_weights(unit: np.ndarray, layout: tuple[int, int], sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Weights of the layout neighbour pairs along the first index of ``unit`` (m, n):
    ((rows - 1, cols), (rows, cols - 1)), from the distance of their rows less what the
    noise explains. The pair's own two columns (their directly lit entries) are left out."""
    rows, cols = layout
    n = unit.shape[1]
    grid = unit.reshape(rows, cols, n)
    index = np.arange(rows * cols).reshape(rows, cols)
    expected = 2.0 * (n - 2) * sigma ** 2
    weights = []
    for a, b, ia, ib in ((grid[:-1], grid[1:], index[:-1], index[1:]),
                         (grid[:, :-1], grid[:, 1:], index[:, :-1], index[:, 1:])):
        diff = a - b
        d2 = np.einsum("...k,...k->...", diff, diff)
        for own in (ia, ib):
            d2 -= np.take_along_axis(diff, own[..., None], axis=-1)[..., 0] ** 2
        weights.append(np.exp(-np.maximum(d2 - expected, 0.0) / (2.0 * n * sigma ** 2 * KAPPA)))
    return weights[0], weights[1]


def _diffuse(unit: np.ndarray, layout: tuple[int, int], weights, width: float,
             skip_diagonal: bool = True) -> np.ndarray:
    """Edge-aware diffusion of ``unit`` (m, n) along its first index in the layout, to a
    standard deviation of ``width`` steps on a uniform region, the diagonal left out
    (``skip_diagonal``: else every entry is filtered alike, as a probe of the filter)."""
    rows, cols = layout
    m, n = unit.shape
    passes = math.ceil(3 * width ** 2)  # each pass at strength <= 0.5 spreads by <= 1/3 step^2
    strength = width ** 2 / (2 * passes - 4 * width ** 2)  # variance per pass 2s / (1 + 4s)
    down, right = (strength * w[..., None] for w in weights)
    idx = np.arange(min(m, n) if skip_diagonal else 0)
    mask = np.ones((m, n))
    mask[idx, idx] = 0.0
    mask = mask.reshape(rows, cols, n)
    x = unit.reshape(rows, cols, n) * mask
    den = mask.copy()  # the normalisation does not change between passes
    den[:-1] += down * mask[1:]
    den[1:] += down * mask[:-1]
    den[:, :-1] += right * mask[:, 1:]
    den[:, 1:] += right * mask[:, :-1]
    inside = mask > 0  # (a left-out entry can have den 0: every neighbour's weight underflowed)
    for _ in range(passes):
        num = x.copy()
        num[:-1] += down * x[1:]
        num[1:] += down * x[:-1]
        num[:, :-1] += right * x[:, 1:]
        num[:, 1:] += right * x[:, :-1]
        x = np.divide(num, den, out=np.zeros_like(num), where=inside)
    out = x.reshape(m, n)
    out[idx, idx] = unit[idx, idx]
    return out


def _pair_weights(unit: np.ndarray, pairs: np.ndarray, sigma, chunk: int = 256) -> np.ndarray:
    """Weights of the neighbour ``pairs`` (e, 2) of rows of ``unit`` (m, n), as
    :func:`_edge_weights` weighs a layout's: from the distance of the two rows less what
    the noise explains, their own two columns (directly lit entries) left out. ``sigma``:
    the noise of an entry, one for all or (m,) one for each row's entries."""
    n = unit.shape[1]
    sigma = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (unit.shape[0],))
    pair_var = sigma[pairs[:, 0]] ** 2 + sigma[pairs[:, 1]] ** 2      # 2 sigma^2 when one for all
    expected = (n - 2) * pair_var
    d2 = np.empty(len(pairs))
    for start in range(0, len(pairs), chunk):     # (chunk, n) at a time: all e x n would be 3 m^2 floats
        a, b = pairs[start:start + chunk, 0], pairs[start:start + chunk, 1]
        diff = unit[a] - unit[b]
        part = np.einsum("ek,ek->e", diff, diff)
        rows = np.arange(len(a))
        for own in (a, b):
            inside = own < n
            part[inside] -= diff[rows[inside], own[inside]] ** 2
        d2[start:start + chunk] = part
    return np.exp(-np.maximum(d2 - expected, 0.0) / (n * pair_var * KAPPA))


def _diffuse_pairs(unit: np.ndarray, pairs: np.ndarray, weights: np.ndarray, width: float,
                   skip_diagonal: bool = True, confidence: np.ndarray | None = None) -> np.ndarray:
    """:func:`_diffuse` on a graph: each pass averages a row of ``unit`` (m, n) with the
    rows it is paired with, the diagonal left out (unless not ``skip_diagonal``).
    ``confidence`` (m,): each row counts as much as it (a cell's pixels) in the averages."""
    import scipy.sparse

    m, n = unit.shape
    passes = math.ceil(3 * width ** 2)
    strength = width ** 2 / (2 * passes - 4 * width ** 2)
    a, b = pairs[:, 0], pairs[:, 1]
    W = scipy.sparse.coo_matrix((np.concatenate([weights, weights]) * strength,
                                 (np.concatenate([a, b]), np.concatenate([b, a]))), shape=(m, m)).tocsr()
    idx = np.arange(min(m, n) if skip_diagonal else 0)
    c = np.ones(m) if confidence is None else np.asarray(confidence, dtype=np.float64)
    x = np.array(unit, dtype=np.float64, order="C")
    x[idx, idx] = 0.0                               # left out: each entry's mask is 1 but the diagonal's
    # the normalisation, c mask + W (c mask), with the mask 1 but on the diagonal: c + W c
    # less W's entry (times its row's c) of the row whose entry is left out
    scale = np.empty((m, n))
    scale[:] = (W @ c + c).reshape(m, 1)
    pair = W.tocoo()                                # its entries: in the columns that hold a diagonal
    inside = pair.col < idx.size
    scale[pair.row[inside], pair.col[inside]] -= pair.data[inside] * c[pair.col[inside]]
    scale[idx, idx] = 1.0                           # > 0 everywhere else: no entry divides by 0
    np.reciprocal(scale, out=scale)                 # once: each pass multiplies
    weighted = c[:, None] if confidence is not None else None
    for _ in range(passes):
        if weighted is None:
            y = W @ x
            y += x
        else:
            cx = x * weighted
            y = W @ cx
            y += cx
        y *= scale
        y[idx, idx] = 0.0
        x = y
    x[idx, idx] = unit[idx, idx]
    return x


def _filter(unit: np.ndarray, layout: tuple[int, int] | None, noise: float, pairs: np.ndarray | None,
            confidence: np.ndarray | None = None):
    """``(along_pixels, along_beams)``: each ``f(x, width, skip_diagonal=True)`` diffuses
    ``x`` (m, k) along its first index to ``width``, with the edge weights of ``unit``
    between its rows (pixels) or its columns (beams), measured once: a further width, or a
    probe of the filter (``skip_diagonal=False``: no entry left out), goes through the
    same linear filter. ``noise``: an entry's, or with ``pairs`` (m,) each row's;
    ``confidence`` (m,), with ``pairs``: how much each row counts along pixels."""
    if pairs is not None:
        pixels = _pair_weights(unit, pairs, noise)
        # along beams a row's scale is common to the two entries averaged: two columns are
        # compared as the cells' sums, where every entry has its noise alike
        sums = unit if confidence is None else unit * np.asarray(confidence, dtype=np.float64)[:, None]
        columns = np.ascontiguousarray(sums.T)      # rows gathered from contiguous memory, both ways
        spread = np.square(noise) if confidence is None else np.square(np.asarray(noise) * confidence)
        beams = _pair_weights(columns, pairs, float(np.sqrt(np.mean(spread))))
        del columns, sums
        return (lambda x, width, skip_diagonal=True: _diffuse_pairs(x, pairs, pixels, width, skip_diagonal,
                                                                    confidence),
                lambda x, width, skip_diagonal=True: _diffuse_pairs(x, pairs, beams, width, skip_diagonal))
    pixels, beams = _edge_weights(unit, layout, noise), _edge_weights(unit.T, layout, noise)
    return (lambda x, width, skip_diagonal=True: _diffuse(x, layout, pixels, width, skip_diagonal),
            lambda x, width, skip_diagonal=True: _diffuse(x, layout, beams, width, skip_diagonal))


def smooth_isf(T: np.ndarray, layout: tuple[int, int] | None, width: float, noise: float,
               pairs: np.ndarray | None = None, confidence: np.ndarray | None = None) -> np.ndarray:
    """T (m, m) with its off-diagonal entries filtered along pixels and beams.

    ``layout`` (rows, cols) is the plan's layout (rows * cols = m); ``width`` is the
    diffusion's standard deviation in layout steps on a uniform region; ``noise`` is the
    noise per entry (sigma), which sets what counts as an edge. ``pairs`` (e, 2): the
    samples that neighbour each other instead of the layout's (an ISF's cells that share a
    pixel edge: row i's cell holds beam i's spot, so the same pairs neighbour as pixels and
    as beams). Returns a new float64 array.
    """
    T = np.asarray(T, dtype=np.float64)
    if width <= 0 or not np.all(np.asarray(noise) > 0):
        return T.copy()
    if pairs is not None:
        pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    along_pixels, along_beams = _filter(T, layout, noise, pairs, confidence)
    return along_beams(np.ascontiguousarray(along_pixels(T, width).T), width).T


def choose_width(unit: np.ndarray, layout: tuple[int, int] | None, noise: float,
                 variance: np.ndarray | None = None, pairs: np.ndarray | None = None,
                 widths=CHOICES, seed: int = 0,
                 confidence: np.ndarray | None = None) -> tuple[np.ndarray, float, list]:
    """The filtered unit-column T at the width of least estimated risk, that width (0:
    none has less than T as measured) and the table of (width, change, risk, bias^2,
    variance), all relative to T's total noise variance.

    The risk of each width is Stein's unbiased estimate of ``||T_w - T_true||^2`` (SURE:
    ``||T_w - T||^2 - sum V + 2 sum V dT_w/dT``), the filter taken as linear with T's
    edge weights and separable, ``T_w = P T B^T`` (P along pixels, B along beams), so
    that the divergence is ``sum V_ij P_ii B_jj`` and the filtered noise
    ``sum V_kl |P_k|^2 |B_l|^2``: the diagonals and row norms of P and B, exact (the
    filter of the identity) up to :data:`PROBE_EXACT_M` samples, else from
    :data:`PROBES` random sign vectors (Hutchinson's estimator; seeded: the same T gets
    the same width). ``V`` (m, m): each entry's variance (T_var.npy), else ``noise**2``.
    The rest of the risk is the filter's bias^2, which counts :data:`BIAS_WEIGHT` times:
    a filter's bias is alike along a row of T and adds up in the bounces, where its noise
    averages out. Widths are reached one from the next (diffusions add their
    variances), so the widest one's passes are all the cost. A width whose change to T
    is past the noise (the discrepancy principle, ``||T_w - T||^2 > sum V``) is not taken.
    """
    m = unit.shape[0]
    if pairs is not None:
        pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    along_pixels, along_beams = _filter(unit, layout, noise, pairs, confidence)
    if m <= PROBE_EXACT_M:
        probe = np.eye(m)
        scale = 1.0
    else:
        probe = np.random.default_rng(seed).choice([-1.0, 1.0], size=(m, PROBES))
        scale = 1.0 / PROBES
    if variance is None and np.ndim(noise) > 0:       # one for each row
        variance = np.repeat(np.square(np.asarray(noise, dtype=np.float64))[:, None], m, axis=1)
    if variance is None:
        total = noise ** 2 * m * (m - 1.0)

        def weighted(a, b):      # sum over i != j of V_ij a_i b_j
            return noise ** 2 * (a.sum() * b.sum() - a @ b)
    else:
        variance = np.asarray(variance, dtype=np.float64)    # once (T_var.npy is float32 on disk)
        diagonal = np.diagonal(variance).copy()
        total = float(variance.sum() - diagonal.sum())

        def weighted(a, b):
            return float(a @ (variance @ b) - np.sum(diagonal * a * b))
    total = max(total, np.finfo(float).tiny)
    # T and its transpose alternate (the two filters commute): one transpose a width
    x, flipped, measured = unit, False, (unit, np.ascontiguousarray(unit.T))
    p, b, previous = probe, probe, 0.0
    best, best_risk, best_x = 0.0, 1.0, unit
    table = []
    for width in sorted(widths):
        delta = math.sqrt(width ** 2 - previous ** 2)
        previous = width
        first, second = (along_beams, along_pixels) if flipped else (along_pixels, along_beams)
        x = second(np.ascontiguousarray(first(x, delta).T), delta)
        flipped = not flipped
        p, b = along_pixels(p, delta, False), along_beams(b, delta, False)
        fit = float(np.sum((x - measured[flipped]) ** 2))      # the diagonal is put back: 0 there
        divergence = weighted(scale * np.sum(probe * p, axis=1), scale * np.sum(probe * b, axis=1))
        spread = weighted(scale * np.sum(p ** 2, axis=1), scale * np.sum(b ** 2, axis=1))
        bias = fit - total + 2.0 * divergence - spread
        risk = (BIAS_WEIGHT * bias + spread) / total
        # the discrepancy principle as a guard: a change past the noise removes more than noise
        guarded = fit > total
        table.append({"width": width, "change": math.sqrt(fit), "risk": risk, "bias2": bias / total,
                      "variance": spread / total, "past_the_noise": guarded})
        if risk < best_risk and not guarded:
            best, best_risk, best_x = width, risk, (x.T if flipped else x)
    return np.array(best_x, dtype=np.float64), best, table


@dataclass(frozen=True)
class Regularisation:
    """What ``regularise_isf`` chose and why.

    width: the filter width (0 = T left as measured); change: ``||T_w - T||_F`` of
    the unit-column T; noise_norm: ``sigma sqrt(m (m - 1))``, the change noise
    explains; tried: (width, change) for every candidate; risks: the table of
    :func:`choose_width` when the width was chosen (None: given).
    """

    width: float
    change: float
    noise_norm: float
    tried: list
    risks: list | None = None
    per_pixel: bool = False

    def describe(self) -> str:
        if self.risks is not None:
            widths = "/".join(f"{row['width']:g}" for row in self.risks)
            if self.width == 0:
                return (f"T left as measured: no width of the edge-aware filter ({widths}) has an estimated "
                        f"risk below T's own noise within the discrepancy principle")
            risk = next(row["risk"] for row in self.risks if row["width"] == self.width)
            return (f"T filtered edge-aware{', per pixel of each cell' if self.per_pixel else ''}, width "
                    f"{self.width:g} (layout steps) of {widths}: the least estimated "
                    f"risk, {risk:.2f} of T's noise (SURE, bias counted {BIAS_WEIGHT:g}x); change "
                    f"{self.change:.3g} <= noise {self.noise_norm:.3g} (discrepancy principle)")
        if self.width == 0:
            if len(self.tried) > 1 and self.noise_norm > 0:
                return (f"T left as measured: the edge-aware filter (width {self.tried[1][0]:g}) changes it by "
                        f"more than the noise explains ({self.tried[1][1]:.3g} > {self.noise_norm:.3g})")
            return "T left as measured"
        return (f"T filtered edge-aware, width {self.width:g} (layout steps): change {self.change:.3g} <= noise "
                f"{self.noise_norm:.3g} (discrepancy principle)")


def regularise_isf(T: np.ndarray | IsfMatrix, layout: tuple[int, int] | None, noise: float,
                   width: float | None = WIDTH, pairs: np.ndarray | None = None,
                   variance: np.ndarray | None = None,
                   areas: np.ndarray | None = None) -> tuple[np.ndarray, Regularisation]:
    """Denoise T by the edge-aware filter at ``width``, kept when its change is no more
    than the noise explains (Morozov's discrepancy principle); ``width=None``: at the
    width of least estimated risk (:func:`choose_width`, with ``variance`` (m, m) the
    entries' own when known).

    Parameters
    ----------
    T : (m, m) measured ISF (any column scaling; filtered with unit columns), or its
        :class:`~ilt.transport.scan.IsfMatrix` (not scanned again).
    layout : (rows, cols) of the beam plan.
    noise : sigma of the noise per entry, relative to the unit-column T.
    areas : (m,) with ``pairs``, the pixels of each cell: the filter then acts on the light
        per pixel of each cell (each row of T over its cell's share of the mean area, its
        noise and variance alike), not on the cells' sums. A row of T is its cell's sum, so
        two neighbouring cells of 7 and 9 px differ by a quarter in every entry: averaged,
        each took part of the other's area (on the noisy M's 384-beam scan with cells of 7
        and 9 columns the bounces' error doubled, 0.030 -> 0.059; per pixel 0.028).

    Returns the filtered (or, refused, the measured) unit-column T (m, m) float64 and
    the :class:`Regularisation`.
    """
    isf = scan_isf(T)
    unit = isf.T / isf.norms
    m = unit.shape[0]
    if pairs is None and layout[0] * layout[1] != m:
        raise ValueError(f"layout {layout} does not hold m = {m} samples")
    share = None
    work, row_noise, noise_norm = unit, noise, noise * np.sqrt(m * (m - 1.0))
    if areas is not None and noise > 0:
        areas = np.asarray(areas, dtype=np.float64)
        if pairs is None or areas.shape != (m,) or not np.all(areas > 0):
            raise ValueError(f"areas: the {m} cells' pixel counts (all > 0), with their pairs")
        share = areas / areas.mean()
        work = unit / share[:, None]
        row_noise = noise / share
        variance = (np.repeat(np.square(row_noise)[:, None], m, axis=1) if variance is None else
                    np.asarray(variance, dtype=np.float64) / np.square(share)[:, None])
        noise_norm = float(np.sqrt(max(variance.sum() - np.trace(variance), 0.0)))

    def back(x):        # per pixel -> the cells' sums
        return x if share is None else x * share[:, None]

    per_pixel = share is not None
    if width is None:
        if not noise > 0:
            return unit, Regularisation(width=0.0, change=0.0, noise_norm=float(noise_norm), tried=[(0.0, 0.0)])
        filtered, chosen, table = choose_width(work, layout, row_noise, variance, pairs, confidence=share)
        tried = [(0.0, 0.0)] + [(row["width"], row["change"]) for row in table]
        change = next((row["change"] for row in table if row["width"] == chosen), 0.0)
        return (back(filtered) if chosen > 0 else unit,
                Regularisation(width=chosen, change=change, noise_norm=float(noise_norm), tried=tried, risks=table,
                               per_pixel=per_pixel))
    candidate = smooth_isf(work, layout, width, row_noise, pairs, share)
    change = float(np.linalg.norm(candidate - work))
    tried = [(0.0, 0.0), (width, change)]
    if width > 0 and noise > 0 and change <= noise_norm:
        return back(candidate), Regularisation(width=width, change=change, noise_norm=float(noise_norm), tried=tried,
                                               per_pixel=per_pixel)
    return unit, Regularisation(width=0.0, change=0.0, noise_norm=float(noise_norm), tried=tried)


def discrepancy_choice(changes: list[tuple[float, float]], noise_norm: float, width: float = WIDTH) -> float:
    """The width :func:`regularise_isf` picks from ``(width, change)`` pairs: ``width``
    when its change is no larger than the noise explains, else 0."""
    return width if any(w == width and change <= noise_norm for w, change in changes) else 0.0


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
    from ilt.transport.operators import bounce_images
    from ilt.transport.solvers import build_operator

    isf = scan_isf(T)
    unit = isf.T / isf.norms
    m = unit.shape[0]
    widths = sorted({0.0, WIDTH, *widths})
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
            filtered = smooth_isf(noisy, layout, w, sigma)
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


def diagonal_raise(T: np.ndarray, variance: np.ndarray | None) -> tuple[np.ndarray | None, dict | None]:
    """(m,) what to add to T's diagonal, its variance over itself, and a record; (None,
    None) when that is nothing (no variance, or every entry's relative variance under
    :data:`DIAGONAL_FLOOR`). ``variance`` (m, m): each unit-column entry's (build-isf's
    ``T_var.npy``); only its diagonal is read.

    A noisy diagonal biases the inverse: E[1 / (d + e)] = (1 + Var[e] / d^2) / d to second
    order, so each beam's solved light came out high by its diagonal's relative variance,
    the light it sends its neighbours with it, and bounce 1 low (a path tracer's noise of 16
    samples: each spot's cell 10.4% noisy, bounce 1 -1.1% and bounce 3 +3.1% at 768 beams);
    d + Var[e] / d is the second-order correction of T^-1 (T^-1 - T^-1 M T^-1, M_ik =
    (T^-1)_ki Var[T_ik], whose off-diagonal terms are products of small entries). Over 20
    draws of a 4-sample path tracer's noise it lowered the full-resolution errors in 95% of
    them (docs/fullres.md)."""
    if variance is None:
        return None, None
    d = np.asarray(np.diagonal(T), dtype=np.float64)
    var = np.maximum(np.asarray(np.diagonal(variance), dtype=np.float64), 0.0)
    positive = np.where(d > 0, d, np.inf)                # a diagonal entry of 0 or less: not raised
    raise_by, relative = var / positive, var / positive**2
    if not np.any(relative > DIAGONAL_FLOOR):
        return None, None
    return raise_by, {"median_relative_sigma": float(np.median(np.sqrt(relative))),
                      "max_relative_raise": float(relative.max()), "mean_relative_raise": float(relative.mean())}


def raise_diagonal(T: np.ndarray, raise_by: np.ndarray, out: np.ndarray | None = None,
                   block: int = 1024) -> np.ndarray:
    """``T + diag(raise_by)`` into ``out`` (float64, T's shape; T itself to raise it in
    place), copied a block of columns at a time (a memory-mapped ``out`` holds no m x m
    temporary); a new array when ``out`` is None."""
    if out is None:
        out = np.array(T, dtype=np.float64)
    elif out is not T:
        for j0 in range(0, T.shape[1], block):
            out[:, j0:j0 + block] = T[:, j0:j0 + block]
    out[np.diag_indices_from(out)] += raise_by
    return out
