"""Solver back-ends for ``C1 = T1 T^-1``, behind the interface of
:class:`ilt.transport.operators.CancellationOperator` (``m``, ``t1``, ``t1_unit``,
``column_norms``, ``rcond``, ``solver``, ``apply``).

- ``dense``: one float64 LU, factors inverted in place (the reference);
- ``mixed``: float32 factorisation (half the memory, about half the time), solves
  refined in float64 against T; ``T1`` comes from the float32 factors, so its
  relative error is about 1e-7 times the condition number: right when the noise in
  T is far above that. Falls back to ``dense`` when refinement does not converge;
- ``blocks``: independent groups of points (connected components of
  ``|T| > threshold``, both ways) are factorised separately: cost sum b^3 not m^3;
- ``series``: products with T sparsified at the noise floor only (Jacobi-scaled
  Neumann series for solves, probing for ``T1``; :mod:`ilt.transport.series`): cost
  ``(colours + k) x iterations x nnz``, for locally coupled scenes. Refuses, naming
  the figure, when T is dense at the floor or the series diverges;
- ``compressed``: T in HODLR form (off-diagonal blocks low-rank to the noise floor)
  with Woodbury solves (:mod:`ilt.transport.compressed`): compression ``~4 m^2 r`` flops per
  level, storage and solves ``O(m r log m)``; T can be a memory map. Refuses, naming
  the residual, when a solve from the compressed form does not reproduce T.

``auto`` picks by structure, size and noise and says why (:func:`choose_solver`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import blas

from ilt.parallel.memory import available_memory
from ilt.transport.compressed import DEFAULT_TOL, compressed_operator
from ilt.transport.operators import (
    CancellationOperator,
    UnitColumnOperator,
    cancellation_operator,
    check_photo,
    scale_rows,
)
from ilt.transport.scan import IsfMatrix, TransportError, scan_isf
from ilt.transport.series import (
    count_nonzeros,
    greedy_colouring,
    iterations_needed,
    jacobi_radius,
    series_operator,
    sparse_unit_columns,
)

log = logging.getLogger(__name__)

SOLVERS = ("auto", "dense", "mixed", "blocks", "series", "compressed")
#: relative noise in T above which float32 factors lose nothing that matters
MIXED_NOISE = 1e-5
#: below this size the float64 LU is cheap enough to always use
MIXED_MIN_M = 2048
# auto picks ``series`` only where it clearly wins (:func:`_series_wins`):
#: from this size (below it a dense LU is cheap)
SERIES_MIN_M = 2048
#: T at the noise floor holding at most m^2 / SERIES_SPARSITY non-zeros
SERIES_SPARSITY = 20
#: probing needing at most this many colours
SERIES_MAX_COLOURS = 64
#: the weight of a sparse flop against a dense one: scipy's CSR products run
#: single-threaded at 2-2.5 GFlop/s, ``dense`` (build and solves) at 36-54 GFlop/s on
#: the idle 2-core machine of docs/accuracy.md (m = 2028-4107); more cores favour dense
SERIES_FLOP_PENALTY = 20
#: "clearly wins": the weighted flops must be at most 1 / SERIES_MARGIN of dense's
SERIES_MARGIN = 2
#: solved columns counted beside the build (16 photos x 8 bounces)
SERIES_USE_COLUMNS = 128
#: auto picks ``compressed`` from this size, where it was measured to win at every
#: noise level (docs/numerics.md, "compressed": on the box, 2.4x faster than dense at
#: m = 6075 noise-free, 2.8x at 1e-3; even at m = 3072)
COMPRESSED_MIN_M = 6000


@dataclass(frozen=True)
class MixedOperator:
    """float32 factors of the unit-column T, float64 iterative refinement of solves."""

    low: CancellationOperator = field(repr=False)
    T: np.ndarray = field(repr=False)
    row_sum_norm: float  # ||T_n||_inf, max row sum of the unit-column T
    max_iterations: int = 10
    solver: str = "mixed"

    @property
    def m(self) -> int:
        return self.low.m

    @property
    def t1_unit(self) -> np.ndarray:
        return self.low.t1_unit

    @property
    def column_norms(self) -> np.ndarray:
        return self.low.column_norms

    @property
    def t1(self) -> np.ndarray:
        return self.low.t1

    @property
    def rcond(self) -> float:
        return self.low.rcond

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``T_n^-1 b`` refined in float64 (LAPACK dsgesv's test): stop when
        ``||r||_inf <= sqrt(m) eps ||T_n||_inf ||x||_inf``.

        Each step costs one float64 product with T (the residual) and one float32
        solve. Raises TransportError when the residual fails to halve (T too
        ill-conditioned for float32 factors).

        Both run on scipy's BLAS (:func:`_product`): numpy's ``@`` would run the
        product on numpy's own OpenBLAS, whose threads then spin against those of
        scipy's between the alternating calls (8 bounces at m = 243 were 28x slower
        than with one BLAS thread; docs/numerics.md, "mixed")."""
        inv_norms = 1.0 / self.low.column_norms
        bound = np.sqrt(self.m) * np.finfo(np.float64).eps * self.row_sum_norm
        x = self.low.solve(b)
        previous = np.inf
        for _ in range(self.max_iterations):
            r = b - _product(self.T, scale_rows(inv_norms, x))
            size = float(np.abs(r).max())
            if size <= bound * float(np.abs(x).max()):
                return x
            if size > 0.5 * previous:
                break
            previous = size
            x = x + self.low.solve(r)
        raise TransportError("mixed precision: iterative refinement did not converge")

    def apply(self, values: np.ndarray) -> np.ndarray:
        check_photo(self.m, values)
        return scale_rows(self.t1_unit, self.solve(np.asarray(values, dtype=np.float64)))


def _product(T: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``T @ x`` (float64; x (m,) or (m, k)) with scipy's BLAS, the library of
    :meth:`CancellationOperator.solve`'s trmm: a C-order T is its transpose in Fortran
    order, so gemv / gemm with ``trans`` read it in place (no copy of T)."""
    a = T.T
    if not (a.flags.f_contiguous and a.dtype == np.float64):
        return T @ x
    if x.ndim == 1:
        return blas.dgemv(1.0, a, x, trans=1)
    return blas.dgemm(1.0, a, np.asfortranarray(x), trans_a=1)


@dataclass(frozen=True)
class BlockOperator(UnitColumnOperator):
    """``C1`` of a block-diagonal T (after permutation): one dense operator per block."""

    blocks: list[np.ndarray] = field(repr=False)
    operators: list[CancellationOperator] = field(repr=False)
    t1_unit: np.ndarray = field(repr=False)
    column_norms: np.ndarray = field(repr=False)
    rcond: float
    threshold: float
    solver: str = "blocks"

    def apply(self, values: np.ndarray) -> np.ndarray:
        check_photo(self.m, values)
        values = np.asarray(values, dtype=np.float64)
        out = np.empty_like(values)
        for idx, op in zip(self.blocks, self.operators):
            out[idx] = op.apply(values[idx])
        return out


def independent_groups(T: np.ndarray | IsfMatrix, threshold: float = 0.0,
                       stop_above: int | None = None) -> list[np.ndarray]:
    """Groups of points that exchange no light: connected components of the graph with
    an edge i-j when ``|T[i, j]| > threshold`` or ``|T[j, i]| > threshold`` (T with unit
    columns). Returns index arrays, largest first.

    Breadth-first search a frontier at a time: O(m^2) reads and no edge list, so a
    connected T costs one pass and memory m x (frontier size) in 512-wide chunks.
    ``stop_above``: stop as soon as a group holds more than this many points; that
    group is then returned as found so far (a part of its component, still the largest
    group) and the points not reached yet in no group at all (what :func:`choose_solver`
    needs: whether T splits into groups of at most m / 2; a dense T is decided after
    one step, not a pass over T per frontier). T: an array, or its
    :class:`~ilt.transport.scan.IsfMatrix` (not scanned again), as in every function here.
    """
    isf = scan_isf(T)
    T, norms = isf.T, isf.norms
    m = T.shape[0]
    unseen = np.ones(m, dtype=bool)
    groups = []
    while unseen.any():
        start = int(np.argmax(unseen))
        unseen[start] = False
        group, frontier = [start], np.array([start])
        while frontier.size:
            reached = np.zeros(m, dtype=bool)
            for k in range(0, frontier.size, 512):
                f = frontier[k:k + 512]
                reached |= np.any(np.abs(T[:, f]) > threshold * norms[f], axis=1)  # light from f
                reached |= np.any(np.abs(T[f, :]) > threshold * norms, axis=0)  # light into f
            frontier = np.flatnonzero(reached & unseen)
            unseen[frontier] = False
            group.extend(frontier.tolist())
            if stop_above is not None and len(group) > stop_above:
                groups.append(np.sort(np.array(group)))
                return sorted(groups, key=len, reverse=True)
        groups.append(np.sort(np.array(group)))
    return sorted(groups, key=len, reverse=True)


def block_operator(T: np.ndarray | IsfMatrix, threshold: float = 0.0) -> BlockOperator:
    """``C1`` factorised per independent group (entries ``<= threshold`` of the unit-
    column T between groups are treated as zero)."""
    isf = scan_isf(T)
    T, norms = isf.T, isf.norms
    groups = independent_groups(isf, threshold)
    t1_unit = np.empty(T.shape[0])
    operators = []
    for idx in groups:
        # a block is another matrix (its own column norms), scanned as it is copied;
        # one group of every point is T itself
        op = cancellation_operator(isf if idx.size == isf.m else T[np.ix_(idx, idx)])
        # the block's own column norms differ from the full T's by what was dropped
        t1_unit[idx] = op.t1_unit * op.column_norms / norms[idx]
        operators.append(op)
    return BlockOperator(
        blocks=groups, operators=operators, t1_unit=t1_unit, column_norms=norms,
        rcond=min(op.rcond for op in operators), threshold=threshold,
    )


def choose_solver(T: np.ndarray | IsfMatrix, noise: float | None) -> tuple[str, str]:
    """The back-end ``auto`` uses for T, and why (a sentence)."""
    isf = scan_isf(T)
    m = isf.m
    groups = independent_groups(isf, threshold=noise or 0.0, stop_above=m // 2)  # a larger group decides it
    largest = len(groups[0])
    if len(groups) > 1 and largest <= m // 2:
        return "blocks", (f"T splits into {len(groups)} independent groups (largest {largest} of {m} points): "
                          f"cost {sum(len(g) ** 3 for g in groups) / m**3:.2g} of one dense LU")
    if m >= SERIES_MIN_M:
        why = _series_wins(isf, noise or 0.0)
        if why:
            return "series", why
    dense_bytes = 2 * 8 * m * m  # T's float64 copy and its factors
    if dense_bytes > available_memory():
        return "compressed", (f"dense needs {dense_bytes / 2**20:.0f} MiB (two m x m float64 arrays, m = {m}), "
                              f"more than the {available_memory() / 2**20:.0f} MiB available")
    if m >= COMPRESSED_MIN_M:
        floor = (f"the noise floor {noise:.2g}" if noise is not None else
                 f"{DEFAULT_TOL:.0e} of max |T| (noise unknown; bounce errors ~1e-7, --solver dense for rounding's)")
        return "compressed", (f"m = {m} >= {COMPRESSED_MIN_M}: T's off-diagonal blocks are low-rank to {floor}, "
                              "so compressing beats a dense LU")
    if noise is not None and noise >= MIXED_NOISE and m >= MIXED_MIN_M:
        return "mixed", (f"noise {noise:.2g} in T is far above float32 rounding and m = {m} >= {MIXED_MIN_M}: "
                         "float32 factors halve time and memory")
    return "dense", f"m = {m}, one connected group, noise {'unknown' if noise is None else f'{noise:.2g}'}"


def _series_wins(isf: IsfMatrix, threshold: float) -> str | None:
    """Why ``series`` clearly beats ``dense`` on T (a sentence with the figures), or
    None: T must be sparse at the floor, need few colours, have a convergent series,
    and the build plus ``SERIES_USE_COLUMNS`` solves, ``2 nnz x iterations x (colours
    + columns)`` flops weighted by ``SERIES_FLOP_PENALTY``, must cost at most
    ``1 / SERIES_MARGIN`` of the dense build and solves, ``4/3 m^3 + 2 m^2 x columns``."""
    m = isf.m
    nnz = count_nonzeros(isf, threshold)
    if nnz > m * m / SERIES_SPARSITY:
        return None
    S, _ = sparse_unit_columns(isf, threshold)
    d = S.diagonal()
    colours = int(greedy_colouring(S).max()) + 1
    if colours > SERIES_MAX_COLOURS or np.any(d <= 0):
        return None
    rho, _ = jacobi_radius(S, 1.0 / d)
    if rho >= 1:
        return None
    iterations = iterations_needed(rho)
    share = (2 * nnz * iterations * (colours + SERIES_USE_COLUMNS)
             / (4 / 3 * m**3 + 2 * m**2 * SERIES_USE_COLUMNS))
    if SERIES_FLOP_PENALTY * SERIES_MARGIN * share > 1:
        return None
    return (f"T is sparse at the noise floor {threshold:.2g} ({nnz / m:.0f} entries per column), probing needs "
            f"{colours} colours and the series' spectral radius is {rho:.2f} (~{iterations} iterations): "
            f"the build and {SERIES_USE_COLUMNS} solves take {share:.2g} of the flops of dense (m = {m})")


def build_operator(T: np.ndarray | IsfMatrix, solver: str = "auto", noise: float | None = None,
                   reason: str | None = None, points: np.ndarray | None = None, executor=None):
    """``C1`` with the chosen back-end. Returns ``(operator, reason)``.

    ``noise``: the floor (relative to T's unit columns) below which ``blocks`` and
    ``series`` treat entries as zero, and the tolerance per entry of ``compressed``.
    ``reason``: why ``solver`` was chosen, when the caller ran :func:`choose_solver`
    itself (default: "asked for <solver>"). ``points``: (m, d) sample positions that
    ``compressed`` orders its tree by (None: index order). T: an array (checked and
    measured here, once) or its :class:`~ilt.transport.scan.IsfMatrix` (the back-ends
    take it and read no more of T than they must). ``executor``: where ``compressed``
    compresses its blocks (a cluster's; :func:`ilt.transport.compressed.compressed_operator`).
    """
    if solver not in SOLVERS:
        raise TransportError(f"unknown solver {solver!r}; choose one of {', '.join(SOLVERS)}")
    reason = reason or f"asked for {solver}"
    isf = scan_isf(T)
    if solver == "auto":
        solver, reason = choose_solver(isf, noise)
    if solver == "blocks":
        return block_operator(isf, threshold=noise or 0.0), reason
    if solver == "series":
        return series_operator(isf, threshold=noise or 0.0), reason
    if solver == "compressed":
        op = compressed_operator(isf, tol=noise or None, points=points, executor=executor)
        return op, f"{reason}; {op.describe()}"
    if solver == "mixed":
        T, norms = isf.T, isf.norms
        row_sums = np.zeros(T.shape[0])
        for j0 in range(0, T.shape[1], 512):  # column blocks: no m x m temporary
            row_sums += np.abs(T[:, j0:j0 + 512]) @ (1.0 / norms[j0:j0 + 512])
        try:
            op = MixedOperator(low=cancellation_operator(isf, dtype=np.float32),
                               T=np.asarray(T, dtype=np.float64),
                               row_sum_norm=float(row_sums.max()))
            op.solve(np.ones(T.shape[0]))
            return op, reason
        except TransportError as exc:
            log.info("mixed precision fails on T (%s); using dense", exc)
            reason += f"; float32 failed ({exc}), fell back to dense"
    return cancellation_operator(isf), reason


def estimate_noise(T: np.ndarray | IsfMatrix) -> float | None:
    """Noise floor of a measured T (unit columns), from its negative entries.

    True ISF entries are >= 0; where the true value is ~0 (points that exchange no
    light), noise makes half the samples negative, and those are half-normal with the
    noise's sigma: ``sigma = sqrt(mean(T[T < 0]^2))``. Returns None when fewer than
    16 entries are negative (the floor is not measurable from T; give it instead).

    The sums come from T's one pass (:func:`ilt.transport.scan.scan_isf`, per column,
    so the unit scaling is applied after it): none when T is an IsfMatrix already.
    """
    scan = scan_isf(T)
    if scan.negatives < 16:
        return None
    return float(np.sqrt(np.sum(scan.negative_squares / scan.norms**2) / scan.negatives))
