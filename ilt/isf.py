"""The ISF stage directory: ``T.npy``, ``samples.csv``, ``manifest.json``.

``T.npy`` is the m x m impulse scatter matrix (float64, column j = beam j, each column
of unit 2-norm, paper Sec. 3). ``samples.csv`` (header ``beam,x,y``) gives the pixel
where sample i is read, in full-resolution sensor pixels with the centre of the
top-left pixel at (0, 0). The manifest keeps the plan's ``layout`` (rows, cols) so a
vector of m samples can be shown as a strip or a grid, and the camera ``frame_shape``.
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ilt.manifest import MANIFEST, read_manifest, save_npy

T_FILE = "T.npy"
SAMPLES_FILE = "samples.csv"


class ISFError(ValueError):
    """An ISF directory or file that cannot be read; the message names the file."""


@dataclass(frozen=True)
class ISF:
    """An impulse scatter matrix with what is needed to show and sample its vectors.

    T : (m, m) float64; samples : (m, 2) float64 pixel (x, y) or None;
    layout : (rows, cols) with rows * cols == m; frame_shape : (H, W) or None.
    """

    T: np.ndarray
    samples: np.ndarray | None
    layout: tuple[int, int]
    frame_shape: tuple[int, int] | None
    path: Path

    @property
    def m(self) -> int:
        return self.T.shape[0]


def write_isf(
    directory: str | os.PathLike, T: np.ndarray, samples: np.ndarray, layout: tuple[int, int],
    frame_shape: tuple[int, int],
) -> dict:
    """Write ``T.npy`` and ``samples.csv`` into ``directory``; return the manifest fields
    (``layout``, ``frame_shape``, ``m``) the caller records."""
    directory = Path(directory)
    save_npy(directory / T_FILE, np.asarray(T, dtype=np.float64))
    write_samples(directory / SAMPLES_FILE, samples)
    return {"m": int(T.shape[0]), "layout": list(layout), "frame_shape": list(frame_shape)}


def write_samples(path: str | os.PathLike, samples: np.ndarray) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["beam", "x", "y"])
        for j, (x, y) in enumerate(samples):
            w.writerow([j, repr(float(x)), repr(float(y))])


def read_samples(path: Path) -> np.ndarray:
    """(m, 2) float64 from a ``beam,x,y`` CSV; beams must be 0..m-1 in order."""
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as exc:
        raise ISFError(f"{path}: cannot read ({exc.strerror})") from None
    out = np.empty((len(rows), 2))
    for i, row in enumerate(rows):
        try:
            beam, out[i, 0], out[i, 1] = int(row["beam"]), float(row["x"]), float(row["y"])
        except (KeyError, TypeError, ValueError):
            raise ISFError(f"{path}: line {i + 2} is not 'beam,x,y' numbers: {row}") from None
        if beam != i:
            raise ISFError(f"{path}: line {i + 2} has beam {beam}, expected {i} (beams in order)")
    return out


def load_isf(path: str | os.PathLike) -> ISF:
    """Read an ISF directory, or a bare ``T.npy`` (with ``samples.csv`` and
    ``manifest.json`` beside it when present)."""
    path = Path(path)
    if path.is_dir():
        directory, t_path = path, path / T_FILE
    else:
        directory, t_path = path.parent, path
    if not t_path.exists():
        raise ISFError(f"{t_path}: no such file (expected an ISF directory or a T .npy file)")
    try:
        T = np.load(t_path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ISFError(f"{t_path}: not a readable .npy array ({exc})") from None
    if T.ndim != 2 or T.shape[0] != T.shape[1]:
        raise ISFError(f"{t_path}: T must be square m x m, got shape {T.shape}")
    m = T.shape[0]
    samples = read_samples(directory / SAMPLES_FILE) if (directory / SAMPLES_FILE).exists() else None
    if samples is not None and samples.shape[0] != m:
        raise ISFError(f"{directory / SAMPLES_FILE}: {samples.shape[0]} samples for an m = {m} ISF")
    layout, frame_shape = (1, m), None
    if (directory / MANIFEST).exists():
        manifest = read_manifest(directory)
        layout = tuple(manifest.get("layout", layout))
        frame_shape = tuple(manifest["frame_shape"]) if manifest.get("frame_shape") else None
        if layout[0] * layout[1] != m:
            raise ISFError(f"{directory / MANIFEST}: layout {layout} does not hold m = {m} samples")
    return ISF(T=T, samples=samples, layout=layout, frame_shape=frame_shape, path=t_path)
