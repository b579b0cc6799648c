"""Pictures people look at: log-scaled matrices and bounce images as PNG files.

`matrix_panel` draws a row of transport matrices as the paper draws them in
Fig. 5 (T, C1 T, ..., each log-scaled to its own max); `bounce_panel` draws a
photo beside its n-bounce images as in Fig. 6, each brightened by the factor in
its title. Figures are built with matplotlib's object API (`Figure` and
`FigureCanvasAgg`, never pyplot), so nothing is kept between calls; `save_png`, the
one picture a stage draws on every run (an ISF's T.png), is drawn with OpenCV. Every
PNG is written atomically.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ilt.imageio import atomic_output, write_png

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
    The PNG is IMAGE_INCHES * DPI pixels (640 x 480): the array (max-pooled to at most
    `_MAX_IMAGE_PIXELS` a side, so a thin diagonal survives; strips thinner than 1:8
    stretched to 1:8) in matplotlib's magma colours, first and last index on each
    axis, a colorbar with its scale and the title. Drawn with OpenCV: a matplotlib
    figure took 0.33 s, most of the serial time at the end of a build-isf run.
    """
    import cv2

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"{path}: a PNG file name must end in .png")
    image = _as_2d(image, "image")
    if log:  # pooled first: the log is monotonic and the max survives pooling
        shown, limits = _decades(_max_pool(image, _MAX_IMAGE_PIXELS), floor_decades), (-floor_decades, 0.0)
        ticks = np.arange(-np.floor(floor_decades), 0.5)
        label = _DECADES_LABEL
    else:
        finite = image[np.isfinite(image)]
        limits = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
        shown, ticks, label = np.nan_to_num(image, nan=limits[0]), np.array(limits), "value"
    low, high = limits if limits[1] > limits[0] else (limits[0], limits[0] + 1.0)
    pooled = _max_pool(shown, _MAX_IMAGE_PIXELS)
    level = np.clip(np.rint(255 * (pooled - low) / (high - low)), 0, 255).astype(np.uint8)
    width, height = round(IMAGE_INCHES[0] * DPI), round(IMAGE_INCHES[1] * DPI)
    canvas = np.full((height, width, 3), 255, np.uint8)
    # the plot box, as save_png's axes were: left 0.1, bottom 0.08, width 0.72, height 0.82
    bx0, by0, bw, bh = 64, 38, 461, 394
    rows, cols = image.shape
    aspect = _aspect(image.shape)  # height of one element / its width
    scale = min(bw / cols, bh / (rows * aspect))
    dw, dh = max(1, round(cols * scale)), max(1, round(rows * aspect * scale))
    x0, y0 = bx0 + (bw - dw) // 2, by0 + (bh - dh) // 2
    picture = cv2.applyColorMap(cv2.resize(level, (dw, dh), interpolation=cv2.INTER_NEAREST), cv2.COLORMAP_MAGMA)
    canvas[y0:y0 + dh, x0:x0 + dw] = picture
    ink = (0, 0, 0)
    cv2.rectangle(canvas, (x0 - 1, y0 - 1), (x0 + dw, y0 + dh), ink, 1)
    _text(canvas, "0", (x0, y0 + dh + 16), 0.4)
    if cols > 1:
        _text(canvas, str(cols - 1), (x0 + dw, y0 + dh + 16), 0.4, align="right")
    _text(canvas, "0", (x0 - 4, y0 + 10), 0.4, align="right")
    if rows > 1:
        _text(canvas, str(rows - 1), (x0 - 4, y0 + dh), 0.4, align="right")
    # the colorbar: the same colours, bottom (low) to top (high), a label at each tick
    cx0, cw = 551, 19
    bar = np.linspace(255, 0, bh).astype(np.uint8)[:, None].repeat(cw, axis=1)
    canvas[by0:by0 + bh, cx0:cx0 + cw] = cv2.applyColorMap(bar, cv2.COLORMAP_MAGMA)
    cv2.rectangle(canvas, (cx0 - 1, by0 - 1), (cx0 + cw, by0 + bh), ink, 1)
    for t in ticks:
        ty = by0 + round((high - t) / (high - low) * (bh - 1))
        cv2.line(canvas, (cx0 + cw, ty), (cx0 + cw + 3, ty), ink, 1)
        _text(canvas, f"{t:.3g}", (cx0 + cw + 6, ty + 4), 0.38)
    side = np.full((22, bh), 255, np.uint8)  # the colorbar's label, written along it
    _text(side, label, (bh // 2, 15), 0.42, align="centre")
    canvas[by0:by0 + bh, width - 24:width - 2] = np.rot90(side, 1)[:, :, None]
    if title is not None:
        _text(canvas, title, (x0 + dw // 2, 26), 0.55, align="centre")
    return write_png(path, canvas)


def _text(canvas: np.ndarray, text: str, at: tuple[int, int], size: float, align: str = "left") -> None:
    """Black text with its baseline at ``at``: starting, centred or ending there."""
    import cv2

    (w, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, size, 1)
    x = at[0] - {"left": 0, "centre": w // 2, "right": w}[align]
    cv2.putText(canvas, text, (x, at[1]), cv2.FONT_HERSHEY_SIMPLEX, size, 0, 1, cv2.LINE_AA)


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
    return padded.reshape(height // fy, fy, width // fx, fx).max(axis=3).max(axis=1)  # one axis at a time: faster


def _save(fig: Figure, path: str | os.PathLike) -> Path:
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"{path}: a PNG file name must end in .png")
    FigureCanvasAgg(fig)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png", dpi=DPI)
    return path
