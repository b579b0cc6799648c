"""Decode Bayer RAW files (rawpy/LibRaw) to a black-subtracted half-resolution green image.

Only the green photosites are used, as in the paper (Sec. 4): the two green sites of
each 2x2 CFA cell are averaged into one pixel of an (H/2, W/2) image. The two greens
of a Bayer cell sit on a diagonal, so their mean is centred on the cell's centre: green
pixel (row i, column j) is at full-frame ``x = 2 j + 0.5``, ``y = 2 i + 0.5`` (x right,
y down, centre of the top-left photosite at (0, 0); DESIGN.md sec. 3). No half-pixel
shift: `to_full_frame` and `GreenInfo.origin` say exactly this.

LibRaw applies a DNG's LinearizationTable while it unpacks (``raw_image`` holds linear
values; checked here against the table); the white level is then capped at the table's
largest value. A DNG's black level is LibRaw's (its BlackLevel per CFA position, or the
means of its MaskedAreas) except where LibRaw is known to be wrong, where it comes from
the DNG's own tags: BlackLevelDeltaH/V (LibRaw adds only their means) and a BlackLevel
pattern under an ActiveArea with an odd origin (LibRaw moves the visible area by one
photosite and leaves the pattern's phase behind). docs/hdr.md "Real files tried".
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ilt.io.exposure import ExposureFacts, quiet_logger, read_exif, resolve_facts

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
    black_levels: (4,) float DN of the 2x2 cell positions in scanline order (their means
        over the image where a DNG gives per-row or per-column deltas).
    white_level: DN of clipping used (the file's, capped at the top of a DNG
        LinearizationTable, or lower where the data clip lower).
    file_white_level: the white level the file states (LibRaw's).
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
        else ``hand_time`` (Fraction, s; ``--times``), else EXIF, else rawpy's ``other``
        (0, negative or absurd values are not used: ilt.io.exposure.resolve_facts).
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
                     tuple(meta["black"]), float(white), float(meta["file_white"]), float(saturation), saturated)
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
    deltas = meta.get("deltas")
    if deltas is not None:  # per-row and per-column black of a DNG, less their means (in black)
        dv, dh = deltas
        green -= (0.5 * (dv[greens[0] // 2:rows:2] + dv[greens[1] // 2:rows:2]))[:, None].astype(dtype)
        green -= (0.5 * (dh[greens[0] % 2:cols:2] + dh[greens[1] % 2:cols:2]))[None, :].astype(dtype)
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
    tags = read_exif(source)
    dng = read_dng_levels(source) if any(k in tags for k in _DNG_VERSION_KEYS) else None
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
            white = [w for w in (raw.camera_white_level_per_channel or []) if w > 0] or [raw.white_level]
            meta = {
                "cell": "".join(desc[c] for c in colors.ravel()),
                "black": [float(black_per_channel[c]) for c in colors.ravel()],
                "white": float(min(white)),
                "other": getattr(raw, "other", None),
                "make": "", "model": "", "shape": mosaic.shape,
            }
            meta["file_white"] = meta["white"]
            if dng is not None:
                _apply_dng_levels(path, dng, raw, meta)
            if mosaic.ndim != 2 or min(mosaic.shape) < 2:
                raise RawError(f"{path}: raw image of shape {mosaic.shape} is not a 2D mosaic")
            if meta["white"] <= max(meta["black"]):
                raise RawError(f"{path}: white level {meta['white']} is not above black {max(meta['black'])}")
            meta["green"] = _green(path, mosaic, meta, margin, dtype)
            del mosaic
    except (rawpy.LibRawError, rawpy.NotSupportedError) as exc:
        raise RawError(f"{path}: not a RAW file LibRaw can decode ({_reason(exc)})") from None
    meta["tags"] = tags
    meta["make"] = str(meta["tags"].get("Image Make", "")).strip()
    meta["model"] = str(meta["tags"].get("Image Model", "")).strip()
    return meta


_DNG_VERSION_KEYS = ("Image DNGVersion", "Image Tag 0xC612")


@dataclass(frozen=True)
class DngLevels:
    """The level tags of a DNG's CFA image (read with tifffile, independently of LibRaw).

    table: LinearizationTable (uint16) or None. black: BlackLevel as a (rows, cols) float
    pattern (BlackLevelRepeatDim), its origin at the ActiveArea's top-left. delta_v,
    delta_h: BlackLevelDeltaV (per ActiveArea row) and BlackLevelDeltaH (per column), or
    None. active: ActiveArea (top, left, bottom, right). white: WhiteLevel or None.
    masked: a MaskedAreas tag is present.
    """

    table: np.ndarray | None
    black: np.ndarray
    delta_v: np.ndarray | None
    delta_h: np.ndarray | None
    active: tuple[int, int, int, int]
    white: float | None
    masked: bool


def read_dng_levels(source) -> DngLevels | None:
    """:class:`DngLevels` of a DNG file (path or binary file object), or None when it is
    not a TIFF with a CFA image tifffile can parse. tifffile's log is silenced meanwhile."""
    import tifffile

    try:
        with quiet_logger("tifffile"):
            if hasattr(source, "read"):
                source.seek(0)
            with tifffile.TiffFile(source) as tf:
                return _levels_of(tf)
    except Exception:  # not a TIFF tifffile reads: LibRaw's levels stand
        return None
    finally:
        if hasattr(source, "seek"):
            source.seek(0)


def _levels_of(tf) -> DngLevels | None:
    candidates = []
    for page in tf.pages[:4]:
        for ifd in [page, *(page.pages or [])]:
            tags = ifd.tags
            kind = tags.get(254)
            if ifd.photometric == 32803 and (kind is None or int(kind.value) == 0):
                candidates.append(ifd)
    if not candidates:
        return None
    ifd = max(candidates, key=lambda d: d.shape[0] * d.shape[1] if len(d.shape) >= 2 else 0)
    tags = ifd.tags

    def values(code):
        tag = tags.get(code)
        if tag is None:
            return None
        v = tag.value
        v = np.atleast_1d(np.asarray(v if not isinstance(v, (int, float)) else [v]))
        if int(tag.dtype) in (5, 10):  # RATIONAL, SRATIONAL: tifffile gives numerator, denominator pairs
            v = v.astype(np.float64).reshape(-1, 2)
            v = v[:, 0] / np.where(v[:, 1] == 0, 1, v[:, 1])
        return v.astype(np.float64)

    height, width = ifd.shape[0], ifd.shape[1]
    area = values(50829)
    active = tuple(int(x) for x in area) if area is not None and area.size == 4 else (0, 0, height, width)
    dim = values(50713)
    rows, cols = (int(dim[0]), int(dim[1])) if dim is not None and dim.size == 2 else (1, 1)
    level = values(50714)
    if level is None:
        level = np.zeros(1)
    if level.size == rows * cols:
        black = level.reshape(rows, cols)
    else:  # several samples per pixel or a short tag: one level for all
        black = np.full((1, 1), float(level[0]))
    table = tags.get(50712)
    white = values(50717)
    return DngLevels(None if table is None else np.asarray(table.value, dtype=np.uint16).ravel(), black,
                     values(50716), values(50715), active, None if white is None else float(white[0]),
                     50830 in tags)


def _apply_dng_levels(path: Path, dng: DngLevels, raw, meta: dict) -> None:
    """Check LibRaw's levels against the DNG's tags and correct them where LibRaw is
    known to be wrong (module docstring); ``meta`` is updated in place."""
    if dng.table is not None and dng.table.size:
        curve = np.asarray(raw.tone_curve)
        n = min(dng.table.size, curve.size)
        if not np.array_equal(curve[:n], dng.table[:n]):
            raise RawError(f"{path}: LibRaw did not apply its DNG LinearizationTable "
                           f"({dng.table.size} entries); ilt cannot linearise it")
        top = float(dng.table.max())
        if top > max(meta["black"]):
            meta["white"] = min(meta["white"], top)
    s = raw.sizes
    oy, ox = s.top_margin - dng.active[0], s.left_margin - dng.active[1]
    h, w = meta["shape"]
    rows, cols = dng.black.shape
    varying = [d for d in (dng.delta_v, dng.delta_h) if d is not None and d.size and np.ptp(d) > 0]
    odd_phase = (dng.black.size > 1 and np.ptp(dng.black) > 0 and (oy % rows or ox % cols))
    if not varying and not odd_phase:
        return
    if rows > 2 or cols > 2 or oy < 0 or ox < 0:
        raise RawError(f"{path}: DNG black levels ({rows} x {cols} pattern, ActiveArea "
                       f"{list(dng.active)}) that ilt cannot place")
    pattern = np.array([[dng.black[(y + oy) % rows, (x + ox) % cols] for x in range(2)] for y in range(2)])

    def delta(d, offset, n):
        if d is None or not d.size:
            return np.zeros(n)
        if d.size < offset + n:
            raise RawError(f"{path}: a BlackLevelDelta tag has {d.size} entries for {offset + n} "
                           "rows or columns of the ActiveArea")
        return d[offset:offset + n]

    dv, dh = delta(dng.delta_v, oy, h), delta(dng.delta_h, ox, w)
    # per position: the pattern plus the deltas' means; the departures go to _green
    mean_v = np.array([dv[k::2].mean() for k in range(2)])
    mean_h = np.array([dh[k::2].mean() for k in range(2)])
    meta["black"] = [float(pattern[k // 2, k % 2] + mean_v[k // 2] + mean_h[k % 2]) for k in range(4)]
    if varying:
        rv, rh = dv.copy(), dh.copy()
        for k in range(2):
            rv[k::2] -= mean_v[k]
            rh[k::2] -= mean_h[k]
        meta["deltas"] = (rv, rh)


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
