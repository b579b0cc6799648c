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
``tol`` = sigma when the noise is known, else :data:`DEFAULT_TOL` times max |T_n|
(near exact).

Costs, rank r: compression about ``9 p q r`` flops per block, ``~4 m^2 r`` per level,
``log2(m / leaf)`` levels (every entry of T is read a few times per level, a block at
a time, so T may be a memory-mapped ``T.npy``); factorisation O(m r^2 log^2 m);
storage O(m r log m) (``memory`` in the figures, against ``8 m^2`` for one dense
matrix); a solve of k vectors O(k m r log m).

Accuracy is checked, not assumed: one solve is multiplied back by T itself, and a
residual far above what the tolerance allows is refused with the figure.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from scipy.sparse.linalg import LinearOperator

from ilt.transport import (
    TransportError,
    UnitColumnOperator,
    check_photo,
    one_norm_estimate,
    prepare_isf,
    scale_rows,
)

log = logging.getLogger(__name__)

#: tolerance per entry, relative to max |T_n|, when the noise floor is unknown
DEFAULT_TOL = 1e-10
#: points per leaf (factorised densely)
LEAF = 256
#: columns added to a block's basis per pass of the range finder
STEP = 32
#: a solve whose residual ``||T_n x - b|| / ||x||`` is this many times the allowance is refused
RESIDUAL_FACTOR = 10
#: rounding allowance of a solve, times ``||T_n||_F = sqrt(m)``: Woodbury solves are not
#: backward stable, measured 6e-12 to 3e-11 at tol 1e-14 on the simulated scenes
#: (m = 256-432), so tolerances below ~1e-12 buy nothing
_ROUNDING = 1e-12


def low_rank(block: np.ndarray, atol: float, rng: np.random.Generator, step: int = STEP):
    """``block ~ U V^T`` with the singular values ``<= atol`` dropped; (p, r) and (q, r)
    float64.

    Adaptive randomised range finder (Halko, Martinsson & Tropp, SIAM Review 2011,
    Alg. 4.2, one power iteration per pass of ``step`` columns, on the block less its
    captured range). It stops when

    - the a-posteriori bound ``10 sqrt(2/pi) max_i ||(I - Q Q^T) B w_i||`` over the
      ``step`` Gaussian probes w_i that start the next pass is below ``atol`` (the
      tail is below the tolerance: exact T), or
    - the directions a pass added carry at most ``atol`` of the block,
      ``||Y^T B||_2 <= atol``: after a power iteration they are the top of what is
      left, so the rest lies below the tolerance. A noisy block's range finder
      reaches this once only noise is left, where the bound never passes (the
      noise's own singular values are below the edge ``atol`` is set to).
    """
    p, q = block.shape
    limit = min(p, q)
    basis, projected = np.zeros((p, 0)), np.zeros((0, q))  # Q and Q^T B
    bound = 10 * np.sqrt(2 / np.pi)
    residual = block @ rng.standard_normal((q, min(step, limit)))  # a sample of what the basis misses
    while basis.shape[1] < limit:
        # one power iteration on the part of the block the basis misses: projecting
        # before each normalisation keeps directions far below the largest singular
        # value (squared by the iteration) above rounding
        y = np.linalg.qr(residual[:, :limit - basis.shape[1]])[0]
        y = block @ np.linalg.qr(block.T @ y)[0]
        y -= basis @ (basis.T @ y)
        # Householder QR of the whole basis keeps it orthonormal even when the new
        # directions are only rounding noise (Gram-Schmidt, even twice, does not); its
        # first columns span the old basis, so the new ones extend it
        y = np.linalg.qr(np.hstack([basis, y]))[0][:, basis.shape[1]:]
        new = y.T @ block
        basis, projected = np.hstack([basis, y]), np.vstack([projected, new])
        if np.linalg.norm(new, 2) <= atol or basis.shape[1] >= limit:
            break
        # the next pass's sample is also the a-posteriori probe (``step`` Gaussian
        # probes; a separate probe cost one more pass over the block)
        residual = block @ rng.standard_normal((q, step))
        residual -= basis @ (basis.T @ residual)
        if bound * np.linalg.norm(residual, axis=0).max() <= atol:
            break
    u, s, vt = np.linalg.svd(projected, full_matrices=False)
    kept = int(np.sum(s > atol))
    return (basis @ u[:, :kept]) * s[:kept], vt[:kept].T


@dataclass
class Node:
    """A HODLR node over tree positions ``lo:hi`` (a leaf when ``children`` is empty)."""

    lo: int
    hi: int
    children: list = field(default_factory=list)
    lu: tuple | None = None  # leaf: scipy lu_factor of the dense block
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

    def solve(self, b: np.ndarray, trans: bool = False) -> np.ndarray:
        """``T_node^-1 b`` (or ``T_node^-T b``), b of shape (size, k)."""
        if not self.children:
            return scipy.linalg.lu_solve(self.lu, b, trans=1 if trans else 0)
        y = self._children_solve(b, trans)
        if self.rank == 0:
            return y
        if not trans:
            return y - self.Y @ scipy.linalg.lu_solve(self.K, self._zt(y))
        return y - self.X @ scipy.linalg.lu_solve(self.K, self._wt(y), trans=1)

    def _children_solve(self, b: np.ndarray, trans: bool = False) -> np.ndarray:
        n1 = self.children[0].size
        return np.concatenate([self.children[0].solve(b[:n1], trans), self.children[1].solve(b[n1:], trans)])

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

    def factorise(self) -> None:
        """Bottom-up: Y, X, K and the diagonal of the inverse (leaves are factorised
        when built)."""
        if not self.children:
            return
        for c in self.children:
            c.factorise()
        inv_diag = np.concatenate([c.inv_diag for c in self.children])
        if self.rank == 0:
            self.inv_diag = inv_diag
            return
        w, z = self._blocks(*self.U, swap=False), self._blocks(*self.V, swap=True)
        self.Y = self._children_solve(w)
        self.X = self._children_solve(z, trans=True)
        k = np.eye(self.rank) + z.T @ self.Y
        self.K = scipy.linalg.lu_factor(k)
        if not np.all(np.isfinite(self.K[0])) or np.min(np.abs(np.diag(self.K[0]))) == 0:
            raise TransportError(f"compressed: the Woodbury matrix of points {self.lo}:{self.hi} (tree order) "
                                 "is singular; use --solver dense")
        xk = scipy.linalg.lu_solve(self.K, self.X.T).T
        self.inv_diag = inv_diag - np.sum(self.Y * xk, axis=1)

    def memory(self) -> int:
        """Bytes held by this node and its descendants."""
        own = sum(a.nbytes for a in (*self.U, *self.V, self.Y, self.X) if a is not None)
        own += sum(part[0].nbytes for part in (self.lu, self.K) if part is not None)
        return own + sum(c.memory() for c in self.children)

    def ranks_by_level(self, level: int = 0, out: dict | None = None) -> dict[int, list[int]]:
        """Off-diagonal ranks ``[r1, r2]`` of every node, by depth (0: the root)."""
        out = {} if out is None else out
        if self.children:
            out.setdefault(level, []).extend(u.shape[1] for u in self.U)
            for c in self.children:
                c.ranks_by_level(level + 1, out)
        return out


def spatial_order(points: np.ndarray) -> np.ndarray:
    """Indices ordering points (m, d) by recursive median bisection along the widest
    axis (a k-d tree), so every half of the index range, at every level, is a compact
    region. Stable: points already ordered along a line keep their order."""
    points = np.asarray(points, dtype=np.float64)

    def split(idx: np.ndarray) -> np.ndarray:
        if idx.size <= 2:
            return idx
        p = points[idx]
        axis = int(np.argmax(p.max(axis=0) - p.min(axis=0)))
        idx = idx[np.argsort(p[:, axis], kind="stable")]
        half = idx.size // 2
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
        As :class:`ilt.transport.CancellationOperator`; ``t1_unit = 1 / diag(T_n^-1)``
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
        x[self.order] = self.root.solve(b[self.order].reshape(self.m, -1), trans).reshape(b.shape)
        return x

    def apply(self, values: np.ndarray) -> np.ndarray:
        """``C1 L`` for sample vectors ``L`` of shape (m,) or (m, k) (float64)."""
        check_photo(self.m, values)
        return scale_rows(self.t1_unit, self.solve(values))


def compressed_operator(T: np.ndarray, tol: float | None = None, points: np.ndarray | None = None,
                        leaf: int | None = None, seed: int = 0) -> CompressedOperator:
    """Build ``C1`` from T in HODLR form (see the module docstring).

    Parameters
    ----------
    T : (m, m) real array or memory map
        ISF matrix, any column scaling; read a block at a time.
    tol : float > 0 or None
        Noise sigma per entry of the unit-column T (``--noise``); None:
        :data:`DEFAULT_TOL` times max |T_n|.
    points : (m, d) float or None
        Positions of the samples (plan grid or scene); the tree follows a k-d tree
        on them. None keeps the index order.
    leaf : int or None
        Points per leaf, factorised densely (None: :data:`LEAF`).

    Raises
    ------
    TransportError
        Everything :func:`ilt.transport.prepare_isf` refuses; a tolerance that is not
        positive, or at or above the largest entry of T_n (nothing would be left of the
        light exchanged); a singular leaf or Woodbury matrix; a solve whose residual
        against T is more than :data:`RESIDUAL_FACTOR` times what the tolerance allows.
    """
    start = time.perf_counter()
    T, norms = prepare_isf(T)
    m = T.shape[0]
    inv_norms = 1.0 / norms
    peak = max(float(np.max(np.abs(T[i0:i0 + 512]) * inv_norms)) for i0 in range(0, m, 512))
    source = "the noise floor"
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
        order, ordering = spatial_order(points), "points ordered by a k-d tree on their positions"
    else:
        order, ordering = np.arange(m), "index order (no positions given)"
    ordered = np.all(order[1:] > order[:-1])
    rng = np.random.default_rng(seed)

    def block(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """``T_n[rows][:, cols]`` (float64), slices when the tree keeps the index order."""
        if ordered:
            b = np.array(T[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1], dtype=np.float64)
        else:
            b = np.array(T[np.ix_(rows, cols)], dtype=np.float64)
        b *= inv_norms[cols]  # in place: the top blocks are (m/2)^2
        return b

    def make(lo: int, hi: int) -> Node:
        node = Node(lo, hi)
        idx = order[lo:hi]
        if hi - lo <= leaf:
            node.lu = scipy.linalg.lu_factor(block(idx, idx), check_finite=False)
            pivots = np.abs(np.diag(node.lu[0]))
            if pivots.min() <= m * np.finfo(float).eps * pivots.max():
                raise TransportError(f"compressed: the block of points {lo}:{hi} (tree order) is singular "
                                     "to working precision; use --solver dense")
            node.inv_diag = np.diag(scipy.linalg.lu_solve(node.lu, np.eye(hi - lo)))
            return node
        mid = (lo + hi) // 2
        node.children = [make(lo, mid), make(mid, hi)]
        first, second = order[lo:mid], order[mid:hi]
        atol = tol * (math.sqrt(mid - lo) + math.sqrt(hi - mid))
        u1, v1 = low_rank(block(first, second), atol, rng)
        u2, v2 = low_rank(block(second, first), atol, rng)
        node.U, node.V = [u1, u2], [v1, v2]
        return node

    root = make(0, m)
    root.factorise()
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
    op.rcond = 1.0 / (_one_norm(T, inv_norms) * one_norm_estimate(_inverse(op)))
    return op


def _check_residual(T, inv_norms: np.ndarray, op: CompressedOperator, seed: int) -> tuple[float, float]:
    """``||T_n x - b|| / ||x||`` for one solve ``x = H^-1 b`` (b random), and what the
    tolerance allows: ``T_n - H`` holds the dropped tails, each ``<= atol`` of its
    block in the 2-norm, the blocks of a level disjoint, so ``||T_n - H||_2 <=``
    the sum over levels of their largest atol; plus rounding."""
    m = op.m
    b = np.random.default_rng(seed + 1).standard_normal(m)
    x = op.solve(b)
    r = -b
    for j0 in range(0, m, 512):  # column blocks of T: no m x m temporary
        r = r + np.asarray(T[:, j0:j0 + 512], dtype=np.float64) @ (inv_norms[j0:j0 + 512] * x[j0:j0 + 512])
    allowance, size = _ROUNDING * math.sqrt(m), m
    while size > op.leaf:
        half = size / 2
        allowance += op.tol * 2 * math.sqrt(half)
        size = math.ceil(half)
    return float(np.linalg.norm(r) / np.linalg.norm(x)), allowance


def _one_norm(T, inv_norms: np.ndarray) -> float:
    """``||T_n||_1``, the largest column sum, a column block at a time."""
    m = T.shape[0]
    return max(float(np.max(np.abs(np.asarray(T[:, j0:j0 + 512], dtype=np.float64)).sum(axis=0)
                            * inv_norms[j0:j0 + 512])) for j0 in range(0, m, 512))


def _inverse(op: CompressedOperator) -> LinearOperator:
    """``H^-1`` as a LinearOperator (solves both ways), for onenormest."""
    m = op.m
    return LinearOperator((m, m), matvec=op.solve, matmat=op.solve,
                          rmatvec=lambda b: op.solve(b, trans=True), rmatmat=lambda b: op.solve(b, trans=True),
                          dtype=np.float64)
