"""An ISF matrix checked and measured once: :func:`scan_isf` reads T a block of rows at
a time and gives the :class:`IsfMatrix` that every solver takes (its column norms for
the unit-column scaling, its negative entries for the noise floor, its columns'
largest entries and 1-norms for ``compressed``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class TransportError(ValueError):
    """An ISF matrix or sample vector the operators cannot be built from or applied to."""


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
class IsfMatrix:
    """An ISF matrix checked and measured in one pass over its rows (:func:`scan_isf`):
    the value every solver of this package takes, so that none of them checks or
    measures T again.

    T : (m, m) real array as given (a memory map stays one); norms : (m,) float64, its
    column 2-norms; negative_squares : (m,) float64, per column the sum of the squared
    negative entries (for :func:`ilt.transport.solvers.estimate_noise`); negatives : how
    many entries are < 0; column_max, column_abs_sums : (m,) float64, per column the
    largest |entry| and the sum of |entries| (``compressed``'s tolerance and condition
    estimate); mapped : T was given as a memory map (``compressed`` then reads it in
    place, a block at a time).
    """

    T: np.ndarray = field(repr=False)
    norms: np.ndarray = field(repr=False)
    negative_squares: np.ndarray = field(repr=False)
    negatives: int
    column_max: np.ndarray = field(repr=False)
    column_abs_sums: np.ndarray = field(repr=False)
    mapped: bool = False

    @property
    def m(self) -> int:
        return self.T.shape[0]


def scan_isf(T: np.ndarray | IsfMatrix) -> IsfMatrix:
    """Check an ISF matrix and measure it in one pass over its rows (T can be a memory
    map: each block of rows is read once and every check and sum runs on it while it is
    in cache). An :class:`IsfMatrix` is returned as it is: it was scanned when made, so
    every function that takes T calls this first and a caller that hands down the
    IsfMatrix has T read once.

    Raises TransportError for a non-square or non-finite T (the first non-finite entry
    in row order, as a row-by-row check finds it), a zero column or two identical
    columns, naming the beam.
    """
    if isinstance(T, IsfMatrix):
        return T
    mapped = isinstance(T, np.memmap)
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
    return IsfMatrix(T=T, norms=norms, negative_squares=neg_sq, negatives=negatives, column_max=column_max,
                     column_abs_sums=abs_sums, mapped=mapped)


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
