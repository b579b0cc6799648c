"""Interreflection cancellation operators and n-bounce decomposition.

Implements Seitz, Matsushita & Kutulakos, "A Theory of Inverse Light Transport"
(ICCV 2005):

- Lambertian cancellation theorem, Eq. (13): ``C1 = T1 T^-1`` with ``T1`` diagonal,
  ``T1[i, i] = 1 / (T^-1)[i, i]``.
- n-th bounce operator, Sec. 2.2: ``Cn = C1 (I - C1)^(n-1)``, ``Ln = Cn L``.

``C1`` is never formed. ``T``'s transpose is factorised once (``T^T = P L U``, LAPACK
getrf: a C-order copy of T is T^T in Fortran order, so no transposing copy) and the
factors are inverted in place (trtri), so one m x m array holds ``U^-1`` (upper
triangle) and ``L^-1`` (strict lower triangle, unit diagonal implied). Since
``T^-1 = P L^-T U^-T`` and ``diag(T^-1) = diag(T^-T)``, that gives ``diag(T^-1)`` in
O(m^2) extra work, and every later solve is two transposed triangular matrix products
(BLAS trmm) on a batch of columns. Cost: 4/3 m^3 flops once, against
2 m^3 for getrf + getri; memory: the factors plus one block of m x 256.

The bounces are computed by the recursion ``r0 = L; Ln = C1 r(n-1); rn = r(n-1) - Ln``,
never by matrix powers, so ``L = L1 + ... + LN + rN`` holds to rounding (closure).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import blas, lapack
from scipy.sparse.linalg import ArpackError, ArpackNoConvergence, LinearOperator, eigs

__all__ = [
    "TransportError",
    "CancellationOperator",
    "Decomposition",
    "cancellation_operator",
    "bounce_images",
    "operator_diagnostics",
    "decomposition_diagnostics",
]

#: block of rows used when reading diag(T^-1) out of the inverted factors
_DIAG_BLOCK = 256
#: condition estimate past which results are flagged as unreliable
CONDITION_WARN = 1e10


class TransportError(ValueError):
    """An ISF matrix or sample vector the operators cannot be built from or applied to."""


class UnitColumnOperator:
    """What every back-end of ``C1`` derives from ``t1_unit`` and ``column_norms``."""

    t1_unit: np.ndarray
    column_norms: np.ndarray

    @property
    def m(self) -> int:
        return self.t1_unit.shape[0]

    @property
    def t1(self) -> np.ndarray:
        """Diagonal of ``T1`` for the column scaling of the ``T`` given (C1 is the same)."""
        return self.t1_unit * self.column_norms


@dataclass(frozen=True)
class CancellationOperator(UnitColumnOperator):
    """``C1 = T1 T^-1`` (paper Eq. 13) in factored form.

    Attributes
    ----------
    factors : (m, m) float64, Fortran order
        ``U^-1`` in the upper triangle (with diagonal), ``L^-1`` in the strict lower
        triangle (unit diagonal implied), where ``P^T T_n^T = L U`` and ``T_n`` is ``T``
        with unit-norm columns: ``T_n^-1 = P L^-T U^-T``.
    perm : (m,) int64
        The row order of the factorisation: ``P^T b = b[perm]``, so the solve ends with
        ``x[perm] = L^-T U^-T b``.
    t1_unit : (m,) float64
        Diagonal of ``T1`` for ``T`` with unit-norm columns (as the paper builds it).
    column_norms : (m,) float64
        2-norms of the columns of the ``T`` given.
    rcond : float
        LAPACK's reciprocal 1-norm condition estimate of the column-normalised ``T``.
    """

    factors: np.ndarray = field(repr=False)
    perm: np.ndarray = field(repr=False)
    t1_unit: np.ndarray = field(repr=False)
    column_norms: np.ndarray = field(repr=False)
    rcond: float
    solver: str = "dense"

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``T_n^-1 b`` for ``b`` of shape (m,) or (m, k), in the factors' precision;
        returns float64 of the same shape."""
        vec = b.ndim == 1
        trmm = blas.get_blas_funcs("trmm", (self.factors,))
        rhs = np.array(b.reshape(self.m, -1), dtype=self.factors.dtype, order="F")
        y = trmm(1.0, self.factors, rhs, lower=0, trans_a=1, overwrite_b=1)           # U^-T b
        z = trmm(1.0, self.factors, y, lower=1, diag=1, trans_a=1, overwrite_b=1)     # L^-T U^-T b
        x = np.empty(z.shape)
        x[self.perm] = z
        return x[:, 0] if vec else x

    def apply(self, values: np.ndarray) -> np.ndarray:
        """``C1 L`` for sample vectors ``L`` of shape (m,) or (m, k) (float64)."""
        check_photo(self.m, values)
        # C1 = T1 T^-1 is invariant to column scaling, so use the unit-column factors.
        return scale_rows(self.t1_unit, self.solve(values))


def scale_rows(d: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``diag(d) x`` for x of shape (m,) or (m, k)."""
    return d[:, None] * x if x.ndim == 2 else d * x


def check_photo(m: int, values: np.ndarray) -> None:
    """Refuse sample vectors that do not fit an m-sample ISF or are not finite."""
    if values.ndim not in (1, 2) or values.shape[0] != m:
        raise TransportError(
            f"sample vector has shape {values.shape}; the ISF has m = {m} "
            f"samples, so expected ({m},) or ({m}, k)"
        )
    if not np.all(np.isfinite(values)):
        bad = np.argwhere(~np.isfinite(values))[0]
        raise TransportError(f"sample vector holds a non-finite value at index {tuple(int(i) for i in bad)}")


def _check_isf(T: np.ndarray) -> np.ndarray:
    """T as an array, refused (TransportError) unless square, non-empty and real; its
    entries are checked for finiteness by :func:`scan_isf`, in its one pass."""
    T = np.asarray(T)
    if T.ndim != 2 or T.shape[0] != T.shape[1]:
        raise TransportError(f"T must be a square m x m matrix, got shape {T.shape}")
    if T.shape[0] == 0:
        raise TransportError("T is empty")
    if not np.issubdtype(T.dtype, np.floating) and not np.issubdtype(T.dtype, np.integer):
        raise TransportError(f"T has dtype {T.dtype}; expected a real floating-point matrix")
    return T


#: bytes of T read per block of rows by :func:`scan_isf` (a block stays in cache
#: while every check and sum runs over it)
_SCAN_BYTES = 1 << 21


@dataclass(frozen=True)
class IsfScan:
    """What one pass over an ISF matrix gives (:func:`scan_isf`): its column 2-norms,
    for :func:`ilt.solvers.estimate_noise` the sums over its negative entries, and for
    ``compressed`` its columns' largest entries and 1-norms.

    norms : (m,) float64; negative_squares : (m,) float64, per column the sum of the
    squared negative entries (of T as given); negatives : how many entries are < 0;
    column_max, column_abs_sums : (m,) float64, per column of T as given the largest
    |entry| and the sum of |entries|.
    """

    norms: np.ndarray = field(repr=False)
    negative_squares: np.ndarray = field(repr=False)
    negatives: int
    column_max: np.ndarray = field(repr=False)
    column_abs_sums: np.ndarray = field(repr=False)

    def matches(self, T: np.ndarray) -> bool:
        return self.norms.shape[0] == T.shape[0]


def scan_isf(T: np.ndarray) -> tuple[np.ndarray, IsfScan]:
    """Check an ISF matrix and measure it in one pass over its rows (T can be a memory
    map: each block of rows is read once and every check and sum runs on it while it is
    in cache). Returns T (as an array) and its :class:`IsfScan`.

    Raises TransportError for a non-square or non-finite T (the first non-finite entry
    in row order, as a row-by-row check finds it), a zero column or two identical
    columns, naming the beam.
    """
    T = _check_isf(T)
    m = T.shape[0]
    keys_from = np.random.default_rng(0).standard_normal(m)  # the random projection of _duplicate_columns
    sq = np.zeros(m)
    neg_sq = np.zeros(m)
    keys = np.zeros(m)
    column_max, abs_sums = np.zeros(m), np.zeros(m)
    negatives = 0
    step = max(1, _SCAN_BYTES // (m * T.dtype.itemsize))
    for i0 in range(0, m, step):
        block = np.asarray(T[i0:i0 + step])
        block_sq = np.einsum("ij,ij->j", block, block, dtype=np.float64)
        if not np.isfinite(block_sq).all():  # a non-finite entry (or squares past 1e308): look
            finite = np.isfinite(block)
            if not finite.all():
                i, j = np.argwhere(~finite)[0]
                raise TransportError(f"T holds a non-finite value {T[i0 + i, j]} at pixel row {i0 + i}, "
                                     f"beam column {j}")
        sq += block_sq
        keys += np.einsum("i,ij->j", keys_from[i0:i0 + step], block)  # a gemv on few rows is slower
        neg = np.minimum(block, 0, dtype=np.float64)
        neg_sq += np.einsum("ij,ij->j", neg, neg)
        negatives += int(np.count_nonzero(neg))
        # for compressed's tolerance and condition estimate: 0.7-0.8 s more on a scan of
        # 3.4 s at m = 33075 (medians of 3), against the whole pass of its own it needed
        magnitude = np.abs(block, dtype=np.float64)
        np.maximum(column_max, magnitude.max(axis=0), out=column_max)
        abs_sums += magnitude.sum(axis=0)
    norms = np.sqrt(sq)
    zero = np.flatnonzero(norms == 0)
    if zero.size:
        raise TransportError(f"T column {zero[0]} (beam {zero[0]}) is all zero: that beam lit nothing")
    dup = _duplicate_columns(T, keys)
    if dup is not None:
        raise TransportError(
            f"T columns {dup[0]} and {dup[1]} are identical (two beams on the same point?): T is singular"
        )
    return T, IsfScan(norms=norms, negative_squares=neg_sq, negatives=negatives, column_max=column_max,
                      column_abs_sums=abs_sums)


def _duplicate_columns(T: np.ndarray, keys: np.ndarray | None = None) -> tuple[int, int] | None:
    """First pair of identical columns of ``T``, found by a random projection (``keys``,
    :func:`scan_isf` computes it in its pass) then confirmed."""
    if keys is None:
        keys = np.random.default_rng(0).standard_normal(T.shape[0]) @ T
    order = np.argsort(keys, kind="stable")
    same = np.flatnonzero(keys[order][1:] == keys[order][:-1])
    for s in same:
        a, b = sorted((int(order[s]), int(order[s + 1])))
        if np.array_equal(T[:, a], T[:, b]):
            return a, b
    return None


def one_norm_estimate(operator, columns: int = 4) -> float:
    """``||operator||_1`` by Higham & Tisseur's block 1-norm estimator (scipy's
    onenormest) with ``columns`` probes from a fixed seed, NumPy's global generator
    left as it was. onenormest draws its probes from that generator: with its default
    2 probes the estimate changed with whatever ran before (a test order made an
    inverse's norm 30 % short on the occluded scene); 4 probes found the exact norm
    for every one of 10 seeds there."""
    from scipy.sparse.linalg import onenormest

    state = np.random.get_state()
    try:
        np.random.seed(0)
        return float(onenormest(operator, t=columns))
    finally:
        np.random.set_state(state)


def prepare_isf(T: np.ndarray, scan: IsfScan | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Check an ISF matrix and return it with its column 2-norms (m,) float64.

    Raises TransportError for a non-square or non-finite T, a zero column or two
    identical columns, naming the beam. ``scan``: T's :func:`scan_isf` when the caller
    has it (T was checked then; no pass over T again).
    """
    if scan is not None and scan.matches(T):
        return np.asarray(T), scan.norms
    T, scan = scan_isf(T)
    return T, scan.norms


def cancellation_operator(T: np.ndarray, dtype=np.float64, scan: IsfScan | None = None) -> CancellationOperator:
    """Build ``C1 = T1 T^-1`` from an ISF matrix (paper Eq. 13).

    Parameters
    ----------
    T : (m, m) real array
        Impulse scatter matrix: column j is the image of beam j sampled at the m
        sample pixels. Any positive column scaling gives the same ``C1``.
    dtype : np.float64 (default) or np.float32
        Precision of the factorisation (float32 halves memory and time and gives
        ``T1`` to about 1e-7 times the condition number; see ilt.solvers "mixed").
    scan : T's :func:`scan_isf` when the caller has it (saves a pass over T).

    Raises
    ------
    TransportError
        Non-square, non-finite, a zero column, identical columns, or singular ``T``.
    """
    T, norms = prepare_isf(T, scan)
    # Equilibrate columns: C1 does not depend on them (paper Sec. 3) and LU is better
    # conditioned on unit columns. This is the only m x m copy we make: in T's own C
    # order (a straight copy; a Fortran-order one transposes in memory, 4 s at m = 12288),
    # which is T_n^T in Fortran order, what getrf factorises in place.
    work = np.array(T, dtype=dtype, order="C")
    work /= norms.astype(dtype)
    work = work.T
    getrf, gecon, trtri, lange = lapack.get_lapack_funcs(("getrf", "gecon", "trtri", "lange"), (work,))
    anorm = float(lange("I", work))  # max row sum of T_n^T = ||T_n||_1, without an m x m temporary
    factors, piv, info = getrf(work, overwrite_a=1)
    if info > 0:
        raise TransportError(f"T is exactly singular: zero pivot at pixel row {info - 1}")
    rcond, _ = gecon(factors, anorm, norm="I")  # ||.||_inf of T_n^T: the 1-norm estimate of T_n
    if rcond < T.shape[0] * np.finfo(dtype).eps:
        raise TransportError(
            f"T is singular to working precision (reciprocal condition estimate {rcond:.2e}): "
            "its columns are linearly dependent"
        )
    perm = _permutation_from_pivots(piv)
    factors, info_u = trtri(factors, lower=0, overwrite_c=1)
    factors, info_l = trtri(factors, lower=1, unitdiag=1, overwrite_c=1)
    if info_u or info_l:
        raise TransportError("T is singular: a triangular factor could not be inverted")
    inv_diag = _inverse_diagonal(factors, perm)
    bad = np.flatnonzero(~np.isfinite(inv_diag) | (inv_diag == 0))
    if bad.size:
        raise TransportError(f"(T^-1)[{bad[0]}, {bad[0]}] is zero: T1 is undefined for beam {bad[0]}")
    return CancellationOperator(
        factors=factors, perm=perm, t1_unit=1.0 / inv_diag, column_norms=norms, rcond=float(rcond),
        solver="dense" if factors.dtype == np.float64 else "float32",
    )


def _permutation_from_pivots(piv: np.ndarray) -> np.ndarray:
    """Turn LAPACK's sequential row interchanges into ``perm`` with ``P^T b = b[perm]``."""
    perm = np.arange(piv.shape[0])
    for i, p in enumerate(piv):
        if p != i:
            perm[i], perm[p] = perm[p], perm[i]
    return perm


def _inverse_diagonal(factors: np.ndarray, perm: np.ndarray) -> np.ndarray:
    """``diag(T^-1)`` from the inverted factors of ``A = T^T``: ``A^-1 = U^-1 L^-1 P^T``,
    whose diagonal is ``T^-1``'s (the transpose's inverse is the inverse's transpose).

    ``(T^-1)[i, i] = sum_k Uinv[i, k] Linv[k, q_i]`` with ``q = argsort(perm)``, done in
    row blocks so the extra memory is ``2 m x _DIAG_BLOCK``. The sums run along
    contiguous rows so numpy sums pairwise: a plain dot product loses a digit at
    m = 2048 (T1 error 9e-15 against 1e-15).
    """
    m = perm.shape[0]
    q = np.argsort(perm)
    cols = np.arange(m)[None, :]
    out = np.empty(m)
    for i0 in range(0, m, _DIAG_BLOCK):
        i1 = min(m, i0 + _DIAG_BLOCK)
        u = np.triu(factors[i0:i1, :], k=i0)  # rows i0..i1 of U^-1
        qi = q[i0:i1, None]
        # rows q_i of L^-1 transposed, i.e. columns of the unit lower triangular L^-1
        lower_t = np.ascontiguousarray(factors[:, q[i0:i1]].T)
        lower_t = np.where(cols > qi, lower_t, 0.0) + (cols == qi)
        out[i0:i1] = (u * lower_t).sum(axis=1, dtype=np.float64)
    return out


@dataclass(frozen=True)
class Decomposition:
    """Bounce images of one sample vector or a batch.

    Attributes
    ----------
    bounces : (N, m) or (N, m, k) float64
        ``L1 ... LN``; N is where the recursion stopped (``stopped_early`` says why).
    residual : (m,) or (m, k) float64
        ``rN = L - L1 - ... - LN``: light of more than N bounces, unexplained.
    relative_norms : (N,) or (N, k) float64
        ``||Ln|| / ||L||`` per bounce (and column).
    stopped_early : bool
        True when every column's ``||Ln|| / ||L||`` fell below ``tol`` before N.
    """

    bounces: np.ndarray
    residual: np.ndarray
    relative_norms: np.ndarray
    requested: int
    tol: float
    stopped_early: bool

    @property
    def count(self) -> int:
        return self.bounces.shape[0]

    @property
    def indirect(self) -> np.ndarray:
        """``L2 + ... + LN`` (the computed interreflections, without the residual)."""
        return self.bounces[1:].sum(axis=0) if self.count > 1 else np.zeros_like(self.residual)


def bounce_images(
    operator: CancellationOperator, photo: np.ndarray, n_bounces: int = 8, tol: float = 0.0
) -> Decomposition:
    """Split sample vectors into n-bounce vectors (paper Sec. 2.2).

    Recursion ``r0 = L; Ln = C1 r(n-1); rn = r(n-1) - Ln`` for n = 1..``n_bounces``,
    stopping after the first bounce where ``||Ln|| / ||L|| < tol`` for every column.

    Parameters
    ----------
    photo : (m,) or (m, k) float
        Linear samples of a photo (any illumination), or a batch of k photos as columns.
    n_bounces : int >= 1
    tol : float >= 0
        Stop early once the bounce energy is below this fraction of the photo's.
    """
    if n_bounces < 1:
        raise TransportError(f"n_bounces must be >= 1, got {n_bounces}")
    if not tol >= 0:
        raise TransportError(f"tol must be >= 0, got {tol}")
    photo = np.asarray(photo, dtype=np.float64)
    check_photo(operator.m, photo)
    total = np.linalg.norm(photo, axis=0)
    total = np.where(total > 0, total, 1.0)
    residual = photo.copy()
    bounces, norms = [], []
    stopped = False
    for n in range(n_bounces):
        ln = operator.apply(residual)
        residual -= ln
        bounces.append(ln)
        norms.append(np.linalg.norm(ln, axis=0) / total)
        if tol > 0 and n + 1 < n_bounces and np.all(norms[-1] < tol):
            stopped = True
            break
    return Decomposition(
        bounces=np.stack(bounces),
        residual=residual,
        relative_norms=np.stack(norms),
        requested=n_bounces,
        tol=tol,
        stopped_early=stopped,
    )


#: relative accuracy of ``spectral_radius_A`` (ARPACK's stopping test, below)
RHO_TOL = 1e-3
#: Krylov basis size of that estimate: the dominant eigenvalue of a scene's ``A`` (the
#: Perron root of a non-negative matrix) stands apart, so a small basis finds it in a
#: few applies of ``C1``; each apply reads all the factors (4.8 s at m = 12288 took
#: ARPACK's default basis of 20 and tolerance 1e-8)
RHO_NCV = 6
#: within this of 1 the estimate is refined to ``RHO_REFINED_TOL``, so ``rho >= 1``
#: (the warning) is decided as sharply as a tight estimate decides it
RHO_REFINE_BAND = 10 * RHO_TOL
RHO_REFINED_TOL = 1e-8


def spectral_radius(operator: CancellationOperator, seed: int = 0, tol: float = RHO_TOL) -> float:
    """Largest ``|eigenvalue|`` of ``A = I - C1`` from matrix-vector products (ARPACK).

    For a physical scene ``A = P K`` is non-negative with row sums < 1, so the value is
    < 1 and the bounce series converges; >= 1 means ``T`` is not a Lambertian ISF
    (noise, flare, a bad spot).

    Accuracy: ARPACK stops when the Ritz pair's residual is at most ``tol`` times the
    value, ``||A x - rho x|| <= tol rho ||x||``: ``rho`` is an eigenvalue of a matrix
    within ``tol rho`` of A (relative error ``tol`` where A's dominant eigenvector is
    well conditioned, as a Perron vector is). A value within ``RHO_REFINE_BAND`` of 1
    is recomputed to ``RHO_REFINED_TOL``.
    """
    m = operator.m
    if m <= 2:
        C1 = operator.apply(np.eye(m))
        return float(np.max(np.abs(np.linalg.eigvals(np.eye(m) - C1))))
    a = LinearOperator((m, m), matvec=lambda x: x - operator.apply(np.ravel(x)), dtype=np.float64)
    v0 = np.random.default_rng(seed).uniform(0.5, 1.0, m)
    # a loose tolerance with a small basis; ARPACK needs 2 < ncv <= m (k = 1)
    ncv = min(m, RHO_NCV if tol > RHO_REFINED_TOL else 20)
    try:
        vals = eigs(a, k=1, which="LM", v0=v0, tol=tol, ncv=ncv, maxiter=max(1000, 10 * m),
                    return_eigenvectors=False)
    except (ArpackNoConvergence, ArpackError):
        return _power_iteration(operator, v0)
    rho = float(np.max(np.abs(vals)))
    if tol > RHO_REFINED_TOL and abs(rho - 1) <= RHO_REFINE_BAND:
        return spectral_radius(operator, seed, tol=RHO_REFINED_TOL)
    return rho


def _power_iteration(operator: CancellationOperator, v: np.ndarray, steps: int = 500) -> float:
    rate = 0.0
    v = v / np.linalg.norm(v)
    for _ in range(steps):
        w = v - operator.apply(v)
        rate = float(np.linalg.norm(w))
        if rate == 0:
            return 0.0
        v = w / rate
    return rate


def operator_diagnostics(T: np.ndarray, operator: CancellationOperator) -> dict:
    """Figures that say whether ``C1`` can be trusted (DESIGN.md sec. 4).

    Returns a JSON-ready dict: ``m``, ``condition_estimate`` (1-norm, of the
    column-normalised T), ``min_diagonal`` (of the column-normalised T) and its beam,
    ``spectral_radius_A``, and ``warnings`` (sentences quoting the figures).
    """
    diag = np.diagonal(T) / operator.column_norms
    jmin = int(np.argmin(diag))
    rho = spectral_radius(operator)
    cond = 1.0 / operator.rcond
    warnings = []
    if cond > CONDITION_WARN:
        warnings.append(
            f"condition estimate of T is {cond:.3g} (> {CONDITION_WARN:.0e}): noise in T is amplified by up to that factor"
        )
    if diag[jmin] <= 0:
        warnings.append(
            f"T[{jmin}, {jmin}] = {diag[jmin]:.3g} <= 0: beam {jmin} does not light its own sample pixel"
        )
    if rho >= 1:
        warnings.append(
            f"spectral radius of A = I - C1 is {rho:.6g} >= 1: the bounce series diverges, "
            "T is not the ISF of a physical Lambertian scene (noise, flare or a wrong spot?)"
        )
    return {
        "m": operator.m,
        "condition_estimate": cond,
        "min_diagonal": float(diag[jmin]),
        "min_diagonal_beam": jmin,
        "spectral_radius_A": rho,
        "warnings": warnings,
    }


#: share of negative samples in a bounce past which a warning is raised
NEGATIVE_WARN = 0.01
#: a sample counts as negative below -NEGATIVE_FLOOR * max|L|: float32 rounding of
#: EXR data (~1e-7 relative, mildly amplified by C1) is not a physical fault
NEGATIVE_FLOOR = 1e-6
#: closure error past which a warning is raised
CLOSURE_WARN = 1e-10


def decomposition_diagnostics(photo: np.ndarray, decomposition: Decomposition) -> dict:
    """Closure error, bounce energies and negative shares of one decomposition.

    ``closure_error`` is ``||L - sum Ln - rN|| / ||L||`` (must be at rounding level);
    ``negative_share[n]`` the fraction of samples of bounce n+1 below
    ``-NEGATIVE_FLOOR * max|L|`` (physical bounce images are non-negative; noise in T
    makes some negative), ``most_negative[n]`` its smallest value over ``max|L|``.
    """
    photo = np.asarray(photo, dtype=np.float64)
    total = np.linalg.norm(photo)
    peak = float(np.abs(photo).max()) or 1.0
    rebuilt = decomposition.bounces.sum(axis=0) + decomposition.residual
    closure = float(np.linalg.norm(photo - rebuilt) / total) if total > 0 else 0.0
    axes = tuple(range(1, decomposition.bounces.ndim))
    negative = (decomposition.bounces < -NEGATIVE_FLOOR * peak).mean(axis=axes)
    most_negative = np.minimum(decomposition.bounces.min(axis=axes) / peak, 0.0)
    residual_share = float(np.linalg.norm(decomposition.residual) / total) if total > 0 else 0.0
    warnings = []
    if closure > CLOSURE_WARN:
        warnings.append(f"closure error {closure:.3g} > {CLOSURE_WARN:.0e}: the decomposition lost light")
    for n, share in enumerate(negative, start=1):
        if share > NEGATIVE_WARN:
            warnings.append(
                f"bounce {n}: {share:.1%} of samples are negative, down to {most_negative[n - 1]:.3g} of the "
                "photo's peak (noise in T or in the photo)"
            )
    if decomposition.stopped_early:
        stop = f"stopped after bounce {decomposition.count}: ||Ln||/||L|| < tol = {decomposition.tol:g}"
    else:
        stop = f"computed all {decomposition.count} requested bounces"
    return {
        "bounces": decomposition.count,
        "requested_bounces": decomposition.requested,
        "stopped_early": decomposition.stopped_early,
        "stop_reason": stop,
        "relative_norms": np.asarray(decomposition.relative_norms).tolist(),
        "residual_share": residual_share,
        "closure_error": closure,
        "negative_share": negative.tolist(),
        "most_negative": most_negative.tolist(),
        "warnings": warnings,
    }
