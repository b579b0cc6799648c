"""Pictures people look at: log-scaled matrices and bounce images as PNG files.

`matrix_panel` draws a row of transport matrices as the paper draws them in
Fig. 5 (T, C1 T, ..., each log-scaled to its own max); `bounce_panel` draws a
photo beside its n-bounce images as in Fig. 6, each brightened by the factor in
its title. Figures are built with matplotlib's object API (`Figure` and
`FigureCanvasAgg`, never pyplot), so nothing is kept between calls; every PNG is
written atomically.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ilt.imageio import atomic_output

DPI = 100
# Figure sizes in inches: a single image (save_png), and one panel of a row.
IMAGE_INCHES = (6.4, 4.8)
PANEL_INCHES = (3.2, 3.6)

# A matrix is max-pooled to at most this many rows and columns before drawing,
# so that a thin structure (the diagonal of an ISF) survives downsampling.
_MAX_MATRIX_PIXELS = 1024
# save_png's axes are about 400 pixels high: a larger image is max-pooled to this first.
_MAX_IMAGE_PIXELS = 512
# Strips thinner than this ratio are stretched to it, so a 1 x m vector shows.
_STRIP_RATIO = 8
_DECADES_LABEL = "log10(value / max)"


def log_scale(x: np.ndarray, floor_decades: float = 6.0) -> np.ndarray:
    """Map positive values to [0, 1] on a log10 scale spanning `floor_decades` below the max.

    x : array of any shape, finite. y = 1 + log10(x / max(x)) / floor_decades,
    clipped to [0, 1]: the max maps to 1, max * 10**-floor_decades and below to 0.
    Zeros and negative values map to 0; if nothing is positive the result is all 0.

    Returns float64 array of the shape of `x`.
    Raises ValueError if `x` holds a NaN or infinity, or floor_decades <= 0.
    """
    x = np.asarray(x, dtype=np.float64)
    if not floor_decades > 0:
        raise ValueError(f"floor_decades must be positive, got {floor_decades}")
    if not np.isfinite(x).all():
        raise ValueError(f"cannot log-scale {int((~np.isfinite(x)).sum())} non-finite values")
    scaled = np.zeros(x.shape)
    positive = x > 0
    if positive.any():
        # log10(x) - log10(max) rather than log10(x / max): the ratio can underflow to 0
        decades = np.log10(x[positive]) - np.log10(x.max())
        scaled[positive] = np.clip(1.0 + decades / floor_decades, 0.0, 1.0)
    return scaled


def save_png(
    path: str | os.PathLike,
    image: np.ndarray,
    log: bool = True,
    title: str | None = None,
    floor_decades: float = 6.0,
) -> Path:
    """Draw a 2D array as a PNG with a colorbar; return the path written.

    image : (H, W) array. With `log`, shown as decades below its max
        (`floor_decades` deep, see `log_scale`); otherwise in its own units.
    The PNG is IMAGE_INCHES * DPI pixels (640 x 480). Strips thinner than 1:8 are
    stretched to 1:8.
    """
    image = _as_2d(image, "image")
    # fixed axes, no layout engine: constrained layout measured every tick label and
    # took most of the time of a figure
    fig = Figure(figsize=IMAGE_INCHES, dpi=DPI)
    ax = fig.add_axes((0.1, 0.08, 0.72, 0.82))
    if log:
        shown, limits, label = _decades(image, floor_decades), (-floor_decades, 0.0), _DECADES_LABEL
    else:
        shown, limits, label = image, (None, None), "value"
    drawn = ax.imshow(
        # max-pooled to about the pixels drawn: a thin diagonal survives, and
        # matplotlib does not resample a large matrix
        _max_pool(shown, _MAX_IMAGE_PIXELS), cmap="magma", vmin=limits[0], vmax=limits[1],
        aspect=_aspect(image.shape), interpolation="nearest",
        extent=(-0.5, image.shape[1] - 0.5, image.shape[0] - 0.5, -0.5),
    )
    fig.colorbar(drawn, cax=fig.add_axes((0.86, 0.08, 0.03, 0.82)), label=label)
    if title is not None:
        ax.set_title(title)
    return _save(fig, path)


def matrix_panel(
    path: str | os.PathLike,
    matrices: dict[str, np.ndarray],
    log: bool = True,
    floor_decades: float = 6.0,
) -> Path:
    """Draw matrices side by side, each scaled to its own max (paper Fig. 5).

    matrices : {title: (pixels, beams) array}, e.g. {"T": T, "C1 T": ..., "T - C1 T": ...}.
        Each panel shows its matrix relative to its own max: in decades below it
        with `log` (negative entries show as the floor), else as value / max
        clipped to [0, 1]. Rows are pixels i, columns beams j.
    The PNG is len(matrices) * PANEL_INCHES * DPI pixels (320n x 360).
    """
    if not matrices:
        raise ValueError("matrix_panel needs at least one matrix")
    fig = Figure(
        figsize=(PANEL_INCHES[0] * len(matrices), PANEL_INCHES[1]), dpi=DPI, layout="constrained"
    )
    axes = fig.subplots(1, len(matrices), squeeze=False)[0]
    for ax, (name, matrix) in zip(axes, matrices.items()):
        matrix = _as_2d(matrix, name)
        peak = matrix.max()
        if log:
            shown = _decades(matrix, floor_decades)
        else:
            shown = np.clip(matrix / peak, 0.0, 1.0) if peak > 0 else np.zeros_like(matrix)
        drawn = ax.imshow(
            _max_pool(shown, _MAX_MATRIX_PIXELS), cmap="magma",
            vmin=-floor_decades if log else 0.0, vmax=0.0 if log else 1.0,
            aspect="auto", interpolation="nearest",
            extent=(-0.5, matrix.shape[1] - 0.5, matrix.shape[0] - 0.5, -0.5),
        )
        ax.set_title(f"{name}\nmax {peak:.3g}")
        ax.set_xlabel("beam j")
        ax.set_ylabel("pixel i")
    fig.colorbar(drawn, ax=list(axes), label=_DECADES_LABEL if log else "value / panel max")
    return _save(fig, path)


def bounce_panel(
    path: str | os.PathLike,
    images: dict[str, np.ndarray],
    log: bool = False,
    floor_decades: float = 6.0,
) -> Path:
    """Draw a photo beside its bounce images (paper Fig. 6).

    images : {title: (H, W) image}; the first is the photo, e.g.
        {"photo": L, "1 bounce": L1, "2 bounces": L2, "indirect": L - L1}. A 1 x m
        strip is stretched to a visible height; grid images are shown as they are.
        Each later image is multiplied by the factor that brings its max to the
        photo's max, and its title says so (``"2 bounces ×12"``); linear grey
        scale from 0 to the photo's max, or with `log` decades below it.
    The PNG is len(images) * PANEL_INCHES * DPI pixels (320n x 360).
    """
    if not images:
        raise ValueError("bounce_panel needs at least the photo")
    items = [(name, _as_2d(image, name)) for name, image in images.items()]
    reference = items[0][1].max()
    fig = Figure(
        figsize=(PANEL_INCHES[0] * len(items), PANEL_INCHES[1]), dpi=DPI, layout="constrained"
    )
    axes = fig.subplots(1, len(items), squeeze=False)[0]
    for index, (ax, (name, image)) in enumerate(zip(axes, items)):
        peak = image.max()
        factor = reference / peak if reference > 0 and peak > 0 else 1.0
        if log:
            # after scaling every max equals the photo's, so its own max is the reference
            shown, limits = _decades(image, floor_decades), (-floor_decades, 0.0)
        else:
            shown, limits = image * factor, (0.0, reference if reference > 0 else 1.0)
        drawn = ax.imshow(
            shown, cmap="gray", vmin=limits[0], vmax=limits[1],
            aspect=_aspect(image.shape), interpolation="nearest",
        )
        ax.set_title(name if index == 0 or factor == 1.0 else f"{name} ×{factor:.3g}")
        ax.set_xticks([])  # a frame, no ticks: bright pixels stay visible at the edge
        ax.set_yticks([])
    fig.colorbar(drawn, ax=list(axes), label=_DECADES_LABEL if log else "photo units")
    return _save(fig, path)


def _decades(x: np.ndarray, floor_decades: float) -> np.ndarray:
    """Values as log10(x / max), in [-floor_decades, 0] (floor for x <= 0)."""
    return log_scale(x, floor_decades) * floor_decades - floor_decades


def _as_2d(image: np.ndarray, name: str) -> np.ndarray:
    image = np.asarray(image, dtype=np.float64)
    if image.ndim != 2 or image.size == 0:
        raise ValueError(f"{name!r}: need a non-empty 2D array, got shape {image.shape}")
    return image


def _aspect(shape: tuple[int, int]) -> float:
    """imshow aspect (height / width of one pixel) that stretches thin strips to 1:8."""
    height, width = shape
    if width > _STRIP_RATIO * height:
        return width / (_STRIP_RATIO * height)
    if height > _STRIP_RATIO * width:
        return _STRIP_RATIO * width / height
    return 1.0


def _max_pool(a: np.ndarray, limit: int) -> np.ndarray:
    """(H, W) -> at most (limit, limit) by the max over integer blocks."""
    fy, fx = (-(-n // limit) for n in a.shape)
    if fy == fx == 1:
        return a
    height, width = -(-a.shape[0] // fy) * fy, -(-a.shape[1] // fx) * fx
    padded = np.full((height, width), a.min())
    padded[: a.shape[0], : a.shape[1]] = a
    return padded.reshape(height // fy, fy, width // fx, fx).max(axis=(1, 3))


def _save(fig: Figure, path: str | os.PathLike) -> Path:
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"{path}: a PNG file name must end in .png")
    FigureCanvasAgg(fig)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png", dpi=DPI)
    return path
