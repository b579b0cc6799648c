"""The ``series`` back-end of ``C1 = T1 T^-1``: products with a sparse T only.

Physics (paper Eq. 5 and 12): ``T = (I - A)^-1 T1`` with ``T1`` diagonal and
``A[i, i] = 0``, so ``T^-1 = T1^-1 (I - A)`` has the sparsity of A, and A's lies
inside T's (``T = T1 + A T1 + A^2 T1 + ...``, all terms non-negative: nothing
cancels). Where points exchange light only locally, T is sparse at its noise floor
and everything ``C1`` needs comes from products with it (after Bai et al. 2010, who
write inverse transport as a series of forward ones):

- solves ``T_n x = b`` (``T_n``: T with unit columns) by the Jacobi-scaled Neumann
  series ``x = sum_k B^k D^-1 b``, ``B = I - D^-1 S``, where S is ``T_n`` with the
  entries ``|T_n[i, j]| <= threshold`` dropped (scipy CSR) and ``D = diag(S)``;
- ``diag(T_n^-1)`` for ``T1`` by probing (Tang & Saad 2012, "A probing method for
  computing the diagonal of a matrix inverse"): colour the graph of S so that no two
  points of one colour are coupled, solve once per colour (one batched solve) with the
  colour's indicator vector, and read ``(T_n^-1)[i, i]`` at each point of the colour:
  exact when ``T_n^-1``'s pattern lies inside S's, i.e. S keeps all of T's non-zeros;
  with a threshold the error is of the order of the dropped entries.

Cost: ``(colours + k) x iterations x nnz(S)`` multiply-adds for the build and k
solves, memory ``nnz(S)``; no factorisation and no dense inverse.

Limits, checked before solving (refused with the figure): T must be sparse at the
floor (few colours), and the series converges only when ``rho(B) < 1``; after the
probing, :func:`_probe_error` estimates how far T1 can be off. For ``T = (I - A)^-1 T1``, B is similar to
``I - diag(G)^-1 G`` with ``G = (I - A)^-1``, and ``G - I`` has eigenvalues
``lambda / (1 - lambda)`` for A's ``lambda``: the series needs roughly
``Re lambda < 1/2`` (``diag(G) > 1`` helps a little), where the bounce series of A
itself needs ``|lambda| < 1``. The chain scene of tests/transport/test_series.py gives
``rho(B)`` = 0.11, 0.39, 0.82 for ``rho(A)`` = 0.1, 0.3, 0.5.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.sparse.linalg import (
    ArpackError,
    ArpackNoConvergence,
    LinearOperator,
    eigs,
)

from ilt.transport.operators import UnitColumnOperator, check_photo, one_norm_estimate, scale_rows
from ilt.transport.scan import IsfMatrix, TransportError, scan_isf

log = logging.getLogger(__name__)

#: relative residual ``||S x - b|| / ||b||`` (per column) at which a solve stops
SERIES_TOL = 1e-12
#: spectral radius past which the series is slow enough to warn about
RHO_WARN = 0.99
#: probing with more colours than m / this (and 2) is refused: T is dense at the floor
MAX_COLOUR_SHARE = 4
#: a probing error (:func:`_probe_error`) this many times the floor (or tol) is warned about
PROBE_WARN = 10
#: below this size spectral radii are computed from the dense iteration matrix
_DENSE_RADIUS_M = 16


def sparse_unit_columns(T: np.ndarray | IsfMatrix, threshold: float = 0.0) -> tuple[sparse.csr_matrix, np.ndarray]:
    """S: the unit-column T with entries ``|T_n[i, j]| <= threshold`` dropped, CSR float64,
    and the column 2-norms of T (m,). Built 512 rows at a time: no m x m temporary.
    T: an array, or its :class:`~ilt.transport.scan.IsfMatrix` (not scanned again)."""
    isf = scan_isf(T)
    T, norms = isf.T, isf.norms
    inv_norms = 1.0 / norms
    rows = []
    for i0 in range(0, T.shape[0], 512):
        block = T[i0:i0 + 512] * inv_norms
        block[np.abs(block) <= threshold] = 0.0
        rows.append(sparse.csr_matrix(block))
    return sparse.vstack(rows, format="csr"), norms


def count_nonzeros(T: np.ndarray | IsfMatrix, threshold: float = 0.0) -> int:
    """nnz of :func:`sparse_unit_columns` without building it (one pass over T; two
    when T is an array, not its IsfMatrix)."""
    isf = scan_isf(T)
    T, norms = isf.T, isf.norms
    floor = threshold * norms
    return sum(int(np.count_nonzero(np.abs(T[i0:i0 + 512]) > floor)) for i0 in range(0, T.shape[0], 512))


def greedy_colouring(S: sparse.spmatrix) -> np.ndarray:
    """Distance-1 colouring of the symmetrised graph of S (i ~ j when ``S[i, j]`` or
    ``S[j, i]`` is non-zero), greedy in index order. Returns colours (m,) int64, 0-based.

    Index order is optimal for banded S (bandwidth + 1 colours) and needs at most
    (largest degree + 1) colours in general.
    """
    pattern = abs(S)
    pattern = (pattern + pattern.T).tocsr()
    indptr, indices = pattern.indptr, pattern.indices
    colours = np.full(S.shape[0], -1, dtype=np.int64)
    count = 0
    for i in range(S.shape[0]):
        taken = colours[indices[indptr[i]:indptr[i + 1]]]
        used = np.zeros(count + 1, dtype=bool)
        used[taken[taken >= 0]] = True
        colours[i] = int(np.argmin(used))  # the first free colour (used has a free slot)
        count = max(count, int(colours[i]) + 1)
    return colours


def jacobi_radius(S: sparse.csr_matrix, d_inv: np.ndarray, seed: int = 0) -> tuple[float, int]:
    """Spectral radius of ``B = I - D^-1 S`` from products with S (ARPACK, relative
    accuracy ~1e-3; power iteration if ARPACK fails). Returns (rho, products with S)."""
    m = S.shape[0]
    if m < _DENSE_RADIUS_M:
        B = np.eye(m) - d_inv[:, None] * S.toarray()
        return float(np.max(np.abs(np.linalg.eigvals(B)))), 0
    products = 0

    def matvec(x):
        nonlocal products
        products += 1
        x = np.ravel(x)
        return x - d_inv * (S @ x)

    v0 = np.random.default_rng(seed).uniform(0.5, 1.0, m)
    try:
        vals = eigs(LinearOperator((m, m), matvec=matvec, dtype=np.float64), k=1, which="LM", v0=v0, tol=1e-3,
                    maxiter=300, return_eigenvectors=False)
        return float(np.max(np.abs(vals))), products
    except (ArpackNoConvergence, ArpackError):
        return _power_radius(matvec, v0), products


def _power_radius(matvec, v: np.ndarray, steps: int = 300) -> float:
    """Growth rate of ``||B^k v||``, averaged over two steps: B of a bipartite coupling
    has eigenvalues +rho and -rho, and one-step ratios then alternate."""
    v = v / np.linalg.norm(v)
    rates = [0.0, 0.0]
    for _ in range(steps):
        w = matvec(v)
        rate = float(np.linalg.norm(w))
        if rate == 0:
            return 0.0
        rates = [rates[1], rate]
        v = w / rate
    return math.sqrt(rates[0] * rates[1])


def iterations_needed(rho: float, tol: float = SERIES_TOL) -> int | float:
    """Iterations for the series' error to fall by ``tol``: ``log(tol) / log(rho)``
    (``math.inf`` when rho >= 1)."""
    if rho <= 0:
        return 1
    return math.ceil(math.log(tol) / math.log(rho)) if rho < 1 else math.inf


def series_solve(S: sparse.csr_matrix, d_inv: np.ndarray, b: np.ndarray, tol: float = SERIES_TOL,
                 max_iterations: int = 1000) -> tuple[np.ndarray, int]:
    """``S^-1 b`` for b of shape (m,) or (m, k) by the Jacobi-scaled Neumann series.

    ``x0 = D^-1 b``, ``x(k+1) = D^-1 b + B x(k) = x(k) + D^-1 (b - S x(k))``: one
    product with S per iteration, which also gives the residual. Stops when every
    column has ``||b - S x|| <= tol ||b||``. Returns x (float64, b's shape) and the
    number of products with one vector. Raises TransportError naming the residual when
    ``max_iterations`` are not enough.
    """
    b = np.asarray(b, dtype=np.float64)
    columns = 1 if b.ndim == 1 else b.shape[1]
    scale = np.linalg.norm(b, axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    x = scale_rows(d_inv, b)
    worst = np.inf
    for iteration in range(1, max_iterations + 1):
        r = b - S @ x
        worst = float(np.max(np.linalg.norm(r, axis=0) / scale))
        if worst <= tol:
            return x, iteration * columns
        x += scale_rows(d_inv, r)
    raise TransportError(f"series: relative residual {worst:.2g} after {max_iterations} iterations is above "
                         f"tol = {tol:.0e}; use --solver dense")


@dataclass
class SeriesOperator(UnitColumnOperator):
    """``C1 = T1 S^-1`` with solves by the Jacobi-scaled Neumann series on a sparse S.

    Attributes
    ----------
    S : (m, m) scipy CSR float64
        The unit-column T with entries ``<= threshold`` dropped.
    d_inv : (m,) float64
        ``1 / diag(S)``.
    t1_unit, column_norms : (m,) float64
        As :class:`ilt.transport.operators.CancellationOperator`; ``t1_unit = 1 / diag(S^-1)`` by probing.
    rcond : float
        Reciprocal 1-norm condition estimate of S (Hager-Higham, from solves).
    jacobi_radius : float
        Spectral radius of ``I - D^-1 S`` (the series converges as its powers).
    colours : int
        Colours of the probing (the build costs that many solves).
    probe_error : float
        How far the probing solves break the pattern and signs of ``T^-1`` that
        physics implies, relative to its diagonal: an estimate of T1's relative error.
    matvecs : int
        Products of S with one vector so far, the build's included.
    """

    S: sparse.csr_matrix = field(repr=False)
    d_inv: np.ndarray = field(repr=False)
    t1_unit: np.ndarray = field(repr=False)
    column_norms: np.ndarray = field(repr=False)
    rcond: float
    jacobi_radius: float
    colours: int
    probe_error: float
    threshold: float
    tol: float
    max_iterations: int
    matvecs: int = 0
    solver: str = "series"

    @property
    def figures(self) -> dict:
        """What the series did and how far to trust it (JSON-ready)."""
        return {"noise_floor": self.threshold, "nonzeros": int(self.S.nnz), "colours": self.colours,
                "jacobi_radius": self.jacobi_radius, "probe_error": self.probe_error, "matvecs": self.matvecs}

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``S^-1 b`` for b of shape (m,) or (m, k) (the unit-column T, thresholded)."""
        x, products = series_solve(self.S, self.d_inv, b, self.tol, self.max_iterations)
        self.matvecs += products
        return x

    def apply(self, values: np.ndarray) -> np.ndarray:
        """``C1 L`` for sample vectors ``L`` of shape (m,) or (m, k) (float64)."""
        check_photo(self.m, values)
        return scale_rows(self.t1_unit, self.solve(values))


def series_operator(T: np.ndarray | IsfMatrix, threshold: float = 0.0, tol: float = SERIES_TOL,
                    max_iterations: int | None = None) -> SeriesOperator:
    """Build ``C1`` from products with the sparse unit-column T (see the module docstring).

    Parameters
    ----------
    T : (m, m) real array, or its :class:`~ilt.transport.scan.IsfMatrix`
        ISF matrix, any column scaling (an IsfMatrix is not checked again).
    threshold : float >= 0
        Noise floor relative to the unit columns: smaller entries are dropped.
    tol : float
        Relative residual at which every solve stops.
    max_iterations : int or None
        Per solve; None: three times what the spectral radius predicts, at least 100.

    Raises
    ------
    TransportError
        Everything :func:`ilt.transport.scan.scan_isf` refuses; a diagonal entry at or
        below the floor; T dense at the floor (colours > m / 4); a spectral radius of
        ``I - D^-1 S`` >= 1 (the series diverges); a solve that does not converge.
    """
    isf = scan_isf(T)
    m = isf.m
    nnz = count_nonzeros(isf, threshold)
    # Turan: a graph with E edges has a clique of m^2 / (m^2 - 2E) points, each needing
    # its own colour; refusing here spares building a dense S
    fewest = math.ceil(m * m / (m * m - nnz + m) - 1e-9)
    if fewest > _colour_limit(m):
        raise _dense(m, nnz, threshold, f"at least {fewest}")
    S, norms = sparse_unit_columns(isf, threshold)
    d = S.diagonal()
    bad = np.flatnonzero(d <= 0)
    if bad.size:
        raise TransportError(f"series: T[{bad[0]}, {bad[0]}] = {d[bad[0]]:.3g} (unit columns) is at or below the "
                             f"noise floor {threshold:.2g}: beam {bad[0]} must light its own sample pixel; "
                             "use --solver dense")
    colours = greedy_colouring(S)
    count = int(colours.max()) + 1
    if count > _colour_limit(m):
        raise _dense(m, nnz, threshold, str(count))
    d_inv = 1.0 / d
    rho, products = jacobi_radius(S, d_inv)
    if rho >= 1:
        raise TransportError(f"series diverges: spectral radius of I - D^-1 T is {rho:.3g} >= 1; use --solver dense")
    predicted = iterations_needed(rho, tol)
    if rho > RHO_WARN:
        log.info("series: spectral radius of I - D^-1 T is %.4f: about %d iterations per solve", rho, predicted)
    if max_iterations is None:
        max_iterations = max(100, 3 * predicted)
    probes = np.zeros((m, count))
    probes[np.arange(m), colours] = 1.0
    y, used = series_solve(S, d_inv, probes, tol, max_iterations)
    products += used
    inv_diag = y[np.arange(m), colours]
    bad = np.flatnonzero(~np.isfinite(inv_diag) | (inv_diag == 0))
    if bad.size:
        raise TransportError(f"(T^-1)[{bad[0]}, {bad[0]}] is zero: T1 is undefined for beam {bad[0]}")
    probe_error = _probe_error(S, colours, probes, y, inv_diag)
    if probe_error > PROBE_WARN * max(threshold, tol):
        log.warning("series: T1 from probing may be off by ~%.2g, %.0f times what the noise floor %.2g and tol "
                    "%.0e explain: T^-1 reaches outside T's pattern or is positive off its diagonal, which a "
                    "Lambertian ISF's is not; compare with --solver dense",
                    probe_error, probe_error / max(threshold, tol), threshold, tol)
    inverse_norm, used = _inverse_one_norm(S, d_inv, tol, max_iterations)
    products += used
    return SeriesOperator(
        S=S, d_inv=d_inv, t1_unit=1.0 / inv_diag, column_norms=norms,
        rcond=1.0 / (float(abs(S).sum(axis=0).max()) * inverse_norm), jacobi_radius=rho, colours=count,
        probe_error=probe_error,
        threshold=threshold, tol=tol, max_iterations=max_iterations, matvecs=products,
    )


def _probe_error(S: sparse.csr_matrix, colours: np.ndarray, probes: np.ndarray, y: np.ndarray,
                 inv_diag: np.ndarray) -> float:
    """How far the probing solves ``y = S^-1 probes`` are from what physics allows, per
    row relative to ``|diag(S^-1)|``: ``S^-1 = T1^-1 (I - A)`` is zero between points
    S does not couple and <= 0 off its diagonal, so ``y[i, c]`` (c not i's colour) must
    be 0 where i is coupled to no point of colour c, and <= 0 where it is.

    A leak outside the pattern also enters ``y[i, colour(i)]``; measured, the figure
    follows the true error of T1 within a factor 2 on sparsified and noisy ISFs. It
    cannot see what lands only on i's own colour (a pattern of 2 colours leaves no room).
    """
    m = S.shape[0]
    pattern = abs(S)
    coupled = ((pattern + pattern.T) @ probes) > 0
    violation = np.where(coupled, np.maximum(y, 0.0), np.abs(y)) / np.abs(inv_diag)[:, None]
    violation[np.arange(m), colours] = 0.0
    return float(violation.max())


def _colour_limit(m: int) -> float:
    return max(2.0, m / MAX_COLOUR_SHARE)


def _dense(m: int, nnz: int, threshold: float, colours: str) -> TransportError:
    return TransportError(f"series: T is dense at the noise floor {threshold:.2g} ({nnz / m:.0f} entries per "
                          f"column): probing T1 needs {colours} colours, more than m / {MAX_COLOUR_SHARE} = "
                          f"{_colour_limit(m):.0f}; use --solver dense or give --noise")


def _inverse_one_norm(S: sparse.csr_matrix, d_inv: np.ndarray, tol: float, max_iterations: int) -> tuple[float, int]:
    """``||S^-1||_1`` estimated from a few solves with S and S^T (Hager-Higham,
    :func:`ilt.transport.operators.one_norm_estimate`). ``I - D^-1 S^T`` is similar to ``(I - D^-1 S)^T``, so the
    series on S^T converges as fast. Returns (estimate, products with S)."""
    ST = S.T.tocsr()
    products = 0

    def solver(matrix):
        def solve(b):
            nonlocal products
            x, used = series_solve(matrix, d_inv, b, tol, max_iterations)
            products += used
            return x
        return solve

    m = S.shape[0]
    inverse = LinearOperator((m, m), matvec=solver(S), matmat=solver(S), rmatvec=solver(ST), rmatmat=solver(ST),
                             dtype=np.float64)
    return one_norm_estimate(inverse), products
