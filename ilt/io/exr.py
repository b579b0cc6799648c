"""Linear float images as OpenEXR files, through OpenImageIO.

Every image ilt writes is a float32 EXR with named channels, lossless compression
and its metadata (exposure, units, provenance) in the header (DESIGN.md sec. 3).
Writes are atomic: a reader sees either the old file or the whole new one.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from ilt.io.atomic import atomic_path

# Lossless for float32 pixels. pxr24 rounds float32 to 24 bits, b44/b44a and
# dwaa/dwab are lossy: a radiometric pipeline must not store data through them.
LOSSLESS_COMPRESSIONS = ("none", "rle", "zips", "zip", "piz")
# zip and zips also take a deflate level, "zip:1" .. "zip:9": still lossless. Level 1
# writes a noisy float image 1.4x faster than the default for 2 % more bytes.
_LEVELLED = ("zip", "zips")


def is_lossless(compression: str) -> bool:
    """True for a compression in `LOSSLESS_COMPRESSIONS` or ``"zip:N"``/``"zips:N"``, N in 1..9."""
    name, _, level = compression.partition(":")
    if not level:
        return name in LOSSLESS_COMPRESSIONS
    return name in _LEVELLED and level in tuple("123456789")


def one_thread_per_process() -> None:
    """Worker initializer: one OpenImageIO (and OpenCV) thread in this process, so that
    N worker processes use N cores (by default each would run a thread per core)."""
    import cv2

    oiio.attribute("threads", 1)
    oiio.attribute("exr_threads", 1)
    cv2.setNumThreads(1)


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """`one_thread_per_process` for the duration of a block, then the settings before:
    a stage run with one worker in this process uses one core, like each of N workers."""
    import cv2

    before = (oiio.get_int_attribute("threads"), oiio.get_int_attribute("exr_threads"), cv2.getNumThreads())
    one_thread_per_process()
    try:
        yield
    finally:
        oiio.attribute("threads", before[0])
        oiio.attribute("exr_threads", before[1])
        cv2.setNumThreads(before[2])

# Header attributes ilt keeps for itself: the caller's channel order (the EXR
# format sorts channels by name and OIIO moves R, G, B, A first on reading) and
# the names of attributes whose values are JSON text.
_CHANNELS_ATTR = "ilt:channels"
_JSON_ATTR = "ilt:json"

_INT32 = (-(2**31), 2**31 - 1)


class ImageError(ValueError):
    """An image file could not be written or read; the message names the file."""


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """:func:`ilt.io.atomic.atomic_path` with failures reported as ImageError naming `path`.

    The temporary name keeps the suffix of `path` so that writers which pick a format
    from the extension still do; on any exception `path` is left untouched.
    """
    path = Path(path)
    try:
        with atomic_path(path) as tmp:
            yield tmp
    except OSError as exc:
        raise ImageError(f"{path}: write failed: {exc.strerror or exc}") from exc


def write_png(path: str | os.PathLike, image: np.ndarray) -> Path:
    """An 8-bit PNG (H, W) grey or (H, W, 3) BGR, atomically; errors name the file."""
    import cv2

    path = Path(path)
    # deflate level 1: level 3 takes about twice the time for files some 10 % smaller
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image, dtype=np.uint8), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ImageError(f"{path}: PNG encoding failed")
    with atomic_output(path) as tmp:
        tmp.write_bytes(buf.tobytes())
    return path


def write_exr(
    path: str | os.PathLike,
    image: np.ndarray,
    channels: list[str] | None = None,
    attributes: dict | None = None,
    compression: str = "zip",
) -> Path:
    """Write a linear image as a float32 OpenEXR file, atomically.

    Parameters
    ----------
    path : where to write; must end in ``.exr``.
    image : (H, W) or (H, W, C) array of real numbers (float or integer dtype), all
        finite after conversion to float32. Stored as 32-bit float, never half.
    channels : C channel names, in order. Default ``["Y"]`` for one channel,
        ``["R", "G", "B"]`` for three, otherwise ``["c0", ..., "c{C-1}"]``.
    attributes : header metadata. Names without a namespace get the ``ilt:``
        prefix (``"exposure"`` is stored as ``"ilt:exposure"``). str values are
        stored as strings, int values in the int32 range as ints, float values
        exactly representable in float32 as floats; any other value (dict, list,
        bool, None, a float or int that would lose precision) is stored as a JSON
        string and decoded again by `read_exr`.
    compression : one of `LOSSLESS_COMPRESSIONS` (default ``"zip"``), or ``"zip:N"`` /
        ``"zips:N"`` with a deflate level N in 1..9.

    Returns
    -------
    The path written.

    Raises
    ------
    ImageError naming the file and the fault. On failure neither `path` nor a
    temporary file is left behind (an existing file at `path` is kept as it was).
    """
    path = Path(path)
    if path.suffix.lower() != ".exr":
        raise ImageError(f"{path}: an EXR file name must end in .exr")
    if not is_lossless(compression):
        raise ImageError(
            f"{path}: compression {compression!r} is not lossless; "
            f"use one of {', '.join(LOSSLESS_COMPRESSIONS)} (zip and zips may take a level, zip:1)"
        )
    pixels = _float32_pixels(path, image)
    names = _channel_names(path, channels, pixels.shape[2])
    _check_finite(path, pixels, names)
    header = _header_attributes(path, attributes or {})

    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], "float")
    spec.channelnames = tuple(names)
    spec.attribute("compression", compression)
    spec.attribute(_CHANNELS_ATTR, json.dumps(names))
    for name, value in header.items():
        spec.attribute(name, value)
    # OpenImageIO stamps the second of writing otherwise ("" leaves it out): the same
    # pixels and attributes give the same bytes, whoever writes them and when
    spec.attribute("DateTime", "")

    with atomic_output(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise ImageError(f"{path}: OpenImageIO has no EXR writer: {oiio.geterror()}")
        if not out.open(str(tmp), spec):
            raise ImageError(f"{path}: cannot open for writing: {out.geterror()}")
        if not out.write_image(pixels):
            error = out.geterror()
            out.close()
            raise ImageError(f"{path}: writing pixels failed: {error}")
        if not out.close():
            raise ImageError(f"{path}: finishing the file failed: {out.geterror()}")
    return path


def read_exr(path: str | os.PathLike, rows: tuple[int, int] | None = None,
             shape: tuple[int, int] | None = None) -> tuple[np.ndarray, dict]:
    """Read an OpenEXR image written by `write_exr` (or any float/half EXR).

    ``rows`` (r0, r1): only those rows of the image (0 <= r0 < r1 <= its height), decoding
    only the blocks of scanlines that hold them. ``shape`` (H, W): the image must be that
    size (checked before any pixel is read).

    Returns
    -------
    pixels : (H, W, C) float32 array, channels in the order they were written.
    attributes : header attributes by their stored name (``"ilt:exposure"``),
        JSON-encoded ones decoded, plus ``"channels"``: the list of C names.

    Raises
    ------
    ImageError naming the file if it is missing, unreadable, not OpenEXR, deep,
    stores any channel as integers, or holds a NaN or infinity (the message gives
    the first such pixel (x, y) in scanline order and its channel).
    """
    path = Path(path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ImageError(f"{path}: cannot read image: {oiio.geterror()}")
    try:
        spec = inp.spec()
        if inp.format_name() != "openexr":
            raise ImageError(f"{path}: is a {inp.format_name()} file, not OpenEXR")
        if spec.deep:
            raise ImageError(f"{path}: deep EXR images are not supported")
        formats = spec.channelformats or (spec.format,) * spec.nchannels
        for name, fmt in zip(spec.channelnames, formats):
            if fmt.basetype not in (oiio.HALF, oiio.FLOAT):
                raise ImageError(f"{path}: channel {name!r} stores {fmt}, not float")
        if shape is not None and (spec.height, spec.width) != tuple(shape):
            raise ImageError(f"{path}: frame is {spec.width} x {spec.height} pixels, expected {shape[1]} x {shape[0]}")
        r0, r1 = (0, spec.height) if rows is None else (int(rows[0]), int(rows[1]))
        if not 0 <= r0 < r1 <= spec.height:
            raise ImageError(f"{path}: rows {r0}-{r1} are not within its {spec.height}")
        if rows is None:
            pixels = inp.read_image("float")
        else:
            pixels = inp.read_scanlines(0, 0, spec.y + r0, spec.y + r1, 0, 0, spec.nchannels, "float")
        if pixels is None:
            raise ImageError(f"{path}: cannot read pixels: {inp.geterror()}")
    finally:
        inp.close()

    pixels = np.asarray(pixels, dtype=np.float32).reshape(r1 - r0, spec.width, spec.nchannels)
    names = list(spec.channelnames)
    _check_finite(path, pixels, names, r0)
    attributes = {p.name: p.value for p in spec.extra_attribs}
    try:
        for name in json.loads(attributes.pop(_JSON_ATTR, "[]")):
            attributes[name] = json.loads(attributes[name])
        stored_order = json.loads(attributes.pop(_CHANNELS_ATTR, "null"))
    except (KeyError, TypeError, json.JSONDecodeError) as exc:
        raise ImageError(f"{path}: corrupt ilt header attribute: {exc!r}") from exc
    if stored_order is not None and stored_order != names and sorted(stored_order) == sorted(names):
        pixels = pixels[:, :, [names.index(n) for n in stored_order]]
        names = stored_order
    attributes["channels"] = names
    return pixels, attributes


def _float32_pixels(path: Path, image: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, C) real array -> C-contiguous (H, W, C) float32."""
    image = np.asarray(image)
    if image.dtype.kind not in "fiu":
        raise ImageError(f"{path}: cannot store pixels of dtype {image.dtype} (need real numbers)")
    if image.ndim not in (2, 3) or 0 in image.shape:
        raise ImageError(f"{path}: image shape {image.shape} is not (H, W) or (H, W, C)")
    with np.errstate(over="ignore"):  # values beyond float32 become inf, refused by the caller
        return np.ascontiguousarray(image.reshape(image.shape[0], image.shape[1], -1), np.float32)


def _check_finite(path: Path, pixels: np.ndarray, names: list[str], row: int = 0) -> None:
    """Raise ImageError at the first NaN/inf of an (H, W, C) array, in scanline order
    (``row``: the image row of the array's first)."""
    bad = ~np.isfinite(pixels)
    if bad.any():
        y, x, c = np.argwhere(bad)[0]
        raise ImageError(
            f"{path}: non-finite float32 value {pixels[y, x, c]} at pixel (x={x}, y={y + row}), "
            f"channel {names[c]!r} ({int(bad.sum())} non-finite values in all)"
        )


def _channel_names(path: Path, channels: list[str] | None, count: int) -> list[str]:
    if channels is None:
        return {1: ["Y"], 3: ["R", "G", "B"]}.get(count, [f"c{i}" for i in range(count)])
    names = list(channels)
    if len(names) != count:
        raise ImageError(f"{path}: {len(names)} channel names given for {count} channels")
    if len(set(names)) != count or not all(isinstance(n, str) and n for n in names):
        raise ImageError(f"{path}: channel names {names} must be distinct non-empty strings")
    return names


def _header_attributes(path: Path, attributes: dict) -> dict:
    """Caller's attributes -> {stored name: str | int | float}, plus the JSON index."""
    header = {}
    json_names = []
    for key, value in attributes.items():
        name = key if ":" in key else f"ilt:{key}"
        if name in (_CHANNELS_ATTR, _JSON_ATTR, "compression"):
            raise ImageError(f"{path}: attribute name {key!r} is reserved")
        if isinstance(value, np.generic):
            value = value.item()
        if isinstance(value, str):
            header[name] = value
        elif isinstance(value, int) and not isinstance(value, bool) and _INT32[0] <= value <= _INT32[1]:
            header[name] = value
        elif isinstance(value, float) and _exact_in_float32(value):
            header[name] = value
        else:
            try:
                header[name] = json.dumps(value.tolist() if isinstance(value, np.ndarray) else value)
            except TypeError as exc:
                raise ImageError(f"{path}: attribute {key!r}: {exc}") from exc
            json_names.append(name)
    if json_names:
        header[_JSON_ATTR] = json.dumps(json_names)
    return header


def _exact_in_float32(value: float) -> bool:
    with np.errstate(over="ignore"):
        return math.isfinite(value) and float(np.float32(value)) == value
