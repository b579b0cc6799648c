"""The ISF stage directory: ``T.npy``, ``samples.csv``, ``manifest.json``.

``T.npy`` is the m x m impulse scatter matrix (float64, column j = beam j, each column
of unit 2-norm, paper Sec. 3). ``samples.csv`` (header ``beam,x,y``) gives the pixel
where sample i is read, in full-resolution sensor pixels with the centre of the
top-left pixel at (0, 0). The manifest keeps the plan's ``layout`` (rows, cols) so a
vector of m samples can be shown as a strip or a grid, and the camera ``frame_shape``.

``ilt build-isf`` adds ``scales.npy`` (the column 2-norms of the raw T) and, for cell
sampling, ``cells.exr`` (per pixel the row of T whose cell it is in, -1 outside every
cell); photos are then integrated over the cells instead of read at the samples. Cells
live on the frame grid the ISF was built from (half resolution after ``ilt merge``); the
manifest's ``pixel_mapping`` {origin, scale} (also in ``cells.exr``'s attributes) says
where that grid's pixels lie in full-frame pixels, and ``frame_shape`` is the grid's.
Photos must be on the same grid. When
beams of the plan were dropped, ``samples.csv`` names the plan beam of each row of T
(strictly increasing) and ``layout`` stays the plan's, so vectors still show as the
plan's strip or grid, with gaps.
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ilt.io.frames import FULL_RESOLUTION, FrameError, PixelMapping
from ilt.io.manifest import MANIFEST, read_manifest, save_npy
from ilt.isf.spill import SPILL_FILE

T_FILE = "T.npy"
SAMPLES_FILE = "samples.csv"
CELLS_FILE = "cells.exr"
SCALES_FILE = "scales.npy"


class ISFError(ValueError):
    """An ISF directory or file that cannot be read; the message names the file."""


@dataclass(frozen=True)
class ISF:
    """An impulse scatter matrix with what is needed to show and sample its vectors.

    T : (m, m) float64; samples : (m, 2) float64 pixel (x, y) or None;
    layout : (rows, cols) of the beam plan, rows * cols >= m; frame_shape : (H, W) or None;
    beams : (m,) int plan beam of each row (scanline position in ``layout``);
    cells : (H, W) int32 row of T per pixel of the frame grid, -1 outside (cell sampling) or None;
    scales : (m,) float64 column norms of the raw T, or None;
    mapping : where frame-grid pixels lie in full-frame pixels (samples are full-frame);
    spill : (m, m) sparse ``Q``, each spot's direct light in the other cells over its own
    (:mod:`ilt.isf.spill`; None: not measured, as for point sampling or an older ISF).
    """

    T: np.ndarray
    samples: np.ndarray | None
    layout: tuple[int, int]
    frame_shape: tuple[int, int] | None
    path: Path
    beams: np.ndarray | None = None
    cells: np.ndarray | None = None
    scales: np.ndarray | None = None
    mapping: PixelMapping = FULL_RESOLUTION
    spill: object = None

    @property
    def m(self) -> int:
        return self.T.shape[0]

    @property
    def grid_samples(self) -> np.ndarray | None:
        """(m, 2) samples in frame-grid pixels: where to read a photo of ``frame_shape``."""
        return None if self.samples is None else self.mapping.to_grid(self.samples)


def write_isf(
    directory: str | os.PathLike, T: np.ndarray, samples: np.ndarray, layout: tuple[int, int],
    frame_shape: tuple[int, int], beams: list[int] | None = None, t_written: bool = False,
) -> dict:
    """Write ``T.npy`` (unless ``t_written``: T is the memory map of ``directory/T.npy``
    already) and ``samples.csv`` into ``directory``; return the manifest fields
    the caller records: ``m`` (rows of T), ``plan_m`` and ``layout`` (the plan's beams and
    their rows x cols, kept when beams were dropped so vectors show in the plan's
    places), ``dropped_beams`` (the plan beams with no row in T: the gaps) and
    ``frame_shape``. ``beams``: plan beam of each row (default 0..m-1)."""
    directory = Path(directory)
    if not t_written:
        save_npy(directory / T_FILE, np.asarray(T, dtype=np.float64))
    write_samples(directory / SAMPLES_FILE, samples, beams)
    plan_m = int(layout[0]) * int(layout[1])
    kept = set(range(len(samples)) if beams is None else (int(b) for b in beams))
    return {"m": int(T.shape[0]), "plan_m": plan_m, "layout": list(layout),
            "dropped_beams": [j for j in range(plan_m) if j not in kept], "frame_shape": list(frame_shape)}


def write_samples(path: str | os.PathLike, samples: np.ndarray, beams: list[int] | None = None) -> None:
    beams = range(len(samples)) if beams is None else beams
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["beam", "x", "y"])
        for j, (x, y) in zip(beams, samples):
            w.writerow([int(j), repr(float(x)), repr(float(y))])


def read_samples(path: Path) -> np.ndarray:
    """(m, 2) float64 from a ``beam,x,y`` CSV; beams must be 0..m-1 in order."""
    return read_samples_with_beams(path)[0]


def read_samples_with_beams(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(m, 2) float64 samples and (m,) int plan beams from a ``beam,x,y`` CSV; beams
    strictly increasing (0..m-1 when no beam was dropped)."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as exc:
        raise ISFError(f"{path}: cannot read ({exc.strerror})") from None
    out = np.empty((len(rows), 2))
    beams = np.empty(len(rows), dtype=np.int64)
    for i, row in enumerate(rows):
        try:
            beams[i], out[i, 0], out[i, 1] = int(row["beam"]), float(row["x"]), float(row["y"])
        except (KeyError, TypeError, ValueError):
            raise ISFError(f"{path}: line {i + 2} is not 'beam,x,y' numbers: {row}") from None
        if beams[i] < i or (i and beams[i] <= beams[i - 1]):
            raise ISFError(f"{path}: line {i + 2} has beam {beams[i]}, expected beams in increasing order from {i}")
    return out, beams


def load_isf(path: str | os.PathLike, mmap: bool = False) -> ISF:
    """Read an ISF directory, or a bare ``T.npy`` (with ``samples.csv`` and
    ``manifest.json`` beside it when present). ``mmap``: T stays a read-only memory
    map of the file, read as the solver needs it (the compressed solver reads it a
    block at a time; dense solvers copy it once)."""
    path = Path(path)
    if path.is_dir():
        directory, t_path = path, path / T_FILE
    else:
        directory, t_path = path.parent, path
    if not t_path.exists():
        raise ISFError(f"{t_path}: no such file (expected an ISF directory or a T .npy file)")
    try:
        T = np.load(t_path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ISFError(f"{t_path}: not a readable .npy array ({exc})") from None
    if T.ndim != 2 or T.shape[0] != T.shape[1]:
        raise ISFError(f"{t_path}: T must be square m x m, got shape {T.shape}")
    m = T.shape[0]
    samples, beams = None, None
    if (directory / SAMPLES_FILE).exists():
        samples, beams = read_samples_with_beams(directory / SAMPLES_FILE)
        if samples.shape[0] != m:
            raise ISFError(f"{directory / SAMPLES_FILE}: {samples.shape[0]} samples for an m = {m} ISF")
    layout, frame_shape, mapping = (1, m), None, FULL_RESOLUTION
    if (directory / MANIFEST).exists():
        manifest = read_manifest(directory)
        try:
            mapping = PixelMapping.from_dict(manifest.get("pixel_mapping"), directory / MANIFEST) or mapping
        except FrameError as exc:
            raise ISFError(str(exc)) from None
        layout = tuple(manifest.get("layout", layout))
        frame_shape = tuple(manifest["frame_shape"]) if manifest.get("frame_shape") else None
        plan_m = (int(beams[-1]) + 1) if beams is not None and m else m
        if layout[0] * layout[1] < plan_m or (beams is None and layout[0] * layout[1] != m):
            raise ISFError(f"{directory / MANIFEST}: layout {layout} does not hold m = {m} samples")
    if beams is not None and layout[0] * layout[1] == m:
        beams = None                                   # every beam kept: rows are the layout
    cells = read_cells(directory / CELLS_FILE, m, frame_shape) if (directory / CELLS_FILE).exists() else None
    scales = np.load(directory / SCALES_FILE, allow_pickle=False) if (directory / SCALES_FILE).exists() else None
    spill = read_spill(directory / SPILL_FILE, m) if (directory / SPILL_FILE).exists() else None
    return ISF(T=T, samples=samples, layout=layout, frame_shape=frame_shape, path=t_path, beams=beams,
               cells=cells, scales=scales, mapping=mapping, spill=spill)


def read_spill(path: Path, m: int):
    """The sparse (m, m) spill matrix of ``spill.npz``, its entries finite and >= 0."""
    import scipy.sparse

    try:
        Q = scipy.sparse.load_npz(path).tocsr()
    except (OSError, ValueError, KeyError) as exc:
        raise ISFError(f"{path}: not a readable sparse matrix ({exc})") from None
    if Q.shape != (m, m) or not np.all(np.isfinite(Q.data)) or (Q.data < 0).any():
        raise ISFError(f"{path}: expected an ({m}, {m}) matrix of finite shares >= 0, got shape {Q.shape}")
    return Q


def read_cells(path: Path, m: int, frame_shape=None) -> np.ndarray:
    """(H, W) int32 labels from ``cells.exr``, checked against m and the frame."""
    from ilt.io.exr import ImageError, read_exr

    try:
        pixels, _ = read_exr(path)
    except ImageError as exc:
        raise ISFError(str(exc)) from None
    labels = pixels[:, :, 0]
    if not np.array_equal(labels, np.round(labels)) or labels.min() < -1 or labels.max() >= m:
        raise ISFError(f"{path}: labels must be integers in -1..{m - 1}")
    if frame_shape is not None and labels.shape != tuple(frame_shape):
        raise ISFError(f"{path}: {labels.shape[1]} x {labels.shape[0]} cells for a "
                       f"{frame_shape[1]} x {frame_shape[0]} frame")
    return labels.astype(np.int32)
