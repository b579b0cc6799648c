"""Show a vector of m samples (one per beam) as an image, and read it back.

A beam plan keeps its layout (DESIGN.md sec. 3): a 1 x m strip for a line of beams
(the paper's M scene), a rows x cols grid (the box), or the beams' spot pixels in
the camera frame. Pixel coordinates: x to the right, y down, in full-resolution
sensor pixels, the centre of the top-left pixel at (0, 0). A sample at (x, y)
belongs to pixel row floor(y + 0.5), column floor(x + 0.5) (halves round up).
"""

from __future__ import annotations

import numpy as np


def vector_to_image(
    values: np.ndarray, layout: tuple[int, int], positions: np.ndarray | None = None
) -> np.ndarray:
    """Arrange m samples in scanline order on a (rows, cols) grid.

    values : (m,) or (m, k) array; m must equal rows * cols, unless
    positions : (m,) distinct ints, the scanline cell of each sample (the beams of a
        plan that were kept when some were dropped); the other cells are 0.
    Returns (rows, cols) or (rows, cols, k), same dtype (a view when possible
    without `positions`).
    """
    values = np.asarray(values)
    rows, cols = (int(n) for n in layout)
    if values.ndim not in (1, 2):
        raise ValueError(f"values of shape {values.shape} are not (m,) or (m, k)")
    if rows < 1 or cols < 1:
        raise ValueError(f"layout {rows} x {cols} has no cells")
    if positions is not None:
        positions = np.asarray(positions)
        if (
            positions.shape != values.shape[:1]
            or positions.dtype.kind not in "iu"
            or np.unique(positions).size != positions.size
            or (positions.size and (positions.min() < 0 or positions.max() >= rows * cols))
        ):
            raise ValueError(
                f"positions must be {values.shape[0]} distinct cells of the "
                f"{rows} x {cols} layout (0 to {rows * cols - 1})"
            )
        full = np.zeros((rows * cols, *values.shape[1:]), dtype=values.dtype)
        full[positions] = values
        values = full
    if rows * cols != values.shape[0]:
        raise ValueError(
            f"layout {rows} x {cols} does not hold {values.shape[0]} samples "
            f"(rows * cols must equal m)"
        )
    return values.reshape(rows, cols, *values.shape[1:])


def splat(
    values: np.ndarray,
    samples: np.ndarray,
    frame_shape: tuple[int, int],
    fill: float = 0.0,
) -> np.ndarray:
    """Write each sample's value at its pixel of an otherwise `fill` frame.

    values : (m,) or (m, k) array.
    samples : (m, 2) pixel coordinates (x, y).
    frame_shape : (H, W) of the camera frame, pixels.
    Returns (H, W) or (H, W, k) float32.

    Raises ValueError naming the sample if one falls outside the frame or two
    fall on the same pixel (one would hide the other).
    """
    values = np.asarray(values)
    height, width = (int(n) for n in frame_shape[:2])
    rows, cols = _pixel_indices(samples, (height, width))
    if values.ndim not in (1, 2) or values.shape[0] != rows.size:
        raise ValueError(f"values of shape {values.shape} do not match {rows.size} samples")
    flat = rows * width + cols
    order = np.argsort(flat, kind="stable")
    clash = np.flatnonzero(np.diff(flat[order]) == 0)
    if clash.size:
        a, b = sorted(order[clash[0] : clash[0] + 2])
        raise ValueError(
            f"samples {a} and {b} fall on the same pixel "
            f"(x={cols[a]}, y={rows[a]}); splat them into a finer frame"
        )
    image = np.full((height, width, *values.shape[1:]), fill, dtype=np.float32)
    image[rows, cols] = values
    return image


def sample_frame(image: np.ndarray, samples: np.ndarray) -> np.ndarray:
    """Read the pixel under each sample: the inverse of `splat`.

    image : (H, W) or (H, W, C) array.
    samples : (m, 2) pixel coordinates (x, y).
    Returns (m,) or (m, C) float64.
    """
    image = np.asarray(image)
    if image.ndim not in (2, 3):
        raise ValueError(f"image of shape {image.shape} is not (H, W) or (H, W, C)")
    rows, cols = _pixel_indices(samples, image.shape[:2])
    return image[rows, cols].astype(np.float64)


def _pixel_indices(samples: np.ndarray, frame_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(m, 2) sample coordinates (x, y) -> (rows, cols) int arrays, checked against the frame."""
    samples = np.asarray(samples, dtype=np.float64)
    if samples.ndim != 2 or samples.shape[1] != 2:
        raise ValueError(f"samples of shape {samples.shape} are not (m, 2) coordinates (x, y)")
    height, width = frame_shape
    pixels = np.floor(samples + 0.5)
    # written as "not inside" so that NaN coordinates count as outside
    outside = ~(
        (pixels[:, 0] >= 0) & (pixels[:, 0] < width) & (pixels[:, 1] >= 0) & (pixels[:, 1] < height)
    )
    if outside.any():
        i = int(np.flatnonzero(outside)[0])
        x, y = samples[i]
        raise ValueError(
            f"sample {i} at (x={x:g}, y={y:g}) is outside the {width} x {height} frame "
            f"({int(outside.sum())} samples outside in all)"
        )
    return pixels[:, 1].astype(np.intp), pixels[:, 0].astype(np.intp)
