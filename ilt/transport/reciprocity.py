"""Is T the ISF of a Lambertian scene?  A reciprocity test from T alone (no extra capture).

For a Lambertian scene the transport is ``A = P F`` (albedo P, form factors F) with
``area_i F_ij = area_j F_ji`` (reciprocity), so ``A = D K`` with D diagonal and K
symmetric, and ``(I - A)^-1 = D^1/2 (I - D^1/2 K D^1/2)^-1 D^-1/2``: a diagonal
similarity of a symmetric matrix. The ISF scales rows (the camera's gain per pixel)
and columns (each beam's power, the unit column norms) by diagonals too, so

    log T_ij - log T_ji = u_i - u_j          for one vector u (m,),

whatever the albedos, areas, gains and beam powers. Hidden points folded into the
visible ones (paper Sec. 3.1.2) keep it: a block of a symmetrisable inverse is
symmetrisable. A glossy surface breaks it: the light a point sends toward another
depends on where it came from, and the laser and the camera look from different
directions.

:func:`reciprocity_check` fits u by least squares over the pairs (i, j) whose two
entries both stand well above their noise (``T_var``, :mod:`ilt.isf.noise`) and
reports the fit's residual (rms, natural-log units) beside the residual that noise
alone would give (``noise_floor``, from each entry's variance: ``Var[log T] ~
Var[T] / T^2``). ``excess = sqrt(residual^2 - floor^2)`` is the asymmetry the noise
does not explain; past :data:`TOLERANCE` the verdict is "not lambertian". What else
breaks the identity on a matte scene: cells (T sums a cell of pixels, not one point,
so the identity holds to the cell's variation: neighbouring cells are left out,
:func:`near_pairs`), a spot's light spilling into the next cells (the same pairs), flare and interreflection inside the
lens, and light that reaches a point round an occluder only one way (it does not:
visibility is symmetric).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import scipy.sparse.linalg
import scipy.spatial

#: asymmetry (robust rms, log units) past the noise's that makes the verdict "not lambertian":
#: matte simulated scans measure 0.00-0.09 (cells), a glossy share of 0.2 0.17 (docs/theory.md)
TOLERANCE = 0.12
#: pairs of samples closer than this many median spot spacings are left out (:func:`near_pairs`)
NEAR_SPACINGS = 2.5
#: both entries of a pair at least this many sigmas above zero (when T's noise is known)
MIN_SNR = 10.0
#: ... and above this share of T's largest off-diagonal entry (always: noise-free T too)
MIN_RELATIVE = 1e-6
#: fewer residual degrees of freedom than this (pairs less the beams' free values) and the verdict is "undecided"
MIN_DOF = 8
#: ... and fewer than this cannot condemn a scene (a 10-beam scan's 23 pairs read 0.22 on a matte M)
MIN_DOF_REFUSE = 30
#: beams named as violating most
WORST_BEAMS = 10
#: pairs fitted at most: an even stride through them past that (m = 4096 has 8 million)
MAX_PAIRS = 400_000
#: Huber's constant (in robust sigmas) and the reweighting steps at most
HUBER_K = 1.345
HUBER_STEPS = 20
#: normal sigma per median absolute deviation
MAD_SIGMA = 1.4826

VERDICTS = ("lambertian", "not lambertian", "undecided")


@dataclass(frozen=True)
class Reciprocity:
    """The fit of ``log T_ij - log T_ji = u_i - u_j`` and its verdict.

    residual: rms of the fit's residuals (log units, degrees of freedom taken out);
    noise_floor: the rms noise alone gives (0 when T's noise is unknown);
    excess: sqrt(residual^2 - noise_floor^2), clipped at 0;
    pairs: pairs used; beams: beams in them;
    per_beam: (m,) rms residual of each beam's pairs (NaN: a beam in none);
    verdict: one of :data:`VERDICTS`; reason: one sentence with the figures.
    """

    residual: float
    noise_floor: float
    excess: float
    pairs: int
    beams: int
    per_beam: np.ndarray
    verdict: str
    reason: str
    tolerance: float = TOLERANCE

    def worst(self, count: int = WORST_BEAMS) -> list[dict]:
        """The ``count`` beams (rows of T) whose pairs violate most, worst first."""
        order = np.argsort(np.where(np.isnan(self.per_beam), -np.inf, self.per_beam))[::-1]
        return [{"beam": int(j), "rms": float(self.per_beam[j])} for j in order[:count] if np.isfinite(self.per_beam[j])]

    def as_dict(self) -> dict:
        return {"verdict": self.verdict, "reason": self.reason, "reciprocity_residual": self.residual,
                "noise_floor": self.noise_floor, "excess": self.excess, "tolerance": self.tolerance,
                "pairs": self.pairs, "beams": self.beams, "worst_beams": self.worst()}


def reciprocity_check(T: np.ndarray, T_var: np.ndarray | None = None, exclude=None,
                      tolerance: float = TOLERANCE, min_snr: float = MIN_SNR, block: int = 1024,
                      max_pairs: int = MAX_PAIRS) -> Reciprocity:
    """Test T (m, m) float64 (any column scaling) for the reciprocity of a Lambertian scene.

    Parameters:
        T_var: (m, m) variance of T's entries (same scaling), or None (noise unknown:
            no SNR test, floor 0).
        exclude: (m, m) sparse or bool array, pairs to leave out (either order), such
            as the spill matrix's entries (a spot's direct light in the next cell).
        block: rows of T handled at a time (T may be a memory map).
        max_pairs: pairs fitted at most (an even stride through them past that).
    Returns: :class:`Reciprocity`.
    """
    m = T.shape[0]
    excluded = np.zeros(0, dtype=np.int64)
    if exclude is not None:
        e = scipy.sparse.coo_matrix(exclude)
        lo_, hi_ = np.minimum(e.row, e.col), np.maximum(e.row, e.col)
        excluded = np.unique(lo_.astype(np.int64) * m + hi_)
    floor_abs = MIN_RELATIVE * _max_offdiagonal(T, block)
    i_all, j_all, y_all, var_all = [], [], [], []
    for lo in range(0, m, block):
        hi = min(m, lo + block)
        upper = np.asarray(T[lo:hi, lo:], dtype=np.float64)            # T_ij, i in [lo, hi), j >= lo
        lower = np.asarray(T[lo:, lo:hi], dtype=np.float64).T           # T_ji
        usable = (upper > floor_abs) & (lower > floor_abs)
        usable &= np.arange(lo, m)[None, :] > np.arange(lo, hi)[:, None]
        if T_var is not None:
            va = np.asarray(T_var[lo:hi, lo:], dtype=np.float64)
            vb = np.asarray(T_var[lo:, lo:hi], dtype=np.float64).T
            usable &= (upper > min_snr * np.sqrt(va)) & (lower > min_snr * np.sqrt(vb))
        i, j = np.nonzero(usable)
        a, b = upper[i, j], lower[i, j]
        if T_var is not None:
            var_all.append(va[i, j] / a**2 + vb[i, j] / b**2)
        i_all.append(i + lo)
        j_all.append(j + lo)
        y_all.append(np.log(a) - np.log(b))
    i, j, y = (np.concatenate(v) for v in (i_all, j_all, y_all))
    variance = np.concatenate(var_all) if var_all else np.zeros(len(y))
    if len(excluded):
        keep = ~np.isin(i.astype(np.int64) * m + j, excluded, assume_unique=False)
        i, j, y, variance = i[keep], j[keep], y[keep], variance[keep]
    if len(y) > max_pairs:
        pick = np.linspace(0, len(y) - 1, max_pairs).astype(np.int64)
        i, j, y, variance = i[pick], j[pick], y[pick], variance[pick]
    return _fit(m, i, j, y, variance, tolerance)


def near_pairs(samples: np.ndarray, spacings: float = NEAR_SPACINGS) -> scipy.sparse.coo_matrix:
    """(m, m) sparse: the pairs of samples (m, 2) pixels closer than ``spacings`` spot spacings (the 90th
    percentile of the nearest-neighbour distances).

    A cell sums a region of pixels, a beam lights a point: where the light varies
    across a cell the two entries of a pair differ by more than a diagonal scaling,
    most for neighbouring cells (next to a spot's own light, at a fold). On the noisy
    box (2e4 e-) the pairs within 2.5 spacings gave an asymmetry of 0.09-0.12 on matte
    scans; without them 0.00-0.09.
    """
    samples = np.asarray(samples, dtype=np.float64)
    if len(samples) < 2:
        return scipy.sparse.coo_matrix((len(samples), len(samples)))
    tree = scipy.spatial.cKDTree(samples)
    # the scan's coarse spacing: refined scans put pairs of beams at an edge's thirds, closer
    # than the rest, and a median of those read a 12-beam refined M at 0.19 (matte)
    spacing = float(np.percentile(tree.query(samples, 2)[0][:, 1], 90))
    return tree.sparse_distance_matrix(tree, spacings * spacing, output_type="coo_matrix")


def _max_offdiagonal(T, block: int) -> float:
    peak = 0.0
    for lo in range(0, T.shape[0], block):
        rows = np.abs(np.asarray(T[lo:lo + block], dtype=np.float64))
        idx = np.arange(rows.shape[0])
        rows[idx, idx + lo] = 0.0
        peak = max(peak, float(rows.max(initial=0.0)))
    return peak


def _solve(m: int, i: np.ndarray, j: np.ndarray, y: np.ndarray, w: np.ndarray, used: np.ndarray, u0: np.ndarray) -> np.ndarray:
    """Weighted least squares ``u_i - u_j = y``: the pairs' graph Laplacian ``L u = b`` by CG.

    L is singular by one constant per connected group; its right side sums to 0 in each
    group, so CG stays in its range. A dense pair graph's Laplacian is well conditioned
    (eigenvalues near the degrees), so a Jacobi-preconditioned CG takes tens of steps.
    """
    rows, cols = np.concatenate([i, j]), np.concatenate([j, i])
    L = scipy.sparse.coo_matrix((np.concatenate([-w, -w]), (rows, cols)), shape=(m, m)).tocsr()
    degree = np.bincount(i, weights=w, minlength=m) + np.bincount(j, weights=w, minlength=m)
    L = (L + scipy.sparse.diags(degree))[used][:, used]
    rhs = (np.bincount(i, weights=w * y, minlength=m) - np.bincount(j, weights=w * y, minlength=m))[used]
    jacobi = scipy.sparse.diags(1.0 / np.maximum(degree[used], 1e-300))
    u_used, _ = scipy.sparse.linalg.cg(L, rhs, x0=u0[used], M=jacobi, rtol=1e-10, maxiter=2000)
    u = np.zeros(m)
    u[used] = u_used
    return u


def _fit(m: int, i: np.ndarray, j: np.ndarray, y: np.ndarray, variance: np.ndarray, tolerance: float) -> Reciprocity:
    """Robust least squares ``u_i - u_j = y`` over the pairs (Huber weights, iterated).

    A beam whose cell is not a fair sample of its point (one pixel wide at an occluding
    edge, split by a fold) makes all its pairs asymmetric; plain least squares spreads
    that over every beam (the occluded M's noise-free cells read 0.43 against 0.004
    point-sampled), the Huber weights keep it to that beam. The residual reported is
    the residuals' robust rms (1.4826 x their median absolute value), the noise floor
    the same statistic of one draw of every pair's noise (its sigma from ``T_var``).
    """
    pairs = len(y)
    per_beam = np.full(m, np.nan)
    if pairs == 0:
        return Reciprocity(0.0, 0.0, 0.0, 0, 0, per_beam, "undecided",
                           "no pair of beams lights the other's sample above the noise", tolerance)
    used = np.unique(np.concatenate([i, j]))
    w = np.ones(pairs)
    u = np.zeros(m)
    scale = np.inf
    for _ in range(HUBER_STEPS):
        u = _solve(m, i, j, y, w, used, u)
        r = y - (u[i] - u[j])
        new_scale = max(MAD_SIGMA * float(np.median(np.abs(r))), 1e-12)
        w = np.minimum(1.0, HUBER_K * new_scale / np.maximum(np.abs(r), 1e-300))
        if abs(new_scale - scale) <= 1e-3 * new_scale:
            break
        scale = new_scale
    residual = MAD_SIGMA * float(np.median(np.abs(r)))
    # what noise alone leaves to the same robust rms: one draw of each pair's noise (seeded), less
    # what the fit's free values absorb (one per beam, less one per connected group of beams)
    graph = scipy.sparse.coo_matrix((np.ones(pairs), (i, j)), shape=(m, m))
    groups = scipy.sparse.csgraph.connected_components(graph, directed=False)[1]
    dof = max(pairs - (len(used) - len(np.unique(groups[used]))), 1)
    drawn = np.random.default_rng(0).standard_normal(pairs) * np.sqrt(variance)
    floor = MAD_SIGMA * float(np.median(np.abs(drawn))) * np.sqrt(dof / pairs)
    excess = float(np.sqrt(max(residual**2 - floor**2, 0.0)))
    counts = np.bincount(i, minlength=m) + np.bincount(j, minlength=m)
    sums = np.bincount(i, weights=r**2, minlength=m) + np.bincount(j, weights=r**2, minlength=m)
    with np.errstate(invalid="ignore", divide="ignore"):
        per_beam = np.where(counts > 0, np.sqrt(sums / np.maximum(counts, 1)), np.nan)
    figures = (f"reciprocity residual {residual:.3g} (log units) over {pairs} pairs of {len(used)} beams, "
               f"noise floor {floor:.3g}, excess {excess:.3g} against tolerance {tolerance:g}")
    if dof < MIN_DOF:
        verdict, why = "undecided", f"too few pairs above the noise: {figures}"
    elif excess > tolerance and dof < MIN_DOF_REFUSE:
        verdict, why = "undecided", f"too few pairs to call it not Lambertian: {figures}"
    elif excess > tolerance:
        verdict, why = "not lambertian", (f"T is not reciprocal, as a Lambertian scene's is: {figures}; "
                                          "glossy or specular surfaces, or flare")
    elif floor > tolerance:
        verdict, why = "undecided", f"the noise could hide a violation: {figures}"
    else:
        verdict, why = "lambertian", figures
    return Reciprocity(residual, floor, excess, pairs, len(used), per_beam, verdict, why, tolerance)
