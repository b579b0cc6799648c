"""Pictures people look at: log-scaled matrices and bounce images as PNG files.

`save_png` draws one array with a colour bar (an ISF's T.png); `matrix_panel` draws a
row of transport matrices as the paper draws them in Fig. 5 (T, C1 T, ..., each
log-scaled to its own max); `bounce_panel` draws a photo beside its n-bounce images as
in Fig. 6, all on the photo's grey scale, a faint image brightened by the gain in its
title. Everything is drawn with OpenCV on a uint8 canvas: matplotlib cost about 1 s to
import and 0.5 s a figure, most of the time `ilt demo --quick` spent drawing. Every
PNG is written atomically.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ilt.io.exr import write_png

#: save_png's PNG, and one panel of matrix_panel's row: (width, height) in pixels
IMAGE_SIZE = (640, 480)
PANEL_SIZE = (320, 360)

# save_png's axes are about 400 pixels high: a larger image is max-pooled to this first.
_MAX_IMAGE_PIXELS = 512
# Strips thinner than this ratio are stretched to it, so a 1 x m vector shows.
_STRIP_RATIO = 8
_DECADES_LABEL = "log10(value / max)"

# bounce_panel: the long side of a panel in the grid, at most this many grid columns,
# and the width of a panel whose aspect (width / height, once stretched) is at least
# _ROW_ASPECT: such a wide frame reads better one panel a row, and a row has room.
_BOUNCE_SIDE = 320
_BOUNCE_COLUMNS = 5
_ROW_ASPECT = 3.0
_ROW_WIDTH = 960
# no side of a bounce_panel PNG is longer than about this, however many panels
_MAX_SIDE = 1900
# bounce_panel's room above a panel for its title, between panels, round the edge, and for the colour bar
_TITLE_ROOM, _GAP, _MARGIN, _BAR_ROOM = 26, 12, 10, 104
# white in bounce_panel is this percentile of the photo's displayed pixels, so that a
# few bright pixels (a laser spot, a highlight) do not leave the rest of the photo black
_DISPLAY_PERCENTILE = 99.5
# a gain may take a faint image's display max this far over the photo's (see nice_gain)
_GAIN_SLACK = 1.1
# Hershey fonts are ASCII only
_ASCII = str.maketrans({"×": "x"})


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


def nice_gain(reference: float, peak: float) -> float:
    """The gain that shows a faint image on the photo's grey scale.

    The largest of 1, 2, 5, 10, 20, 50, ... not above 1.1 * reference / peak (the
    photo's display max over the image's): the brightened image's display max comes
    within a factor 2.5 of the photo's and at most 10 % over it, so it saturates
    about as little as the photo does. 1 where that bound is below 2, not finite, or
    either value is not positive. Photo 100, bounce 3: 1.1 * 100 / 3 = 36.7 gives 20;
    bounce 21: 5.2 gives 5.
    """
    bound = _GAIN_SLACK * reference / peak if reference > 0 and peak > 0 else 0.0
    return _nice(bound) if math.isfinite(bound) and bound >= 1 else 1.0


def gain_title(name: str, gain: float) -> str:
    """A panel's title: its name, and the gain it is shown at unless that is 1 (``bounce 2 ×20``)."""
    return name if gain == 1 else f"{name} ×{gain:.0f}"


def save_png(
    path: str | os.PathLike,
    image: np.ndarray,
    log: bool = True,
    title: str | None = None,
    floor_decades: float = 6.0,
    xlabel: str | None = None,
    ylabel: str | None = None,
) -> Path:
    """Draw a 2D array as a PNG with a colorbar; return the path written.

    image : (H, W) array. With `log`, shown as decades below its max
        (`floor_decades` deep, see `log_scale`); otherwise in its own units.
    The PNG is IMAGE_SIZE (640 x 480): the array (max-pooled to at most
    `_MAX_IMAGE_PIXELS` a side, so a thin diagonal survives; strips thinner than 1:8
    stretched to 1:8) in matplotlib's magma colours, first and last index on each
    axis with the axis names `xlabel` (columns) and `ylabel` (rows) when given, a
    colorbar with its scale and the title.
    """
    import cv2

    path = _png_path(path)
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
    width, height = IMAGE_SIZE
    canvas = np.full((height, width, 3), 255, np.uint8)
    # the plot box, as save_png's axes were: left 0.1, bottom 0.08, width 0.72, height 0.82
    bx0, by0, bw, bh = 64, 38, 461, 394
    rows, cols = image.shape
    aspect = _aspect(image.shape)  # height of one element / its width
    scale = min(bw / cols, bh / (rows * aspect))
    dw, dh = max(1, round(cols * scale)), max(1, round(rows * aspect * scale))
    x0, y0 = bx0 + (bw - dw) // 2, by0 + (bh - dh) // 2
    picture = cv2.applyColorMap(cv2.resize(level, (dw, dh), interpolation=cv2.INTER_NEAREST), cv2.COLORMAP_MAGMA)
    _paste(canvas, picture, x0, y0)
    _axis_ends(canvas, x0, y0, dw, dh, rows, cols)
    if xlabel is not None:  # below the end indices, which sit 16 pixels under the picture
        _text(canvas, xlabel, (x0 + dw // 2, y0 + dh + 32), 0.45, align="centre")
    if ylabel is not None:  # left of the end indices (right-aligned 4 pixels off the picture)
        length = max(dh, _text_width(ylabel, 0.42) + 8)
        top = max(0, min(y0 + (dh - length) // 2, height - length))
        _vertical_text(canvas, ylabel, x0 - 60, top, length)
    _colour_bar(canvas, (551, by0, 19, bh), cv2.COLORMAP_MAGMA,
                [((t - low) / (high - low), f"{t:.3g}") for t in ticks])
    _vertical_text(canvas, label, width - 24, by0, bh)
    if title is not None:
        _text(canvas, title, (x0 + dw // 2, 26), 0.55, align="centre")
    return write_png(path, canvas)


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
        clipped to [0, 1], in magma colours under its name and max. Rows are pixels
        i, columns beams j. A matrix larger than its panel is max-pooled to the
        panel's size, so a thin diagonal survives.
    The PNG is len(matrices) * PANEL_SIZE pixels (320n x 360), one colour bar at the right.
    """
    import cv2

    path = _png_path(path)
    if not matrices:
        raise ValueError("matrix_panel needs at least one matrix")
    items = [(name, _as_2d(matrix, name)) for name, matrix in matrices.items()]
    width, height = PANEL_SIZE[0] * len(items), PANEL_SIZE[1]
    canvas = np.full((height, width, 3), 255, np.uint8)
    bar_room, left, right, top, bottom = 80, 52, 10, 46, 40
    cell = (width - bar_room) // len(items)
    bw, bh = cell - left - right, height - top - bottom
    for k, (name, matrix) in enumerate(items):
        peak = matrix.max()
        # pooled to the box, not beyond: the nearest-neighbour resize below then only enlarges
        pooled = _max_pool(matrix, min(bw, bh))
        if log:
            shown = log_scale(pooled, floor_decades)
        else:
            shown = np.clip(pooled / peak, 0.0, 1.0) if peak > 0 else np.zeros_like(pooled)
        level = np.rint(255 * shown).astype(np.uint8)
        x0 = k * cell + left
        picture = cv2.applyColorMap(cv2.resize(level, (bw, bh), interpolation=cv2.INTER_NEAREST), cv2.COLORMAP_MAGMA)
        _paste(canvas, picture, x0, top)
        _axis_ends(canvas, x0, top, bw, bh, *matrix.shape)
        _text(canvas, name, (x0 + bw // 2, 18), 0.5, align="centre")
        _text(canvas, f"max {peak:.3g}", (x0 + bw // 2, 37), 0.45, align="centre")
        _text(canvas, "beam j", (x0 + bw // 2, top + bh + 32), 0.45, align="centre")
        _vertical_text(canvas, "pixel i", k * cell + 4, top, bh)
    if log:
        ticks = [(1 + t / floor_decades, f"{t:.3g}") for t in np.arange(-np.floor(floor_decades), 0.5)]
    else:
        ticks = [(t, f"{t:.3g}") for t in (0.0, 0.5, 1.0)]
    _colour_bar(canvas, (len(items) * cell + 8, top, 14, bh), cv2.COLORMAP_MAGMA, ticks)
    _vertical_text(canvas, _DECADES_LABEL if log else "value / panel max", width - 24, top, bh)
    return write_png(path, canvas)


def bounce_panel(
    path: str | os.PathLike,
    images: dict[str, np.ndarray],
    log: bool = False,
    floor_decades: float = 6.0,
) -> Path:
    """Draw a photo beside its bounce images on one grey scale (paper Fig. 6).

    images : {title: (H, W) image}; the first is the photo, e.g. {"photo": L,
        "bounce 1": L1, "bounce 2": L2, "indirect": L - L1}: full-resolution frames,
        1 x m strips or sample grids. Non-finite values count as 0.
    Every panel is area-averaged (or, where the image is smaller, enlarged in blocks)
    to about 320 pixels on its long side, strips thinner than 1:8 stretched to 1:8,
    in up to 5 columns; frames at least 3:1 wide are laid out one a row, 960 pixels
    wide. No side of the PNG is much over 1900 pixels: with many panels they shrink.
    One linear grey scale for every panel, from 0 (and any negative value) in black to
    the photo's display max (the 99.5th percentile of its displayed pixels, or its max
    where that is 0) in white, a colour bar in photo units; a later image is shown
    multiplied by `nice_gain` (photo's display max, its own), written in its title
    (``bounce 2 ×20``, see `gain_title`). With `log`, the scale is decades below the
    photo's display max, `floor_decades` deep, and every gain is 1.
    """
    canvas, _ = _bounce_canvas(images, log, floor_decades)
    return write_png(_png_path(path), canvas)


def _bounce_panels(images: dict[str, np.ndarray], log: bool) -> tuple[list[tuple[str, np.ndarray, float]], float, int]:
    """(title, image at display size, gain) per panel, the photo's display max, and the columns."""
    if not images:
        raise ValueError("bounce_panel needs at least the photo")
    items = []
    for name, image in images.items():
        image = _as_2d(image, name, np.float32)
        if not np.isfinite(image).all():
            image = np.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0)
        items.append((name, image))
    h, w = _display_shape(items[0][1].shape)
    if w >= _ROW_ASPECT * h:
        columns = 1
        box = (_ROW_WIDTH, _MAX_SIDE / len(items) - _TITLE_ROOM - _GAP)
    else:
        columns = min(len(items), _BOUNCE_COLUMNS)
        side = min(_BOUNCE_SIDE, _MAX_SIDE / -(-len(items) // columns) - _TITLE_ROOM - _GAP)
        box = (side, side)
    shown = [(name, _resample(image, _fit(_display_shape(image.shape), box))) for name, image in items]
    photo_max = _display_max(shown[0][1])
    panels = [(name, image, 1.0 if log or k == 0 else nice_gain(photo_max, _display_max(image)))
              for k, (name, image) in enumerate(shown)]
    return panels, photo_max, columns


def _bounce_canvas(images: dict[str, np.ndarray], log: bool, floor_decades: float) -> tuple[np.ndarray, list]:
    """bounce_panel's picture, and each panel's (x, y, width, height) on it."""
    import cv2

    if not floor_decades > 0:
        raise ValueError(f"floor_decades must be positive, got {floor_decades}")
    panels, photo_max, columns = _bounce_panels(images, log)
    white = photo_max if photo_max > 0 else 1.0
    cell_w = max(max(image.shape[1], _text_width(gain_title(name, gain), 0.5)) for name, image, gain in panels) + _GAP
    cell_h = max(image.shape[0] for _, image, _ in panels) + _TITLE_ROOM + _GAP
    rows = -(-len(panels) // columns)
    canvas = np.full((_MARGIN + rows * cell_h, 2 * _MARGIN + columns * cell_w + _BAR_ROOM, 3), 255, np.uint8)
    boxes = []
    for k, (name, image, gain) in enumerate(panels):
        if log:
            with np.errstate(divide="ignore"):
                decades = np.log10(np.maximum(image, 0)) - math.log10(white)
            level = np.clip(np.rint(255 * (1 + decades / floor_decades)), 0, 255)
        else:
            level = np.clip(np.rint(image * (255 * gain / white)), 0, 255)
        dh, dw = image.shape
        x = _MARGIN + (k % columns) * cell_w + (cell_w - _GAP - dw) // 2
        y = _MARGIN + (k // columns) * cell_h + _TITLE_ROOM
        _paste(canvas, level.astype(np.uint8)[:, :, None], x, y)
        cv2.rectangle(canvas, (x - 1, y - 1), (x + dw, y + dh), (160, 160, 160), 1)
        _text(canvas, gain_title(name, gain), (x + dw // 2, y - 8), 0.5, align="centre")
        boxes.append((x, y, dw, dh))
    if log:
        ticks = [(1 - d / floor_decades, f"{white * 10.0 ** -d:.2g}") for d in range(int(floor_decades) + 1)]
    else:
        step = _nice(white / 5, above=True)
        ticks = [(v / white, f"{v:.3g}") for v in np.arange(0, white * (1 + 1e-9), step)]
    bar_x, bar_top = 2 * _MARGIN + columns * cell_w, _MARGIN + _TITLE_ROOM
    bar_h = boxes[-1][1] + boxes[-1][3] - bar_top
    _colour_bar(canvas, (bar_x, bar_top, 16, bar_h), None, ticks)
    _text(canvas, "photo units", (bar_x, bar_top - 8), 0.42)
    return canvas, boxes


def _nice(x: float, above: bool = False) -> float:
    """The largest of 1, 2 or 5 times a power of ten not above x; with `above`, the smallest not below."""
    exponent = math.floor(math.log10(x))
    candidates = [s * 10.0 ** e for e in range(exponent - 1, exponent + 2) for s in (1, 2, 5)]
    slack = 1e-9 * x  # x = 100 / 10 may come out a hair under 10
    if above:
        return min(c for c in candidates if c >= x - slack)
    return max(c for c in candidates if c <= x + slack)


def _display_shape(shape: tuple[int, int]) -> tuple[float, float]:
    """(height, width) an image is shown at, in its own pixels, thin strips stretched."""
    return shape[0] * _aspect(shape), float(shape[1])


def _fit(shape: tuple[float, float], box: tuple[float, float]) -> tuple[int, int]:
    """(width, height) of a (height, width) shape scaled to fit a (width, height) box."""
    scale = min(box[0] / shape[1], box[1] / shape[0])
    return max(1, round(shape[1] * scale)), max(1, round(shape[0] * scale))


def _resample(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W) -> (height, width) of `size`: area mean along a shrinking axis, blocks along a growing one."""
    import cv2

    width, height = size
    rows, cols = image.shape
    image = np.ascontiguousarray(image)
    if width < cols or height < rows:
        image = cv2.resize(image, (min(width, cols), min(height, rows)), interpolation=cv2.INTER_AREA)
    if image.shape != (height, width):
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_NEAREST)
    return image


def _display_max(image: np.ndarray) -> float:
    high = float(np.percentile(image, _DISPLAY_PERCENTILE))
    return high if high > 0 else float(image.max())


def _paste(canvas: np.ndarray, picture: np.ndarray, x: int, y: int) -> None:
    canvas[y:y + picture.shape[0], x:x + picture.shape[1]] = picture


def _axis_ends(canvas: np.ndarray, x0: int, y0: int, dw: int, dh: int, rows: int, cols: int) -> None:
    """A frame round a picture, and the first and last index of each axis beside it."""
    import cv2

    cv2.rectangle(canvas, (x0 - 1, y0 - 1), (x0 + dw, y0 + dh), (0, 0, 0), 1)
    _text(canvas, "0", (x0, y0 + dh + 16), 0.4)
    if cols > 1:
        _text(canvas, str(cols - 1), (x0 + dw, y0 + dh + 16), 0.4, align="right")
    _text(canvas, "0", (x0 - 4, y0 + 10), 0.4, align="right")
    if rows > 1:
        _text(canvas, str(rows - 1), (x0 - 4, y0 + dh), 0.4, align="right")


def _colour_bar(canvas: np.ndarray, box: tuple[int, int, int, int], colormap: int | None,
                ticks: list[tuple[float, str]]) -> None:
    """A vertical bar, low at the bottom, in an OpenCV colour map (None: grey); ticks at fractions 0..1."""
    import cv2

    x, y, w, h = box
    ramp = np.linspace(255, 0, h).astype(np.uint8)[:, None].repeat(w, axis=1)
    _paste(canvas, cv2.applyColorMap(ramp, colormap) if colormap is not None else ramp[:, :, None], x, y)
    cv2.rectangle(canvas, (x - 1, y - 1), (x + w, y + h), (0, 0, 0), 1)
    for fraction, label in ticks:
        ty = y + round((1 - fraction) * (h - 1))
        cv2.line(canvas, (x + w, ty), (x + w + 3, ty), (0, 0, 0), 1)
        _text(canvas, label, (x + w + 6, ty + 4), 0.38)


def _vertical_text(canvas: np.ndarray, text: str, x: int, y: int, length: int) -> None:
    """Text read bottom to top, centred along `length` pixels down from (x, y), 22 pixels wide."""
    side = np.full((22, length), 255, np.uint8)
    _text(side, text, (length // 2, 15), 0.42, align="centre")
    region = canvas[y:y + length, x:x + 22]
    region[...] = np.minimum(region, np.rot90(side, 1)[:, :, None])  # keeps ink already there


def _text_width(text: str, size: float) -> int:
    import cv2

    return cv2.getTextSize(text.translate(_ASCII), cv2.FONT_HERSHEY_SIMPLEX, size, 1)[0][0]


def _text(canvas: np.ndarray, text: str, at: tuple[int, int], size: float, align: str = "left") -> None:
    """Black text with its baseline at ``at``: starting, centred or ending there."""
    import cv2

    x = at[0] - {"left": 0, "centre": _text_width(text, size) // 2, "right": _text_width(text, size)}[align]
    cv2.putText(canvas, text.translate(_ASCII), (x, at[1]), cv2.FONT_HERSHEY_SIMPLEX, size, 0, 1, cv2.LINE_AA)


def _decades(x: np.ndarray, floor_decades: float) -> np.ndarray:
    """Values as log10(x / max), in [-floor_decades, 0] (floor for x <= 0)."""
    return log_scale(x, floor_decades) * floor_decades - floor_decades


def _png_path(path: str | os.PathLike) -> Path:
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"{path}: a PNG file name must end in .png")
    return path


def _as_2d(image: np.ndarray, name: str, dtype=np.float64) -> np.ndarray:
    image = np.asarray(image, dtype=dtype)
    if image.ndim != 2 or image.size == 0:
        raise ValueError(f"{name!r}: need a non-empty 2D array, got shape {image.shape}")
    return image


def _aspect(shape: tuple[int, int]) -> float:
    """Height / width of one pixel as shown, that stretches thin strips to 1:8."""
    height, width = shape
    if width > _STRIP_RATIO * height:
        return width / (_STRIP_RATIO * height)
    if height > _STRIP_RATIO * width:
        return _STRIP_RATIO * width / height
    return 1.0


def _max_pool(a: np.ndarray, limit: int) -> np.ndarray:
    """(H, W) -> at most (limit, limit) by the max over integer blocks, a band of rows
    at a time (T of m = 24000 is 4.6 GB: no padded copy of it, only of one band)."""
    fy, fx = (-(-n // limit) for n in a.shape)
    if fy == fx == 1:
        return a
    rows, cols = -(-a.shape[0] // fy), -(-a.shape[1] // fx)
    out = np.empty((rows, cols))
    for r in range(rows):
        band = np.asarray(a[r * fy:(r + 1) * fy], dtype=np.float64).max(axis=0)
        padded = np.full(cols * fx, band.min())
        padded[: band.size] = band
        out[r] = padded.reshape(cols, fx).max(axis=1)
    return out
