"""The fine operator, for full-resolution n-bounce images (docs/fullres.md); it is
applied to photos by :mod:`ilt.decompose.fullres`.

The sample-level recursion (:mod:`ilt.transport`) splits a photo's cell integrals
``L`` (m values) into bounces ``L1, L2, ...``. To split the photo's *pixels*, use that
for a Lambertian scene the light reaching pixel p after at least one interreflection is
linear in the outgoing light of the m cells: ``indirect(p) = sum_j K[p, j] L[j]``.
Every beam frame shows K at work: the unit beam frame ``F_j`` is its direct spot
``D_j`` plus ``K T[:, j]``, so ``K = G T^-1`` with ``G = F - D`` (pixels x m), the
indirect part of the unit beam frames.

G is never stored whole (P pixels x m beams, the size of the scan). Indirect light
is smooth over a surface, so inside each cell ``i`` G is modelled as a low-order
polynomial in the pixel position about the cell's centroid::

    G[p, j] = G_ij / area_i + sum_k c[k, i, j] b_k(p)          p in cell i

with basis functions ``b_k`` of zero sum over the cell (``dx``, ``dy`` for degree 1;
also ``dx^2``, ``dx dy``, ``dy^2`` less their cell means for degree 2; ``dx, dy`` in
units of the cell's size ``sqrt(area)``). The constant term is fixed by T itself:
the cell integrals of G are ``T - T1`` (T1 diagonal, the paper's direct term: the spot
is all of a beam's direct light and lies in its own cell), so only the coefficients
``c`` (K, m, m) are stored, float32, fitted by least squares over each cell's pixels
in the same pass over the frames that builds T (a sparse product per frame, like the
cell integrals). A beam's own cell holds its spot: its coefficients are set to zero
(the indirect light there is taken as flat).

For a photo, with ``r_n = L - L1 - ... - Ln`` (``r_0 = L``) and
``x_n = T^-1 r_n = L_(n+1) / t1`` (the recursion already gives it), the indirect
field of ``r_n`` is ``Phi_n(p) = r_(n+1)[i] / area_i + sum_k b_k(p) (c_k x_n)[i]``
(because ``(T - T1) T^-1 r_n = r_n - C1 r_n = r_(n+1)``), and::

    bounce 1 = photo - Phi_0,   bounce n = Phi_(n-2) - Phi_(n-1),   residual = Phi_(N-1)
    indirect = photo - bounce 1 = Phi_0

The basis sums to zero over each cell, so the full-resolution images integrate over
every cell to the sample-level bounces exactly (to rounding): the cell-consistency
identity, tested (decompose then bounds each pixel's Phi_0 by the photo and keeps the
identity wherever a cell's photo can hold its indirect light:
:class:`ilt.decompose.fullres.PhotoBound`). Pixels outside every cell have no indirect model: their coverage is
0, their bounces 0 and their residual the photo.
"""

from __future__ import annotations

import functools
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse

from ilt.io.manifest import MANIFEST, fingerprint_array, read_manifest

log = logging.getLogger(__name__)

FINE_DIR = "fine"
COEFFICIENTS_FILE = "coefficients.npy"
#: polynomial degree of the indirect light inside a cell (0: flat cells)
DEFAULT_DEGREE = 1
#: pixels outside every cell but within this many pixels of one (chessboard distance) are
#: the rim: they take the indirect light of the nearest pixel inside a cell, up to the
#: photo's own (:func:`rim`, docs/fullres.md "The rim"). Half the widest window of
#: build-isf's lit test (``ilt.isf.build.LIT_WIDE``): the reach within which that test can
#: let the scan's faint light in or out by the noise alone
RIM_PX = 10
DEGREES = (0, 1, 2)


class FineError(ValueError):
    """A fine operator that cannot be used with the ISF or photo at hand; names the file."""


def basis_terms(degree: int) -> int:
    """Number of zero-sum basis functions per cell: 0, 2 or 5."""
    if degree not in DEGREES:
        raise FineError(f"fine degree must be one of {DEGREES}, got {degree}")
    return (degree + 1) * (degree + 2) // 2 - 1


def adjacent_cells(labels: np.ndarray) -> np.ndarray:
    """(e, 2) int64 pairs ``a < b`` of cells that share a pixel edge (4-neighbours), from
    an (H, W) label image (-1 outside every cell), each pair once."""
    labels = np.asarray(labels).astype(np.int64)
    pairs = []
    for a, b in ((labels[:, :-1], labels[:, 1:]), (labels[:-1], labels[1:])):
        edge = (a >= 0) & (b >= 0) & (a != b)
        pairs.append(np.stack([np.minimum(a[edge], b[edge]), np.maximum(a[edge], b[edge])], axis=1))
    pairs = np.concatenate(pairs)
    return np.unique(pairs, axis=0) if pairs.size else np.empty((0, 2), np.int64)


@dataclass(frozen=True)
class CellGeometry:
    """What the basis needs of the cells: per pixel inside a cell its label, and per cell
    its pixel count and centroid. Derived from the labels alone, so the build and every
    decompose compute the same basis.

    inside : (n,) int64 flat indices of the pixels in a cell; label : (n,) int64 their cell;
    area : (m,) float64 pixels per cell; centre : (m, 2) float64 centroid (x, y), frame grid;
    size : (m,) float64 sqrt(area), the unit of dx, dy.
    """

    shape: tuple[int, int]
    inside: np.ndarray
    label: np.ndarray
    area: np.ndarray
    centre: np.ndarray
    size: np.ndarray

    @classmethod
    def from_labels(cls, labels: np.ndarray, m: int) -> CellGeometry:
        labels = np.asarray(labels)
        flat = labels.ravel()
        inside = np.flatnonzero(flat >= 0)
        label = flat[inside].astype(np.int64)
        area = np.bincount(label, minlength=m).astype(np.float64)
        x, y = (inside % labels.shape[1]).astype(np.float64), (inside // labels.shape[1]).astype(np.float64)
        safe = np.maximum(area, 1.0)
        centre = np.stack([np.bincount(label, x, m) / safe, np.bincount(label, y, m) / safe], axis=1)
        return cls(tuple(labels.shape), inside, label, area, centre, np.sqrt(safe))

    @property
    def m(self) -> int:
        return self.area.shape[0]

    def basis(self, degree: int) -> np.ndarray:
        """(K, n) float64 basis functions at the pixels inside cells, each of zero sum over
        its cell: dx, dy (degree 1), then dx^2, dx dy, dy^2 less their cell means."""
        width = self.shape[1]
        dx = ((self.inside % width) - self.centre[self.label, 0]) / self.size[self.label]
        dy = ((self.inside // width) - self.centre[self.label, 1]) / self.size[self.label]
        terms = [dx, dy] if degree >= 1 else []
        if degree >= 2:
            for q in (dx * dx, dx * dy, dy * dy):
                mean = np.bincount(self.label, q, self.m) / np.maximum(self.area, 1.0)
                terms.append(q - mean[self.label])
        return np.array(terms) if terms else np.empty((0, self.inside.size))

    def gram(self, degree: int, B: np.ndarray | None = None) -> np.ndarray:
        """(m, K, K) float64 ``B^T B`` of every cell's basis (``B``: :meth:`basis`, if at hand)."""
        K, m = basis_terms(degree), self.m
        B = self.basis(degree) if B is None else B
        gram = np.zeros((m, K, K))
        for a in range(K):
            for b in range(a, K):
                gram[:, a, b] = gram[:, b, a] = np.bincount(self.label, B[a] * B[b], m)
        return gram


#: a cell whose polynomial explains less than this share of its frames' variation about
#: the cell mean (beams of other cells, pooled) is taken as flat: it straddles a fold or
#: an edge of the surface, where the light jumps (measured on the M scene at m = 48: a
#: fit across the peaks doubled bounce 2's error there; flat there, bounce 1-3 errors
#: fell 10-20% below flat cells everywhere)
MIN_EXPLAINED = 0.9
#: ... or whose polynomial explains no more than this many spreads of what noise alone would
NOISE_SIGMAS = 3.0


def fit_operator(geometry: CellGeometry, degree: int) -> scipy.sparse.csr_matrix:
    """(K m, H W) sparse least-squares fit: ``fit @ frame.ravel()`` gives the (K, m)
    coefficients (row k m + i: term k of cell i) of a frame's polynomial in every cell.

    Per cell, ``(B^T B)^-1 B^T`` of its basis ``B``; the constant is not fitted (it is
    the cell integral, orthogonal to the zero-sum basis). Cells too small to fit a term
    (fewer pixels than terms, or all on a line) get the pseudo-inverse, so a term they
    cannot resolve gets coefficient 0.
    """
    K, m = basis_terms(degree), geometry.m
    B = geometry.basis(degree)
    label = geometry.label
    gram = geometry.gram(degree, B)
    scale = np.maximum(np.trace(gram, axis1=1, axis2=2), 1e-300)[:, None, None]
    inverse = np.linalg.pinv(gram / scale, rcond=1e-9, hermitian=True) / scale
    weights = np.einsum("nab,bn->an", inverse[label], B)          # (K, n): row a of (B^T B)^-1 B^T
    rows = (np.arange(K)[:, None] * m + label[None]).ravel()
    cols = np.broadcast_to(geometry.inside, (K, geometry.inside.size)).ravel()
    return scipy.sparse.csr_matrix((weights.ravel(), (rows, cols)), shape=(K * m, int(np.prod(geometry.shape))))


class FineAccumulator:
    """The stored coefficients and each cell's explained share, a block of beam columns
    at a time as the frames arrive (:func:`ilt.isf.build.build_isf`): nothing m x m in
    float64 is kept.

    out : (K, m, m) float32, written column block by column block (a memory map of
    ``fine/coefficients.npy``). Per block (:meth:`add`) the raw fits of its beams get
    their own cell zeroed (its spot is no indirect light), add their explained and
    total variation to each cell's sums over the beams of other cells, and are stored
    scaled by 1 / scales_j (unit beam frames, columns scaled like T's). :meth:`finish`
    then zeroes, in place, every cell whose polynomial explains less than
    :data:`MIN_EXPLAINED` of the frames' variation in it and returns the (m,) shares.
    The shares are sums over the beams, so blocks of any width give them to rounding
    (the coefficients themselves bit for bit).
    """

    def __init__(self, out: np.ndarray, geometry: CellGeometry, degree: int, noise_aware: bool = False,
                 keep_flat: np.ndarray | None = None):
        self.out, self.degree, self.noise_aware = out, degree, noise_aware
        # cells that take their neighbours' slope whatever their fit (at folds: ilt.isf.folds.cells_at_barriers)
        self.keep_flat = np.empty(0, np.int64) if keep_flat is None else np.asarray(keep_flat, np.int64)
        self.gram = geometry.gram(degree)                               # (m, K, K)
        self.area = np.maximum(geometry.area, 1.0)
        m = geometry.m
        self.explained, self.total = np.zeros(m), np.zeros(m)
        # what the frames' noise alone puts into both sums, and the spread of each
        self.noise_explained, self.noise_total, self.noise_spread = np.zeros(m), np.zeros(m), np.zeros(m)
        self.noise_total_spread = np.zeros(m)

    def add(self, j0: int, coefficients: np.ndarray, raw: np.ndarray, squares: np.ndarray,
            scales: np.ndarray, variance: np.ndarray | None = None) -> None:
        """Beams ``j0 .. j0 + b - 1``: coefficients (K, m, b) float64 raw fits (modified
        in place), raw (m, b) cell sums, squares (m, b) cell sums of the squared frames,
        scales (b,) their columns' 2-norms, variance (m, b) cell sums of the frames'
        per-pixel variance (:mod:`ilt.isf.noise`; with ``noise_aware``)."""
        b = raw.shape[1]
        own, k = np.arange(j0, j0 + b), np.arange(b)
        coefficients[:, own, k] = 0.0
        variation = squares - raw * raw / self.area[:, None]
        variation[own, k] = 0.0
        self.total += variation.sum(axis=1)
        self.explained += np.einsum("aij,iab,bij->i", coefficients, self.gram, coefficients)
        if self.noise_aware:
            if variance is None:
                raise ValueError("a noise-aware fine fit needs each block's cell variances")
            # noise of variance v per pixel puts (n - 1) v into a cell's variation about its
            # mean (spread 2 (n - 1) v^2) and K v (a chi-square of K terms: spread 2 K v^2)
            # into what K terms explain
            K, n = coefficients.shape[0], self.area[:, None]
            pixel = variance / n                                          # (m, b) mean per-pixel variance
            pixel[own, k] = 0.0
            self.noise_total += ((n - 1.0) * pixel).sum(axis=1)
            self.noise_explained += (K * pixel).sum(axis=1)
            self.noise_spread += (2.0 * K * pixel**2).sum(axis=1)
            self.noise_total_spread += (2.0 * (n - 1.0) * pixel**2).sum(axis=1)
        coefficients /= scales[None, None, :]
        self.out[:, :, j0:j0 + b] = coefficients

    def finish(self) -> np.ndarray:
        """Zero the cells kept flat; returns the (m,) shares, and flat cells get share < MIN_EXPLAINED.

        With the frames' noise known, the test is on the light, not on light + noise: the
        noise's expected parts are taken off both sums (noise alone made 73% of the cells
        of a noisy path-traced scan flat), and a cell whose polynomial explains no more
        than :data:`NOISE_SIGMAS` x the spread of what noise alone would is flat too: its
        slopes are noise, and would add it to every bounce image. So is a cell whose light
        varies by no more than that many spreads of the noise's own variation: there the
        share divides by a difference of two sums that noise makes alike, and reads noise
        (photon and read noise: the M's 48-beam scan 6% better, the textured M's 96 1%, the rest
        within 0.0006; photon noise alone and a path tracer's within 0.4%). And so are the
        cells given as ``keep_flat`` (those at a fold)."""
        explained, total = self.explained - self.noise_explained, self.total - self.noise_total
        share = np.where(total > 0, explained / np.where(total > 0, total, 1.0), 1.0)
        if self.noise_aware:
            resolved = (explained > NOISE_SIGMAS * np.sqrt(self.noise_spread)) & \
                (total > NOISE_SIGMAS * np.sqrt(self.noise_total_spread))
            share = np.where(resolved, share, np.minimum(share, 0.0))
        if self.keep_flat.size:
            share[self.keep_flat] = np.minimum(share[self.keep_flat], 0.0)
        flat = np.flatnonzero(share < MIN_EXPLAINED)
        if flat.size:
            self.out[:, flat, :] = 0.0
        return share


def write_fine(directory: Path, degree: int, m: int, t_fingerprint: str, labels_fingerprint: str, frames: dict,
               share: np.ndarray | None = None) -> dict[str, str]:
    """The manifest of ``directory/fine/`` (the build wrote coefficients.npy there, a
    memory map filled by :class:`FineAccumulator`; none for degree 0): the degree and the
    fingerprints of what it was built from (T by its :func:`~ilt.io.manifest.fingerprint_array`,
    the cells, the frames' directory), checked by :func:`load_fine`. Returns the
    fingerprints of the files it lists, by their paths relative to ``directory`` (the
    ISF's manifest takes them instead of reading the files again)."""
    from ilt.io.manifest import write_manifest

    fine = Path(directory) / FINE_DIR
    fine.mkdir(exist_ok=True)
    write_manifest(fine, "fine-operator", {"degree": degree},
                   inputs={"T": t_fingerprint, "cells": labels_fingerprint, **frames},
                   extra={"terms": basis_terms(degree), "m": m,
                          "flat_cells": int((share < MIN_EXPLAINED).sum()) if share is not None else m,
                          "min_explained": MIN_EXPLAINED})
    return {f"{FINE_DIR}/{name}": fingerprint for name, fingerprint in read_manifest(fine)["outputs"].items()}


@dataclass(frozen=True)
class FineOperator:
    """The per-cell indirect model of an ISF, ready to evaluate photos.

    geometry : the cells' :class:`CellGeometry`; degree : the polynomial degree;
    coefficients : (K, m, m) float32 (a memory map), K = :func:`basis_terms`; folds : the
    build's fold lines, (start, end, solid): frame-grid pixels, True at a 3D fold
    (:func:`ilt.isf.fold_transfer.recorded_lines`).
    """

    path: Path
    geometry: CellGeometry
    degree: int
    coefficients: np.ndarray
    folds: tuple = ()

    @property
    def shape(self) -> tuple[int, int]:
        return self.geometry.shape

    @functools.cached_property
    def flat_cells(self) -> np.ndarray:
        """(m,) bool: the cells the build kept flat (every coefficient of theirs 0)."""
        flat = np.ones(self.geometry.m, bool)
        for k in range(self.coefficients.shape[0]):
            flat &= ~np.any(np.asarray(self.coefficients[k]) != 0, axis=1)
        return flat

    def neighbour_slopes(self, basis: np.ndarray | None = None):
        """The :class:`ilt.isf.slopes.NeighbourSlopes` of the flat cells, or None for degree
        0 (flat cells asked for) or when no cell is flat; ``basis``: :meth:`CellGeometry.basis`."""
        from ilt.isf.slopes import NeighbourSlopes

        if self.degree < 1 or not self.flat_cells.any():
            return None
        return NeighbourSlopes(self.geometry, self.flat_cells, basis, self.folds)

    def coverage(self) -> np.ndarray:
        """(H, W) float32: 1 where a pixel's indirect light is modelled (inside a cell)."""
        out = np.zeros(int(np.prod(self.shape)), np.float32)
        out[self.geometry.inside] = 1.0
        return out.reshape(self.shape)

    @functools.cached_property
    def rim(self) -> tuple[np.ndarray, np.ndarray]:
        """:func:`rim` of the cells (found once for every photo)."""
        return rim(self.geometry)

    def per_cell(self, solved: np.ndarray) -> np.ndarray:
        """(K, m, N c) float32 ``c_k x_n`` for solved vectors ``x_n``, (N, m, c)."""
        N, m, c = solved.shape
        stacked = np.ascontiguousarray(solved.transpose(1, 0, 2).reshape(m, N * c), dtype=np.float32)
        return np.stack([np.asarray(self.coefficients[k]) @ stacked for k in range(self.coefficients.shape[0])]) \
            if self.coefficients.size else np.zeros((0, m, N * c), np.float32)

    def field(self, residual: np.ndarray, per_cell: np.ndarray, basis: np.ndarray) -> np.ndarray:
        """``Phi_n`` at the pixels inside cells, (n, c) float64: ``r_(n+1)[i] / area_i`` plus
        the basis terms, for one residual (m, c) and its (K, m, c) slice of :meth:`per_cell`."""
        label = self.geometry.label
        out = residual[label] / self.geometry.area[label][:, None]
        for k in range(basis.shape[0]):
            out += basis[k][:, None] * per_cell[k][label]
        return out


def rim(geometry: CellGeometry, width: int = RIM_PX) -> tuple[np.ndarray, np.ndarray]:
    """The pixels outside every cell within ``width`` px of one (chessboard), as flat
    indices, and for each the position in ``geometry.inside`` of the nearest pixel inside a
    cell (Euclidean). Two chamfer distance transforms and a k-d tree over the cells'
    border pixels: 0.31 s at 12 Mpx, 0.32x an exact Euclidean transform with indices
    (benchmarks/bench_rim.py)."""
    from scipy.ndimage import distance_transform_cdt
    from scipy.spatial import cKDTree

    none = np.empty(0, np.int64)
    height, width_px = geometry.shape
    if geometry.inside.size == 0 or geometry.inside.size == height * width_px or width < 1:
        return none, none
    covered = np.zeros(height * width_px, bool)
    covered[geometry.inside] = True
    covered = covered.reshape(geometry.shape)
    away = distance_transform_cdt(~covered, metric="chessboard")     # outside: to the nearest cell pixel
    pixels = np.flatnonzero((away > 0) & (away <= width))
    if pixels.size == 0:
        return none, none
    border = np.flatnonzero(covered & (distance_transform_cdt(covered, metric="chessboard") == 1))
    _, nearest = cKDTree(np.column_stack(np.divmod(border, width_px))).query(
        np.column_stack(np.divmod(pixels, width_px)))
    return pixels, np.searchsorted(geometry.inside, border[nearest])


def load_fine(isf, t_fingerprint: str | None = None) -> tuple[FineOperator | None, str]:
    """The fine operator of an ISF and, when there is none, the reason in one line.

    Raises :class:`FineError` naming the file when it exists but was built from another
    T or other cells than the ISF now holds, or from frames that have changed since.
    ``t_fingerprint``: T's :func:`~ilt.io.manifest.fingerprint_array` when the caller has it
    (hashing T again costs a pass over it).
    """
    directory = Path(isf.path).parent / FINE_DIR
    if isf.cells is None:
        return None, (f"{isf.path.parent}: no cells.exr (point sampling, ilt simulate or a bare T.npy): "
                      "bounce images at the m samples only")
    if not (directory / MANIFEST).exists():
        return None, (f"{directory}: no fine operator (built by ilt build-isf without it): "
                      "bounce images at the m samples only")
    manifest = read_manifest(directory)
    inputs = manifest.get("inputs", {})
    if inputs.get("T") != (t_fingerprint or fingerprint_array(np.asarray(isf.T))):
        raise FineError(f"{directory}: built for another T than {isf.path} (T changed since the fine operator "
                        "was built); run ilt build-isf again")
    if inputs.get("cells") != fingerprint_array(np.asarray(isf.cells)):
        raise FineError(f"{directory}: built on other cells than {isf.path.parent / 'cells.exr'}; "
                        "run ilt build-isf again")
    for where, fingerprint in inputs.items():
        if not where.startswith("frames "):
            continue
        frames = Path(isf.path).parent / where[7:]   # relative to the ISF (an absolute path stays as it is)
        if not (frames / MANIFEST).exists():
            log.info("%s: the frames it was built from (%s) are not here: not checked", directory, frames)
            continue
        from ilt.io.stage import fingerprint_input

        if fingerprint_input(frames) != fingerprint:
            raise FineError(f"{directory}: the frames in {os.path.normpath(frames)} changed since the fine "
                            "operator was built; run ilt build-isf again")
    degree = int(manifest.get("parameters", {}).get("degree", -1))
    K = basis_terms(degree) if degree in DEGREES else -1
    m = isf.m
    if K > 0:
        try:
            coefficients = np.load(directory / COEFFICIENTS_FILE, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise FineError(f"{directory / COEFFICIENTS_FILE}: not readable ({exc})") from None
        if coefficients.shape != (K, m, m):
            raise FineError(f"{directory / COEFFICIENTS_FILE}: shape {coefficients.shape}, expected {(K, m, m)} "
                            f"for degree {degree} and m = {m}")
    elif K == 0:
        coefficients = np.zeros((0, m, m), np.float32)
    else:
        raise FineError(f"{directory / MANIFEST}: degree {degree} unknown (known: {DEGREES})")
    from ilt.isf.fold_transfer import recorded_lines

    return FineOperator(directory, CellGeometry.from_labels(isf.cells, m), degree, coefficients,
                        tuple(recorded_lines(Path(isf.path).parent))), ""


def frames_inputs(hdr_path: str | os.PathLike, isf_dir: str | os.PathLike) -> dict:
    """The fingerprint of a beam frames' directory (its manifest, no frame re-read) to
    record in the fine operator, by its path from the ISF directory ``isf_dir`` (so the
    check holds when the workspace moves), or nothing when it has no manifest."""
    from ilt.io.stage import fingerprint_input

    path = Path(hdr_path)
    if not (path / MANIFEST).exists():
        return {}
    return {f"frames {os.path.relpath(path.absolute(), Path(isf_dir).absolute())}": fingerprint_input(path)}


__all__ = ["FineOperator", "FineError", "CellGeometry", "fit_operator", "FineAccumulator", "write_fine",
           "load_fine", "basis_terms", "FINE_DIR", "DEFAULT_DEGREE", "DEGREES"]
