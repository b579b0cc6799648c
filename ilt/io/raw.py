"""Decode Bayer RAW files (rawpy/LibRaw) to a black-subtracted half-resolution green image.

Only the green photosites are used, as in the paper (Sec. 4): the two green sites of
each 2x2 CFA cell are averaged into one pixel of an (H/2, W/2) image. The two greens
of a Bayer cell sit on a diagonal, so their mean is centred on the cell's centre: green
pixel (row i, column j) is at full-frame ``x = 2 j + 0.5``, ``y = 2 i + 0.5`` (x right,
y down, centre of the top-left photosite at (0, 0); DESIGN.md sec. 3). No half-pixel
shift: `to_full_frame` and `GreenInfo.origin` say exactly this.
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ilt.io.exposure import ExposureFacts, read_exif, resolve_facts

#: default headroom below the white level: a sample within 3 % of clipping counts as
#: saturated, so shot noise (about 1 % of full scale near it) is never cut by the clip
SATURATION_MARGIN = 0.03


class RawError(ValueError):
    """A file that is not a Bayer RAW file LibRaw can decode; the message names it."""


@dataclass(frozen=True)
class GreenInfo:
    """What a decoded frame says about itself.

    path: the file. exposure: its exposure facts. make, model: camera.
    full_shape: (H, W) visible photosites. cfa: the 2x2 pattern letters ("RGGB").
    black_levels: (4,) float DN of the 2x2 cell positions in scanline order.
    white_level: DN of clipping used (the file's, or lower where the data clip lower).
    saturation: black-subtracted green DN at and above which a sample counts as saturated
        (``(white - black) * (1 - margin)``).
    saturated: (H/2, W/2) bool, either green site of the cell at or above ``saturation``.
    origin, scale: green pixel (i, j) is at full-frame (x, y) = origin + scale * (j, i).
    """

    path: Path
    exposure: ExposureFacts
    make: str
    model: str
    full_shape: tuple[int, int]
    cfa: str
    black_levels: tuple[float, float, float, float]
    white_level: float
    file_white_level: float
    saturation: float
    saturated: np.ndarray
    origin: tuple[float, float] = (0.5, 0.5)
    scale: float = 2.0

    @property
    def camera(self) -> str:
        return f"{self.make} {self.model}".strip()


def to_full_frame(x_half, y_half, info: GreenInfo | None = None):
    """Half-resolution green pixel coordinates -> full-frame sensor coordinates (x, y)."""
    origin, scale = (info.origin, info.scale) if info else ((0.5, 0.5), 2.0)
    return origin[0] + scale * np.asarray(x_half), origin[1] + scale * np.asarray(y_half)


def read_green(
    path: str | os.PathLike,
    exposure_time: str | None = None,
    f_number: str | None = None,
    hand_time=None,
    margin: float = SATURATION_MARGIN,
    data: bytes | None = None,
    dtype=np.float64,
) -> tuple[np.ndarray, GreenInfo]:
    """Decode a Bayer RAW file to its green image.

    Parameters
    ----------
    path : a RAW file (DNG, CR2, NEF, ...) with a 2x2 Bayer CFA.
    exposure_time, f_number : the capture manifest's text, if any ("1/125", "1.2");
        else EXIF, else rawpy's ``other``, else ``hand_time`` (Fraction, s).
    margin : fraction of the black-to-white range below the white level at which
        samples count as saturated.
    data : the file's bytes, if already read (one read serves hashing and decoding).
    dtype : of ``green``; float32 halves the memory and time of a merge.

    Returns
    -------
    green : (H/2, W/2) ``dtype``, black-subtracted DN: mean of the two green sites.
    info : GreenInfo (exposure facts, levels, saturation mask, coordinate mapping).

    Raises RawError (or ExposureError) with a one-line message naming ``path``.
    """
    path = Path(path)
    source = io.BytesIO(data) if data is not None else path
    meta = _decode(path, source, margin, dtype)
    green, saturated, white, saturation = meta.pop("green")
    facts = resolve_facts(path, exposure_time, f_number, meta["tags"], meta["other"], hand_time)
    info = GreenInfo(path, facts, meta["make"], meta["model"], meta["shape"], meta["cell"],
                     tuple(meta["black"]), float(white), float(meta["white"]), float(saturation), saturated)
    return green, info


def _green(path: Path, mosaic: np.ndarray, meta: dict, margin: float, dtype):
    """(green, saturated, white, saturation) from the visible mosaic, read in place."""
    cell = meta["cell"]
    greens = [k for k in range(4) if cell[k] == "G"]
    if len(greens) != 2 or greens not in ([0, 3], [1, 2]):
        raise RawError(f"{path}: CFA {cell!r} is not a Bayer pattern with two diagonal greens")
    black = meta["black"]
    rows, cols = mosaic.shape[0] // 2 * 2, mosaic.shape[1] // 2 * 2
    g = [mosaic[k // 2:rows:2, k % 2:cols:2] for k in greens]
    white = _effective_white(path, mosaic, meta["white"])
    black_g = (black[greens[0]] + black[greens[1]]) / 2
    top_black = max(black[greens[0]], black[greens[1]])
    saturation = (white - top_black) * (1.0 - margin)
    green = np.add(g[0], g[1], dtype=dtype)
    green *= 0.5
    green -= black_g
    saturated = np.maximum(g[0], g[1]) >= saturation + top_black
    return green, saturated, white, saturation


def read_color(path: str | os.PathLike, margin: float = SATURATION_MARGIN,
               data: bytes | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Linear camera RGB for ``--color``.

    LibRaw's ``postprocess`` with linear settings: gamma (1, 1), no auto brightening,
    ``adjust_maximum_thr=0``, unit white balance, raw colour, 16 bits, and ``half_size``
    so that each 2x2 cell gives one pixel at the same place as the green image (no
    demosaic interpolation), scaled back from 16 bits to DN above black.

    Returns (H/2, W/2, 3) float64 and an (H/2, W/2) bool mask of cells with any
    photosite within ``margin`` of the white level.
    """
    import rawpy

    path = Path(path)
    source = io.BytesIO(data) if data is not None else str(path)
    try:
        with rawpy.imread(source) as raw:
            black = float(np.mean(raw.black_level_per_channel))
            scale = (float(raw.white_level) - black) / 65535.0
            mosaic = raw.raw_image_visible
            rows, cols = mosaic.shape[0] // 2 * 2, mosaic.shape[1] // 2 * 2
            limit = black + (float(raw.white_level) - black) * (1.0 - margin)
            saturated = np.zeros((rows // 2, cols // 2), bool)
            for k in range(4):
                saturated |= mosaic[k // 2:rows:2, k % 2:cols:2] >= limit
            rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, adjust_maximum_thr=0.0,
                                  user_wb=[1.0, 1.0, 1.0, 1.0], output_color=rawpy.ColorSpace.raw,
                                  output_bps=16, half_size=True, user_flip=0)
    except (rawpy.LibRawError, rawpy.NotSupportedError) as exc:
        raise RawError(f"{path}: LibRaw cannot render it ({_reason(exc)})") from None
    return rgb[: rows // 2, : cols // 2].astype(np.float64) * scale, saturated


def _decode(path: Path, source, margin: float, dtype) -> dict:
    """Levels, EXIF tags and the `_green` image (under ``"green"``) of a RAW file, checked.
    The green image is taken from the visible mosaic in place, before the file closes
    (a copy of the whole mosaic would cost a third of the decode).
    ``source``: ``path`` or a binary file object holding its bytes."""
    import rawpy

    if isinstance(source, Path) and not path.is_file():
        raise RawError(f"{path}: no such file")
    try:
        with rawpy.imread(source if hasattr(source, "read") else str(path)) as raw:
            if raw.raw_type != rawpy.RawType.Flat:
                raise RawError(f"{path}: not a single-plane CFA raw (LibRaw raw type {raw.raw_type.name}); "
                               "only Bayer sensors are supported")
            pattern = raw.raw_pattern
            desc = raw.color_desc.decode("ascii", "replace")
            if pattern is None or pattern.shape != (2, 2):
                raise RawError(f"{path}: CFA pattern {None if pattern is None else pattern.shape} "
                               "is not a 2x2 Bayer pattern")
            mosaic = raw.raw_image_visible
            # the visible area's 2x2 pattern from the raw one; raw_colors_visible would
            # build a full-frame array of colour indices for four values
            top, left = raw.sizes.top_margin, raw.sizes.left_margin
            colors = np.roll(pattern, (-top, -left), axis=(0, 1))
            black_per_channel = list(raw.black_level_per_channel)
            white = raw.camera_white_level_per_channel or [raw.white_level]
            meta = {
                "cell": "".join(desc[c] for c in colors.ravel()),
                "black": [float(black_per_channel[c]) for c in colors.ravel()],
                "white": float(min(white)),
                "other": getattr(raw, "other", None),
                "make": "", "model": "", "shape": mosaic.shape,
            }
            if mosaic.ndim != 2 or min(mosaic.shape) < 2:
                raise RawError(f"{path}: raw image of shape {mosaic.shape} is not a 2D mosaic")
            if meta["white"] <= max(meta["black"]):
                raise RawError(f"{path}: white level {meta['white']} is not above black {max(meta['black'])}")
            meta["green"] = _green(path, mosaic, meta, margin, dtype)
            del mosaic
    except (rawpy.LibRawError, rawpy.NotSupportedError) as exc:
        raise RawError(f"{path}: not a RAW file LibRaw can decode ({_reason(exc)})") from None
    meta["tags"] = read_exif(source)
    meta["make"] = str(meta["tags"].get("Image Make", "")).strip()
    meta["model"] = str(meta["tags"].get("Image Model", "")).strip()
    return meta


def _effective_white(path: Path, mosaic: np.ndarray, file_white: float) -> float:
    """The file's white level, or the clipping seen in the data when it is lower.

    Canon's saturation point moves with ISO and is often below the white level in the
    file; many photosites at exactly the maximum value below it reveal the real clip.
    """
    top = int(mosaic.max())
    if top >= file_white:
        return file_white
    at_top = int(np.count_nonzero(mosaic == top))
    if at_top >= max(16, mosaic.size // 20000):
        return float(top)
    return file_white


def _reason(exc: Exception) -> str:
    text = str(exc)
    if text.startswith("b'") or text.startswith('b"'):
        text = text[2:-1]
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
