"""The ``compressed`` back-end of ``C1 = T1 T^-1``: T in HODLR form, for m past dense.

Light exchanged between two groups of points far apart is smooth (form factors vary
slowly), so after ordering the points along a spatial tree every off-diagonal block
of the unit-column ``T_n`` is numerically low-rank: hierarchically off-diagonal
low-rank (HODLR). The tree halves the index range down to leaves of ``leaf`` points,
factorised densely (LU); each node above holds

    T_node = [[T_1, U_1 V_1^T], [U_2 V_2^T, T_2]] = D + W Z^T,

``D = blockdiag(T_1, T_2)`` (the children), ``W = blockdiag(U_1, U_2)``,
``Z^T = [[0, V_1^T], [V_2^T, 0]]``. Woodbury's identity gives solves and the diagonal
of the inverse without anything m x m:

    T^-1 = D^-1 - Y K^-1 Z^T D^-1,   Y = D^-1 W,   K = I + Z^T Y,
    diag(T^-1) = diag(D^-1) - rowsum(Y * (K^-1 X^T)^T),   X = D^-T Z,

so ``T1 = 1 / diag(T_n^-1)`` (paper Eq. 13) and ``C1 L = T1 T_n^-1 L`` come from the
compressed form (Ambikasaran & Darve, J. Sci. Comput. 2013).

Tolerance tied to the noise floor: a measured T carries noise of sigma per entry
(relative to its unit columns). In a p x q block that noise has singular values up to
about ``sigma (sqrt p + sqrt q)`` (the Marchenko-Pastur edge); the signal's singular
values below that edge are drowned in it, so dropping them loses nothing the data had.
Each off-diagonal block is compressed to that 2-norm, ``tol (sqrt p + sqrt q)``, with
``tol`` = sigma when the noise is known, else :data:`DEFAULT_TOL` times max |T_n|:
1e-8, below the float32 rounding (6e-8) of the frames a measured T is built from, and
bounce errors of 1e-7 to 2e-7 on the simulated box (m = 3072 to 16428).

The tree: a k-d tree on the samples' positions (camera pixels, or the plan's grid),
whose large nodes split along whichever axis gives the blocks between the halves the
lowest rank, estimated from sub-blocks (:func:`spatial_order`, :func:`_split_rank`):
two facets meeting along an edge exchange near-singular light there, and a split along
that edge is expensive.

Costs, rank r: compression about ``4 p q r`` flops per block (a sample and a
projection per direction, :func:`low_rank`), so ``~2 m^2 r`` for the top level and
less below; every entry of T is read into memory once, a block at a time, so T may be
a memory-mapped ``T.npy``; factorisation O(m r^2 log^2 m); storage O(m r log m)
(``memory`` in the figures, against ``8 m^2`` for one dense matrix); a solve of k
vectors O(k m r log m). The blocks are compressed on a thread per core, each with one
BLAS thread, or as tasks on a Dask cluster's workers that read T's file themselves
(``executor``, :func:`_compress_on`; docs/cluster.md), and the two halves of the tree
are factorised and solved side by side.

Accuracy is checked, not assumed: one solve is multiplied back by T itself, and a
residual far above what the tolerance allows is refused with the figure.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import threadpoolctl
from scipy.sparse.linalg import LinearOperator

from ilt.transport.operators import UnitColumnOperator, check_photo, one_norm_estimate, scale_rows
from ilt.transport.scan import IsfMatrix, TransportError, scan_isf

log = logging.getLogger(__name__)

#: tolerance per entry, relative to max |T_n|, when the noise floor is unknown
DEFAULT_TOL = 1e-8
#: points per leaf (factorised densely)
LEAF = 256
#: from this size the phases of a build are logged at INFO (seconds each), below at DEBUG
PROGRESS_M = 4096
#: nodes of more than this many leaves choose the split that gives the lowest ranks (:func:`spatial_order`)
SPLIT_MIN = 8
#: columns added to a block's basis per pass of the range finder
STEP = 32
#: a solve whose residual ``||T_n x - b|| / ||x||`` is this many times the allowance is refused
RESIDUAL_FACTOR = 10
#: rounding allowance of a solve, times ``||T_n||_F = sqrt(m)``: Woodbury solves are not
#: backward stable, measured 6e-12 to 3e-11 at tol 1e-14 on the simulated scenes
#: (m = 256-432), so tolerances below ~1e-12 buy nothing
_ROUNDING = 1e-12


def low_rank(block: np.ndarray, atol: float, rng: np.random.Generator, step: int = STEP, power: bool = False):
    """``block ~ U V^T`` with the singular values ``<= atol`` dropped; (p, r) and (q, r)
    float64.

    Adaptive randomised range finder (Halko, Martinsson & Tropp, SIAM Review 2011,
    Alg. 4.2) in passes of growing width: ``2 step`` random directions, then as many
    as the spectrum so far suggests (:func:`_next_width`, at most doubling the basis),
    each pass two wide products with the block (the sample
    ``B W`` and the new rows of ``Q^T B``); once a pass finds a direction that holds at
    most ``atol`` of the block (it reached the tail), the next is a probe of ``step``.
    The sample of each pass is first the a-posteriori probe of the basis so far: it
    stops when ``2 max_i ||R w_i||`` over its Gaussian probes w_i is at most ``atol``,
    ``R = (I - Q Q^T) B`` (the tail). That bounds ``||R||_2``: with R's top singular
    pair (s, v), ``||R w|| >= s |v^T w|`` and ``v^T w`` is standard normal, so all of
    k probes fall below s / 2 with probability ``P(|g| < 1/2)^k = 0.383^k``
    (4.6e-14 for k = 32). (Halko et al.'s Lemma 4.1 factor, ``10 sqrt(2/pi)``, bounds
    it for probability 10^-k; on the box's top block it cost two more passes.) The
    SVD of ``Q^T B`` drops what the basis holds past the tolerance.

    ``power`` (a tolerance at a noise floor): one power iteration per pass, on the
    block less its captured range, and a second stop: the directions a pass added
    carry at most ``atol`` of the block, ``||Y^T B||_2 <= atol``. A noisy block's
    tail is noise whose own singular values sit at the edge ``atol`` is set to, so
    the probe never passes; after a power iteration the new directions are the top of
    what is left, so once they carry no more than the floor, the rest lies below it.
    Costs two more products per pass; noisy blocks have low ranks.
    """
    p, q = block.shape
    limit = min(p, q)
    basis = np.zeros((p, 0))
    rows = []  # Q^T B, a pass at a time
    sample = block @ rng.standard_normal((q, min(2 * step, limit)))
    while True:
        sample -= basis @ (basis.T @ sample)
        if basis.shape[1] and 2 * np.linalg.norm(sample, axis=0).max() <= atol:
            break
        if power:
            # projecting before each normalisation keeps directions far below the
            # largest singular value (squared by the iteration) above rounding
            sample = block @ np.linalg.qr(block.T @ np.linalg.qr(sample)[0])[0]
            sample -= basis @ (basis.T @ sample)
        # block Gram-Schmidt, orthonormalised and projected once more: the new
        # directions stay orthogonal to the basis to rounding even when they are only
        # rounding noise themselves (those the final SVD drops)
        new = _orthonormal(sample)
        new -= basis @ (basis.T @ new)
        new = _orthonormal(new)
        basis = np.hstack([basis, new])
        rows.append(new.T @ block)
        # what the new directions hold of the block (from the Gram matrix: only the
        # width and the stop below use it, to a precision far coarser than rounding)
        caught = np.sqrt(np.maximum(np.linalg.eigvalsh(rows[-1] @ rows[-1].T)[::-1], 0))
        if (power and caught[0] <= atol) or basis.shape[1] >= limit:
            break
        width = _next_width(caught, atol, basis.shape[1], step)
        sample = block @ rng.standard_normal((q, min(width, limit - basis.shape[1])))
    # SVD of the wide Q^T B through the QR of its transpose (1.7x faster than gesdd
    # on 244 x 8214): Q^T B = R^T Q2^T, R^T = u s w^T, so V = Q2 w
    q2, r = np.linalg.qr(np.vstack(rows).T)
    u, s, wt = np.linalg.svd(r.T)
    kept = int(np.sum(s > atol))
    return (basis @ u[:, :kept]) * s[:kept], q2 @ wt[:kept].T


def _orthonormal(y: np.ndarray) -> np.ndarray:
    """Orthonormal columns spanning those of y (p, w), p >= w: Cholesky QR twice
    (Fukaya et al. 2014), BLAS-3 products and triangular solves: 10 ms against 40 ms
    for LAPACK's Householder QR on 8214 x 64 (one thread, medians of 7); Householder
    when y is too ill-conditioned for it (the Cholesky factor fails, or the result is
    not orthonormal to 1e-12)."""
    q = y
    try:
        for _ in range(2):
            r = scipy.linalg.cholesky(q.T @ q, check_finite=False)
            q = scipy.linalg.solve_triangular(r, q.T, trans="T", check_finite=False).T
    except np.linalg.LinAlgError:
        return np.linalg.qr(y)[0]
    if np.all(np.isfinite(q)) and np.abs(q.T @ q - np.eye(q.shape[1])).max() <= 1e-12:
        return q
    return np.linalg.qr(y)[0]


def _next_width(caught: np.ndarray, atol: float, found: int, step: int) -> int:
    """Columns of the range finder's next pass, from the singular values ``caught``
    (descending) of what the last pass's directions hold of the block: a probe of
    ``step`` once one of them is at most ``atol`` (the pass reached the tail), else
    twice the count of directions left above ``atol`` were the values to keep falling
    at the last pass's geometric rate (the decay slows further down a kernel's
    spectrum), plus ``step``, and at most ``found`` (doubling the basis). A guess that
    is short costs a pass, one that overshoots costs columns; the probe, not the
    guess, decides when to stop."""
    if caught[-1] <= atol:
        return step
    decay = (caught[-1] / caught[0]) ** (1 / max(caught.size - 1, 1))
    more = math.log(atol / caught[-1]) / math.log(decay) if decay < 1 else found
    return int(min(found, 2 * more + step))


@dataclass
class Node:
    """A HODLR node over tree positions ``lo:hi`` (a leaf when ``children`` is empty)."""

    lo: int
    hi: int
    children: list = field(default_factory=list)
    inverse: np.ndarray | None = None  # leaf: the dense block's inverse
    inv_diag: np.ndarray | None = None
    U: list = field(default_factory=list)  # [U1, U2]
    V: list = field(default_factory=list)  # [V1, V2]
    Y: np.ndarray | None = None  # D^-1 W
    X: np.ndarray | None = None  # D^-T Z
    K: tuple | None = None  # lu_factor of K = I + Z^T Y

    @property
    def size(self) -> int:
        return self.hi - self.lo

    @property
    def rank(self) -> int:
        return sum(u.shape[1] for u in self.U)

    def walk(self):
        """This node and its descendants."""
        yield self
        for c in self.children:
            yield from c.walk()

    def solve(self, b: np.ndarray, trans: bool = False, split: int = 0) -> np.ndarray:
        """``T_node^-1 b`` (or ``T_node^-T b``), b of shape (size, k); the two
        children's subtrees on two threads for the top ``split`` levels."""
        if not self.children:
            return (self.inverse.T if trans else self.inverse) @ b
        n1 = self.children[0].size
        y = np.concatenate(_both(lambda: self.children[0].solve(b[:n1], trans, split - 1),
                                 lambda: self.children[1].solve(b[n1:], trans, split - 1), split > 0))
        return self._correct(y, trans)

    def _correct(self, y: np.ndarray, trans: bool) -> np.ndarray:
        """``T_node^-1 b`` from ``y = D^-1 b`` (Woodbury), or the transposed."""
        if self.rank == 0:
            return y
        if not trans:
            return y - self.Y @ scipy.linalg.lu_solve(self.K, self._zt(y))
        return y - self.X @ scipy.linalg.lu_solve(self.K, self._wt(y), trans=1)

    def _zt(self, y: np.ndarray) -> np.ndarray:
        """``Z^T y``: [V1^T y_2; V2^T y_1]."""
        n1 = self.children[0].size
        return np.concatenate([self.V[0].T @ y[n1:], self.V[1].T @ y[:n1]])

    def _wt(self, y: np.ndarray) -> np.ndarray:
        """``W^T y``: [U1^T y_1; U2^T y_2]."""
        n1 = self.children[0].size
        return np.concatenate([self.U[0].T @ y[:n1], self.U[1].T @ y[n1:]])

    def _blocks(self, first: np.ndarray, second: np.ndarray, swap: bool) -> np.ndarray:
        """(size, r1 + r2): ``first`` (r1 columns) and ``second`` on the diagonal
        (``W``), or on the anti-diagonal (``Z``, ``swap``)."""
        n1 = self.children[0].size
        r1 = self.U[0].shape[1]
        out = np.zeros((self.size, self.rank))
        rows1, rows2 = (slice(n1, None), slice(None, n1)) if swap else (slice(None, n1), slice(n1, None))
        out[rows1, :r1], out[rows2, r1:] = first, second
        return out

    def factorise(self, up: np.ndarray | None = None, vp: np.ndarray | None = None, split: int = 0):
        """Bottom-up: Y, X, K and the diagonal of the inverse. Returns
        ``(T_node^-1 up, T_node^-T vp)`` for the columns ``up`` and ``vp`` (size, k)
        of the ancestors' W and Z on this node's rows.

        Each node solves its own W (Z) columns and all its ancestors' in one pass
        down its subtree, so a leaf multiplies its inverse by one matrix of every
        ancestor's columns instead of once per ancestor. The two children's subtrees
        run on two threads for the top ``split`` levels."""
        up = np.zeros((self.size, 0)) if up is None else up
        vp = np.zeros((self.size, 0)) if vp is None else vp
        if not self.children:
            return self.inverse @ up, self.inverse.T @ vp
        n1 = self.children[0].size
        (u1, u2), (v1, v2) = self.U, self.V
        r1, r2 = u1.shape[1], u2.shape[1]
        # Z's first r1 columns hold V1 on the second child's rows, the rest V2 on the first's
        (a0u, a0v), (a1u, a1v) = _both(
            lambda: self.children[0].factorise(np.hstack([u1, up[:n1]]), np.hstack([v2, vp[:n1]]), split - 1),
            lambda: self.children[1].factorise(np.hstack([u2, up[n1:]]), np.hstack([v1, vp[n1:]]), split - 1),
            split > 0)
        inv_diag = np.concatenate([c.inv_diag for c in self.children])
        du, dv = np.vstack([a0u[:, r1:], a1u[:, r2:]]), np.vstack([a0v[:, r2:], a1v[:, r1:]])
        if self.rank == 0:
            self.inv_diag = inv_diag
            return du, dv
        self.Y = self._blocks(a0u[:, :r1], a1u[:, :r2], swap=False)
        self.X = self._blocks(a1v[:, :r1], a0v[:, :r2], swap=True)
        k = np.eye(self.rank) + self._zt(self.Y)
        self.K = scipy.linalg.lu_factor(k)
        if not np.all(np.isfinite(self.K[0])) or np.min(np.abs(np.diag(self.K[0]))) == 0:
            raise TransportError(f"compressed: the Woodbury matrix of points {self.lo}:{self.hi} (tree order) "
                                 "is singular; use --solver dense")
        xk = scipy.linalg.lu_solve(self.K, self.X.T).T
        self.inv_diag = inv_diag - np.sum(self.Y * xk, axis=1)
        return self._correct(du, False), self._correct(dv, True)

    def memory(self) -> int:
        """Bytes held by this node and its descendants."""
        own = sum(a.nbytes for a in (*self.U, *self.V, self.Y, self.X, self.inverse) if a is not None)
        own += self.K[0].nbytes if self.K is not None else 0
        return own + sum(c.memory() for c in self.children)

    def ranks_by_level(self, level: int = 0, out: dict | None = None) -> dict[int, list[int]]:
        """Off-diagonal ranks ``[r1, r2]`` of every node, by depth (0: the root)."""
        out = {} if out is None else out
        if self.children:
            out.setdefault(level, []).extend(u.shape[1] for u in self.U)
            for c in self.children:
                c.ranks_by_level(level + 1, out)
        return out


def _tree(lo: int, hi: int, leaf: int) -> Node:
    """The HODLR tree over positions ``lo:hi``: halves down to at most ``leaf`` points."""
    node = Node(lo, hi)
    if hi - lo > leaf:
        mid = (lo + hi) // 2
        node.children = [_tree(lo, mid, leaf), _tree(mid, hi, leaf)]
        node.U, node.V = [None, None], [None, None]
    return node


def worker_threads() -> int:
    """Cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _split_levels(workers: int) -> int:
    """Tree levels whose two subtrees run on two threads each, for ``workers`` cores."""
    return math.ceil(math.log2(workers)) if workers > 1 else 0


@contextlib.contextmanager
def one_blas_thread():
    """Every BLAS call on one thread while the block runs (the work is spread over
    threads of our own instead): the build's calls are mostly QR, SVD and LU of a
    few hundred columns, and the whole build of the box at m = 3072 took 3.05 s on
    two OpenBLAS threads against 1.82 s on one (sigma 1e-4, last stop's code)."""
    with threadpoolctl.threadpool_limits(1, user_api="blas"):
        yield


def _in_parallel(calls: list, workers: int) -> list:
    """Results of the zero-argument ``calls``, run on ``workers`` threads (numpy drops
    the GIL in BLAS and LAPACK); the first exception raised is raised here."""
    if workers <= 1 or len(calls) <= 1:
        return [call() for call in calls]
    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(lambda call: call(), calls))


def _both(first, second, parallel: bool) -> tuple:
    """``(first(), second())``, the two on two threads when ``parallel``."""
    if not parallel:
        return first(), second()
    with ThreadPoolExecutor(1) as pool:
        other = pool.submit(first)
        mine = second()
        return other.result(), mine


def spatial_order(points: np.ndarray, cost=None, min_size: int = 0) -> np.ndarray:
    """Indices ordering points (m, d) by recursive median bisection along the widest
    axis (a k-d tree), so every half of the index range, at every level, is a compact
    region. Stable: points already ordered along a line keep their order.

    ``cost(a, b)``, for index sets of more than ``min_size`` points: what splitting
    them into halves a and b costs (the ranks of the blocks between them). Every axis
    at least a quarter as wide as the widest is tried, and the cheapest split is kept.
    Two facets that meet along an edge exchange light that is near singular there, and
    a split along that edge gives the blocks between the halves a high rank; a split
    across the facets cuts lines within each facet, which exchange only multiply
    bounced light, smooth. On the box (m = 16428, ordered by pixel) the widest axis
    cut the upper half along the floor's edge: rank 364 at tol 1e-8, against 74 for
    the other axis."""
    points = np.asarray(points, dtype=np.float64)

    def split(idx: np.ndarray) -> np.ndarray:
        if idx.size <= 2:
            return idx
        p = points[idx]
        extent = p.max(axis=0) - p.min(axis=0)
        axes = [int(np.argmax(extent))]
        if cost is not None and idx.size > min_size:
            axes = [int(a) for a in np.argsort(-extent, kind="stable") if extent[a] >= extent.max() / 4]
        best = None
        for axis in axes:
            candidate = idx[np.argsort(p[:, axis], kind="stable")]
            half = candidate.size // 2
            figure = cost(candidate[:half], candidate[half:]) if len(axes) > 1 else 0.0
            if best is None or figure < best[0]:
                best = (figure, candidate)
        idx, half = best[1], idx.size // 2
        return np.concatenate([split(idx[:half]), split(idx[half:])])

    return split(np.arange(points.shape[0]))


def grid_points(layout: tuple[int, int] | None, m: int, beams: np.ndarray | None = None) -> np.ndarray | None:
    """(m, 2) (row, col) of each sample on the plan's grid ``layout`` (scanline
    positions ``beams``, default 0..m-1), or None when the layout does not place m
    points."""
    if layout is None:
        return None
    rows, cols = (int(n) for n in layout)
    beams = np.arange(m) if beams is None else np.asarray(beams)
    if beams.shape != (m,) or rows * cols < m or beams.min() < 0 or beams.max() >= rows * cols:
        return None
    return np.stack([beams // cols, beams % cols], axis=1).astype(np.float64)


@dataclass(frozen=True)
class _Build:
    """What every block of one build shares: the tolerance per entry of T_n, the seed
    of the blocks' generators, and whether the range finder iterates (a noise floor)."""

    tol: float
    seed: int
    power: bool


def _gather(T, rows: np.ndarray, cols: np.ndarray, inv_norms: np.ndarray, buffer) -> np.ndarray:
    """``T_n[rows][:, cols]`` (float64) for sorted ``rows`` and ``cols``, read in index
    order into ``buffer(size)``: from a :class:`FileRows` by positioned reads, else a
    slice of the array or map where both are ranges (T in index order), else row by
    row."""
    b = buffer(rows.size * cols.size).reshape(rows.size, cols.size)
    if isinstance(T, FileRows):
        T.gather(rows, cols, b)
    elif rows[-1] - rows[0] + 1 == rows.size and cols[-1] - cols[0] + 1 == cols.size:
        b[...] = T[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
    else:
        for k, i in enumerate(rows):
            np.take(T[i], cols, out=b[k])
    b *= inv_norms[cols]
    return b


def _off_diagonal(T, order: np.ndarray, offset: int, node: tuple[int, int, int], side: int, inv_norms: np.ndarray,
                  build: _Build, buffer) -> tuple[np.ndarray, np.ndarray]:
    """``(U, V)`` of the off-diagonal block ``side`` (0: upper right) of the node over
    tree positions ``lo:hi``, children split at ``mid`` (``node = (lo, mid, hi)``),
    rows in tree order; ``order[i]``: the point at tree position ``offset + i`` (the
    whole order, or a subtree's part of it). The block is gathered in index order
    (0.13 s against 0.85 s in tree order for 6144 x 6144; U's and V's rows are put back
    after). Each block draws from its own generator, so the result does not depend on
    which thread or worker ran it."""
    lo, mid, hi = node
    halves = (order[lo - offset:mid - offset], order[mid - offset:hi - offset])
    rows, cols = halves[side], halves[1 - side]
    atol = build.tol * (math.sqrt(rows.size) + math.sqrt(cols.size))
    by_row, by_col = np.argsort(rows), np.argsort(cols)
    rng = np.random.default_rng([build.seed, lo, hi, side])
    u_sorted, v_sorted = low_rank(_gather(T, rows[by_row], cols[by_col], inv_norms, buffer), atol, rng,
                                  power=build.power)
    u, v = np.empty_like(u_sorted), np.empty_like(v_sorted)
    u[by_row], v[by_col] = u_sorted, v_sorted
    return u, v


def _leaf_inverse(T, idx: np.ndarray, where: tuple[int, int], inv_norms: np.ndarray,
                  buffer) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of the leaf's dense block ``T_n[idx][:, idx]`` (``idx``: its points in
    tree order, at tree positions ``where``) and its diagonal. TransportError when it is
    singular to working precision."""
    by_row = np.argsort(idx)
    dense = np.empty((idx.size, idx.size))
    dense[np.ix_(by_row, by_row)] = _gather(T, idx[by_row], idx[by_row], inv_norms, buffer)  # out of the buffer
    lu = scipy.linalg.lu_factor(dense, check_finite=False)
    pivots = np.abs(np.diag(lu[0]))
    if pivots.min() <= inv_norms.size * np.finfo(float).eps * pivots.max():
        raise TransportError(f"compressed: the block of points {where[0]}:{where[1]} (tree order) is singular "
                             "to working precision; use --solver dense")
    inverse = scipy.linalg.lu_solve(lu, np.eye(idx.size))
    return inverse, np.diag(inverse).copy()


def _split(node: Node) -> tuple[int, int, int]:
    """``(lo, mid, hi)`` of a node with children."""
    return node.lo, node.lo + node.children[0].size, node.hi


@dataclass(frozen=True)
class MappedFile:
    """Where a memory-mapped T lies in its file, for a worker to read it there; its size
    and modification time say whether the file a worker finds is the same one."""

    path: str
    offset: int
    shape: tuple[int, int]
    dtype: str
    size: int
    mtime_ns: int

    def open(self) -> FileRows:
        """T's file opened for reading (:class:`FileRows`, a context manager). OSError
        naming the file when it is not there, or differs in size or modification time
        from the one the build started from (another file at the same path on this
        machine, or T rewritten meanwhile)."""
        fd = os.open(self.path, os.O_RDONLY)
        try:
            st = os.fstat(fd)
            if (st.st_size, st.st_mtime_ns) != (self.size, self.mtime_ns):
                raise OSError(f"{self.path}: not the T.npy the build started from (size {st.st_size} bytes against "
                              f"{self.size}, or another modification time): it changed, or this machine sees "
                              "another file at that path")
        except BaseException:
            os.close(fd)
            raise
        return FileRows(self, fd)


class FileRows:
    """T read from its file (:class:`MappedFile`) a row segment at a time, by
    positioned reads: what a worker reads stays in the kernel's page cache, not in its
    own resident memory, which a Dask worker's memory limit counts (a map's pages would
    count, up to half of T for a root block). As fast as the map on the 2-core VM:
    1.02 against 1.12 GB/s into a buffer touched for the first time."""

    def __init__(self, source: MappedFile, fd: int):
        self.source, self.fd = source, fd
        self.dtype = np.dtype(source.dtype)
        self.shape = source.shape

    def __enter__(self) -> FileRows:
        return self

    def __exit__(self, *exc) -> None:
        os.close(self.fd)

    def gather(self, rows: np.ndarray, cols: np.ndarray, out: np.ndarray) -> None:
        """``out[k] = T[rows[k], cols]`` (sorted ``cols``): each row's span
        ``cols[0]..cols[-1]`` read once, straight into ``out`` when it is the block's
        row itself."""
        c0, span = int(cols[0]), int(cols[-1]) - int(cols[0]) + 1
        direct = span == cols.size and self.dtype == out.dtype
        scratch = None if direct else np.empty(span, dtype=self.dtype)
        picks = cols - c0
        row_bytes, item = self.shape[1] * self.dtype.itemsize, self.dtype.itemsize
        for k, i in enumerate(rows):
            target = out[k] if direct else scratch
            self._read(target, self.source.offset + int(i) * row_bytes + c0 * item)
            if not direct:
                out[k] = scratch[picks]

    def _read(self, target: np.ndarray, at: int) -> None:
        view = memoryview(target).cast("B")
        while view.nbytes:
            n = os.preadv(self.fd, [view], at)
            if n <= 0:
                raise OSError(f"{self.source.path}: ends at byte {at}, before the {self.shape} matrix its "
                              "header announces")
            view, at = view[n:], at + n


def mapped_file(T: np.ndarray) -> MappedFile | None:
    """The file T is a whole, C-ordered memory map of (a ``np.load(..., mmap_mode="r")``
    or a view of one), else None."""
    base = T
    while base is not None and not isinstance(base, np.memmap):
        base = getattr(base, "base", None)
    if base is None or getattr(base, "filename", None) is None or base.shape != T.shape or base.dtype != T.dtype:
        return None
    if not (T.flags.c_contiguous and T.ctypes.data == base.ctypes.data):
        return None
    st = os.stat(base.filename)
    return MappedFile(str(base.filename), int(base.offset), tuple(T.shape), T.dtype.str, st.st_size, st.st_mtime_ns)


def _block_task(source: MappedFile, order: np.ndarray, node: tuple[int, int, int], side: int,
                inv_norms: np.ndarray, build: _Build) -> tuple[np.ndarray, np.ndarray]:
    """On a worker: :func:`_off_diagonal` of one block (``order``: the node's points,
    from its first tree position on), T read from ``source``, in a buffer of its own
    (freed with the task: a worker keeps nothing between tasks)."""
    with source.open() as T, one_blas_thread():
        return _off_diagonal(T, order, node[0], node, side, inv_norms, build, np.empty)


def _subtree_task(source: MappedFile, order: np.ndarray, top: Node, inv_norms: np.ndarray, build: _Build) -> dict:
    """On a worker: every block and leaf of the subtree ``top`` (``order``: its points),
    largest first, in one buffer reused from block to block (memory touched for the
    first time is the slow part of a copy: 0.33 GB/s against 19 GB/s reused, on the
    2-core VM). Returns ``{(lo, hi, side): (U, V)}`` and ``{(lo, hi): (inverse,
    diagonal)}`` in one dict."""
    held: list[np.ndarray] = []

    def buffer(size: int) -> np.ndarray:
        if not held or held[0].size < size:
            held[:] = [np.empty(size)]
        return held[0][:size]

    out = {}
    with source.open() as T, one_blas_thread():
        for node in sorted(top.walk(), key=lambda n: -n.size):
            if node.children:
                for side in (0, 1):
                    out[node.lo, node.hi, side] = _off_diagonal(T, order, top.lo, _split(node), side, inv_norms,
                                                                build, buffer)
            else:
                idx = order[node.lo - top.lo:node.hi - top.lo]
                out[node.lo, node.hi] = _leaf_inverse(T, idx, (node.lo, node.hi), inv_norms, buffer)
    return out


def _cluster_workers(executor) -> int:
    """The workers (threads) behind ``executor``: a cluster's, else a pool's size."""
    count = getattr(executor, "worker_threads", None)
    if callable(count):
        return max(1, count())
    return max(1, getattr(executor, "_max_workers", 1))


def _compress_on(executor, source: MappedFile, root: Node, order: np.ndarray, inv_norms: np.ndarray,
                 build: _Build, level: int) -> None:
    """Every block and leaf of the tree, as tasks of ``executor`` reading T from
    ``source``, their results put in the tree's nodes.

    The blocks of the top ``cut`` levels are a task each (the root's two are half the
    work of the whole build), the subtrees below a task each, ``2^cut`` of them for at
    least as many workers: few tasks (4 for 2 workers, 22 for 8), each a block or a subtree
    whose blocks reuse one buffer. A task is sent T's file, the tree positions it
    covers and the column scales, a few MB; it returns its U and V (the compressed
    form's own arrays) or leaf inverses. The first error a task raises is raised here,
    the other tasks cancelled; a task the cluster lost (its workers kept dying) is a
    TransportError naming its points."""
    from concurrent.futures import FIRST_COMPLETED, BrokenExecutor, wait

    cut = max(1, math.ceil(math.log2(_cluster_workers(executor))))
    nodes = {(n.lo, n.hi): n for n in root.walk()}
    blocks, subtrees = [], []

    def split(node: Node, depth: int) -> None:
        if depth >= cut or not node.children:
            subtrees.append(node)
            return
        blocks.extend((node, side) for side in (0, 1))
        for c in node.children:
            split(c, depth + 1)

    split(root, 0)
    futures = {}
    for node, side in sorted(blocks, key=lambda b: -b[0].size):  # the largest first: workers finish together
        futures[executor.submit(_block_task, source, order[node.lo:node.hi].copy(), _split(node), side,
                                inv_norms, build)] = (node, side)
    for top in sorted(subtrees, key=lambda n: -n.size):
        futures[executor.submit(_subtree_task, source, order[top.lo:top.hi].copy(), top, inv_norms,
                                build)] = (top, None)
    pending, done_count = set(futures), 0
    try:
        while pending:
            finished, pending = wait(pending, return_when=FIRST_COMPLETED)
            for f in finished:
                node, side = futures[f]
                try:
                    result = f.result()
                except BrokenExecutor as exc:
                    raise TransportError(f"compressed: the cluster lost the task of points {node.lo}:{node.hi} "
                                         f"(tree order): {exc}") from None
                if side is not None:
                    node.U[side], node.V[side] = result
                else:
                    for key, value in result.items():
                        target = nodes[key[:2]]
                        if len(key) == 3:
                            target.U[key[2]], target.V[key[2]] = value
                        else:
                            target.inverse, target.inv_diag = value
                done_count += 1
                log.log(level, "compressed: %d of %d tasks done (points %d:%d)", done_count, len(futures),
                        node.lo, node.hi)
    finally:
        for f in pending:
            f.cancel()


@dataclass
class CompressedOperator(UnitColumnOperator):
    """``C1 = T1 T_n^-1`` with T_n in factorised HODLR form.

    Attributes
    ----------
    root : Node
        The tree over the points in tree order ``order``.
    order : (m,) int64
        Point at each tree position: the tree holds ``T_n[order][:, order]``.
    t1_unit, column_norms : (m,) float64
        As :class:`ilt.transport.operators.CancellationOperator`; ``t1_unit = 1 / diag(T_n^-1)``
        from the Woodbury recursion.
    rcond : float
        Reciprocal 1-norm condition estimate of T_n (Hager-Higham, from solves).
    tol : float
        Tolerance per entry of T_n; a p x q block is compressed to ``tol (sqrt p + sqrt q)``.
    """

    root: Node = field(repr=False)
    order: np.ndarray = field(repr=False)
    t1_unit: np.ndarray = field(repr=False)
    column_norms: np.ndarray = field(repr=False)
    rcond: float
    tol: float
    tol_source: str
    ordering: str
    seconds: float
    residual: float
    allowance: float
    leaf: int
    solver: str = "compressed"

    @property
    def memory(self) -> int:
        """Bytes of the compressed, factorised form (dense: ``8 m^2`` per matrix)."""
        return self.root.memory()

    @property
    def figures(self) -> dict:
        """What the compression kept and how far to trust it (JSON-ready)."""
        ranks = self.root.ranks_by_level()
        return {
            "tol": self.tol, "tol_source": self.tol_source, "ordering": self.ordering,
            "leaf": self.leaf,
            "ranks_by_level": [[min(r), max(r)] for _, r in sorted(ranks.items())],
            "memory_bytes": self.memory, "dense_bytes": 8 * self.m**2,
            "compression_seconds": self.seconds, "solve_residual": self.residual,
            "residual_allowance": self.allowance,
        }

    def describe(self) -> str:
        """One sentence with the figures, for the solver reason."""
        ranks = self.root.ranks_by_level()
        top = max(ranks[0]) if ranks else 0
        return (f"HODLR to tol {self.tol:.2g} per entry of T ({self.tol_source}), {self.ordering}; "
                f"top rank {top}, {self.memory / 2**20:.0f} MiB against {8 * self.m**2 / 2**20:.0f} MiB dense, "
                f"solve residual {self.residual:.2g} (allowed {self.allowance:.2g})")

    def solve(self, b: np.ndarray, trans: bool = False) -> np.ndarray:
        """``T_n^-1 b`` (or ``T_n^-T b``) for b of shape (m,) or (m, k), float64."""
        b = np.asarray(b, dtype=np.float64)
        x = np.empty_like(b)
        with one_blas_thread():
            x[self.order] = self.root.solve(b[self.order].reshape(self.m, -1), trans,
                                            _split_levels(worker_threads())).reshape(b.shape)
        return x

    def apply(self, values: np.ndarray) -> np.ndarray:
        """``C1 L`` for sample vectors ``L`` of shape (m,) or (m, k) (float64)."""
        check_photo(self.m, values)
        return scale_rows(self.t1_unit, self.solve(values))


def compressed_operator(T: np.ndarray | IsfMatrix, tol: float | None = None, points: np.ndarray | None = None,
                        leaf: int | None = None, seed: int = 0, split_min: int | None = SPLIT_MIN,
                        executor=None) -> CompressedOperator:
    """Build ``C1`` from T in HODLR form (see the module docstring).

    Parameters
    ----------
    T : (m, m) real array or memory map, or its :class:`~ilt.transport.scan.IsfMatrix`
        ISF matrix, any column scaling; read a block at a time. An IsfMatrix was
        checked and measured when made, and is not read for it again.
    tol : float > 0 or None
        Noise sigma per entry of the unit-column T (``--noise``); None:
        :data:`DEFAULT_TOL` times max |T_n|.
    points : (m, d) float or None
        Positions of the samples (plan grid or scene); the tree follows a k-d tree
        on them. None keeps the index order.
    leaf : int or None
        Points per leaf, factorised densely (None: :data:`LEAF`).
    split_min : int or None
        Nodes of more than ``split_min`` leaves choose, among the axes of ``points``,
        the split whose blocks have the lowest ranks (estimated from sub-blocks,
        :func:`_split_rank`); None: always the widest axis.
    executor : concurrent.futures.Executor or None
        A cluster's (:func:`ilt.parallel.cluster.executor_for`): the blocks are compressed and
        the leaves inverted there, as tasks that read T's file themselves (it must be on
        storage every worker sees at the same path; :func:`_compress_on`). The result
        is the same, bit for bit, as in this process (T in memory or mapped). None, or a T
        that is not a memory-mapped file: threads of this process.

    Raises
    ------
    TransportError
        Everything :func:`ilt.transport.scan.scan_isf` refuses; a tolerance that is not
        positive, or at or above the largest entry of T_n (nothing would be left of the
        light exchanged); a singular leaf or Woodbury matrix; a solve whose residual
        against T is more than :data:`RESIDUAL_FACTOR` times what the tolerance allows.
    """
    start = time.perf_counter()
    scan = scan_isf(T)
    T, norms, mapped = scan.T, scan.norms, scan.mapped
    m = T.shape[0]
    inv_norms = 1.0 / norms
    # max |T_n| and ||T_n||_1 (the largest column sum) from the scan's figures of T
    peak = float(np.max(scan.column_max * inv_norms))
    one_norm = float(np.max(scan.column_abs_sums * inv_norms))
    source, power = "the noise floor", tol is not None
    if tol is None:
        tol, source = DEFAULT_TOL * peak, f"{DEFAULT_TOL:.0e} of max |T|, noise unknown"
    if not (math.isfinite(tol) and tol > 0):
        raise TransportError(f"compressed: tolerance {tol!r} must be a positive number")
    if tol >= peak:
        raise TransportError(f"compressed: tolerance {tol:.3g} is at or above the largest entry of T "
                             f"({peak:.3g}, unit columns): nothing of the light exchanged would be kept; "
                             "give a smaller --noise")
    leaf = LEAF if leaf is None else leaf
    if leaf < 2:
        raise TransportError(f"compressed: leaf size {leaf} must be at least 2")
    if points is not None:
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[0] != m or not np.all(np.isfinite(points)):
            raise TransportError(f"compressed: sample positions of shape {points.shape} do not place m = {m} points")
        if split_min is None:
            order, ordering = spatial_order(points), "points ordered by a k-d tree on their positions"
        else:
            order = spatial_order(points, lambda a, b: _split_rank(T, inv_norms, tol, a, b), split_min * leaf)
            ordering = "points ordered by a k-d tree on their positions, split where the blocks' ranks are lowest"
    else:
        order, ordering = np.arange(m), "index order (no positions given)"

    build = _Build(tol=float(tol), seed=seed, power=power)
    buffers = threading.local()

    def buffer(size: int) -> np.ndarray:
        """This thread's buffer of at least ``size`` float64 (valid until its next
        block), allocated once, for the first (largest) block: memory the process
        touches for the first time came at 0.5 GB/s on the 2-core VM, reused memory at
        5 GB/s."""
        if getattr(buffers, "data", None) is None or buffers.data.size < size:
            buffers.data = np.empty(size)
        return buffers.data[:size]

    def compress(node: Node, side: int) -> None:
        node.U[side], node.V[side] = _off_diagonal(T, order, 0, _split(node), side, inv_norms, build, buffer)

    def invert(node: Node) -> None:
        node.inverse, node.inv_diag = _leaf_inverse(T, order[node.lo:node.hi], (node.lo, node.hi), inv_norms, buffer)

    root = _tree(0, m, leaf)
    workers = worker_threads()
    read = time.perf_counter()
    level = logging.INFO if m >= PROGRESS_M else logging.DEBUG
    source_file = mapped_file(T) if executor is not None else None
    if executor is not None and source_file is None:
        log.info("compressed: T is not a memory-mapped .npy file in C order (it was changed in memory, "
                    "e.g. by --regularise, or its file is in Fortran order): its blocks are compressed here, "
                    "not on the cluster")
    if source_file is not None:
        log.log(level, "compressed: T (m = %d) checked in %.1f s; compressing to tol %.2g on the cluster", m,
                read - start, tol)
        _compress_on(executor, source_file, root, order, inv_norms, build, level)
        with one_blas_thread():
            compressed = time.perf_counter()
            root.factorise(split=_split_levels(workers))
    else:
        log.log(level, "compressed: T (m = %d) checked in %.1f s; compressing to tol %.2g on %d threads", m,
                read - start, tol, workers)
        nodes = sorted(root.walk(), key=lambda n: -n.size)  # the largest blocks first: threads finish together
        jobs = [(lambda n=n, s=s: compress(n, s)) if n.children else (lambda n=n: invert(n))
                for n in nodes for s in ((0, 1) if n.children else (0,))]
        with one_blas_thread():
            if mapped and root.children:
                # the root's two blocks, a quarter of T each, one after the other: a
                # memory-mapped T is not held in memory, and neither are two quarters of
                # it: the process holds a quarter of T plus a sixteenth a thread. One
                # BLAS thread, as every other block and every cluster task: the sums run
                # in the same order, so the result is the same bit for bit however T
                # came (box m = 16428: 2.08 s a block, 1.56 s on two BLAS threads)
                for job in jobs[:2]:
                    job()
                jobs, buffers.data = jobs[2:], None
            _in_parallel(jobs, workers)
            compressed = time.perf_counter()
            root.factorise(split=_split_levels(workers))
    log.log(level, "compressed: blocks compressed in %.1f s (top rank %d), factorised in %.1f s",
            compressed - read, root.rank, time.perf_counter() - compressed)
    inv_diag = np.empty(m)
    inv_diag[order] = root.inv_diag
    bad = np.flatnonzero(~np.isfinite(inv_diag) | (inv_diag == 0))
    if bad.size:
        raise TransportError(f"compressed: (T^-1)[{bad[0]}, {bad[0]}] is zero or not finite: T1 is undefined "
                             f"for beam {bad[0]} at tol {tol:.2g}; use --solver dense")
    seconds = time.perf_counter() - start
    op = CompressedOperator(root=root, order=order, t1_unit=1.0 / inv_diag, column_norms=norms, rcond=0.0,
                            tol=float(tol), tol_source=source, ordering=ordering, seconds=seconds,
                            residual=0.0, allowance=0.0, leaf=leaf)
    op.residual, op.allowance = _check_residual(T, inv_norms, op, seed)
    if op.residual > RESIDUAL_FACTOR * op.allowance:
        raise TransportError(f"compressed: a solve's residual ||T x - b|| / ||x|| = {op.residual:.3g} is "
                             f"{op.residual / op.allowance:.0f} times what tol {tol:.2g} allows "
                             f"({op.allowance:.2g}); use --solver dense")
    checked = time.perf_counter()
    op.rcond = 1.0 / (one_norm * one_norm_estimate(_inverse(op)))
    log.log(level, "compressed: residual checked in %.1f s, condition estimated in %.1f s",
            checked - start - seconds, time.perf_counter() - checked)
    return op


def _split_rank(T, inv_norms: np.ndarray, tol: float, a: np.ndarray, b: np.ndarray, sample: int = 256) -> int:
    """The ranks, at the tolerance, of the two blocks between index sets a and b,
    estimated from their sub-blocks on about ``sample`` points of each (evenly spaced
    in the given order, so spread over each region): a kernel sampled at fewer points
    has singular values smaller by the square root of the entries' ratio, so the
    sub-block is measured against the tolerance scaled by it. On the box (m = 16428)
    it ranked three pairs of candidate splits as the full ranks do (estimates 156 /
    184, 90 / 170, 104 / 176 for full ranks 145 / 445, 74 / 364, 98 / 206)."""
    sa, sb = np.sort(a[::max(1, a.size // sample)]), np.sort(b[::max(1, b.size // sample)])
    atol = tol * (math.sqrt(a.size) + math.sqrt(b.size)) * math.sqrt(sa.size * sb.size / (a.size * b.size))
    rank = 0
    for rows, cols in ((sa, sb), (sb, sa)):
        sub = np.asarray(T[np.ix_(rows, cols)], dtype=np.float64) * inv_norms[cols]
        rank += int(np.sum(np.linalg.svd(sub, compute_uv=False) > atol))
    return rank


def _check_residual(T, inv_norms: np.ndarray, op: CompressedOperator, seed: int) -> tuple[float, float]:
    """``||T_n x - b|| / ||x||`` for one solve ``x = H^-1 b`` (b random), and what the
    tolerance allows: ``T_n - H`` holds the dropped tails, each ``<= atol`` of its
    block in the 2-norm, the blocks of a level disjoint, so ``||T_n - H||_2 <=``
    the sum over levels of their largest atol; plus rounding."""
    m = op.m
    b = np.random.default_rng(seed + 1).standard_normal(m)
    x = op.solve(b)
    r = unit_column_product(T, inv_norms, x) - b
    allowance, size = _ROUNDING * math.sqrt(m), m
    while size > op.leaf:
        half = size / 2
        allowance += op.tol * 2 * math.sqrt(half)
        size = math.ceil(half)
    return float(np.linalg.norm(r) / np.linalg.norm(x)), allowance


def unit_column_product(T, inv_norms: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``T_n x = T diag(inv_norms) x`` for x of shape (m,) or (m, k), a block of 512
    columns of T at a time: no m x m temporary, and T may be a memory map."""
    out = np.zeros((T.shape[0], *x.shape[1:]))
    for j0 in range(0, T.shape[1], 512):
        scaled = x[j0:j0 + 512] * inv_norms[j0:j0 + 512].reshape(-1, *([1] * (x.ndim - 1)))
        out += np.asarray(T[:, j0:j0 + 512], dtype=np.float64) @ scaled
    return out


def _inverse(op: CompressedOperator) -> LinearOperator:
    """``H^-1`` as a LinearOperator (solves both ways), for onenormest."""
    m = op.m
    return LinearOperator((m, m), matvec=op.solve, matmat=op.solve,
                          rmatvec=lambda b: op.solve(b, trans=True), rmatmat=lambda b: op.solve(b, trans=True),
                          dtype=np.float64)
