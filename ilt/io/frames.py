"""HDR directories (one linear EXR per beam) and their frames.

An HDR directory is any directory of EXR files, one per beam, taken in the order of
their sorted names (``ilt merge`` writes ``beam-00000.exr`` ...), with an optional
``manifest.json`` carrying the beam plan's ``layout`` [rows, cols]. With a plan, the
files must be named ``beam-<index>.exr`` or be exactly rows x cols in number.

Frames may sit on a coarser grid than the sensor: ``ilt merge`` writes half-resolution
green images. The EXR attributes ``ilt:pixel_origin`` [x, y] and ``ilt:pixel_scale``
(else the directory manifest's ``pixel_mapping``) say where frame pixel (i, j) lies in
full-frame sensor pixels (DESIGN.md sec. 3); frames without them are full resolution.
Spots and samples are stored in full-frame pixels; cells stay on the frame grid.

Per-beam work on them (centroids, columns of T) runs in chunks of beams through
:mod:`ilt.parallel.chunks`.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from ilt.io.exr import ImageError, read_exr
from ilt.io.manifest import MANIFEST

_BEAM_NAME = re.compile(r"^beam-(\d+)\.exr$", re.IGNORECASE)


class FrameError(ValueError):
    """An HDR directory or frame that cannot be used; the message names the file or beam."""


@dataclass(frozen=True)
class PixelMapping:
    """Frame pixel (row i, column j) lies at full-frame (x, y) = origin + scale * (j, i).

    Full resolution: origin (0, 0), scale 1. A half-resolution green image of a Bayer
    sensor (:func:`ilt.io.raw.to_full_frame`): origin (0.5, 0.5), scale 2.
    """

    origin: tuple[float, float] = (0.0, 0.0)
    scale: float = 1.0

    ORIGIN_ATTR = "ilt:pixel_origin"
    SCALE_ATTR = "ilt:pixel_scale"

    def to_full(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) frame-grid (x, y) -> full-frame pixels."""
        return np.asarray(self.origin) + self.scale * np.asarray(xy, dtype=np.float64)

    def to_grid(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) full-frame (x, y) -> frame-grid pixels."""
        return (np.asarray(xy, dtype=np.float64) - np.asarray(self.origin)) / self.scale

    def attributes(self) -> dict:
        """EXR header attributes for :func:`ilt.io.exr.write_exr`."""
        return {self.ORIGIN_ATTR: [float(v) for v in self.origin], self.SCALE_ATTR: float(self.scale)}

    def as_dict(self) -> dict:
        return {"origin": [float(v) for v in self.origin], "scale": float(self.scale)}

    @classmethod
    def from_dict(cls, data: dict | None, where) -> PixelMapping | None:
        """From ``{"origin": [x, y], "scale": s}`` (a manifest's ``pixel_mapping``); None when absent."""
        if not data:
            return None
        try:
            origin = tuple(float(v) for v in data["origin"])
            scale = float(data["scale"])
            assert len(origin) == 2 and scale > 0
        except (KeyError, TypeError, ValueError, AssertionError):
            raise FrameError(f"{where}: pixel_mapping {data!r} is not {{origin: [x, y], scale: > 0}}") from None
        return cls(origin, scale)

    @classmethod
    def from_attributes(cls, attributes, where) -> PixelMapping | None:
        """From EXR header attributes (a dict or an OpenImageIO ImageSpec); None when absent."""
        get = attributes.getattribute if hasattr(attributes, "getattribute") else attributes.get
        origin, scale = get(cls.ORIGIN_ATTR), get(cls.SCALE_ATTR)
        if origin is None and scale is None:
            return None
        if isinstance(origin, str):
            try:
                origin = json.loads(origin)
            except json.JSONDecodeError:
                pass
        return cls.from_dict({"origin": origin if origin is not None else (0.0, 0.0),
                              "scale": scale if scale is not None else 1.0}, where)


FULL_RESOLUTION = PixelMapping()


@dataclass(frozen=True)
class HDRDirectory:
    """The beam frames of one scan.

    files: m paths, file b is beam b of the plan; layout: (rows, cols), rows * cols == m;
    frame_shape: (H, W) pixels, the same for every file (checked from the headers);
    mapping: where frame pixels lie in full-frame sensor pixels, the same for every file.
    """

    path: Path
    files: tuple[Path, ...]
    layout: tuple[int, int]
    frame_shape: tuple[int, int]
    mapping: PixelMapping = FULL_RESOLUTION

    @property
    def m(self) -> int:
        return len(self.files)


def frame_header(path: Path) -> tuple[tuple[int, int], PixelMapping | None]:
    """(H, W) and the pixel mapping (None when the header has none) from an EXR header,
    without reading the pixels."""
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise FrameError(f"{path}: cannot read image header: {oiio.geterror()}")
    try:
        spec = inp.spec()
        if inp.format_name() != "openexr":
            raise FrameError(f"{path}: is a {inp.format_name()} file, not OpenEXR")
        return (int(spec.height), int(spec.width)), PixelMapping.from_attributes(spec, path)
    finally:
        inp.close()


def open_hdr_directory(path: str | os.PathLike | HDRDirectory) -> HDRDirectory:
    """List and check an HDR directory (headers only): every beam has an image, all the
    same size. An :class:`HDRDirectory` already opened is returned as it is (a run of
    two stages reads the headers once)."""
    if isinstance(path, HDRDirectory):
        return path
    path = Path(path)
    if not path.is_dir():
        raise FrameError(f"{path}: not a directory of EXR frames")
    files = sorted(p for p in path.iterdir() if p.suffix.lower() == ".exr" and not p.name.startswith("."))
    if not files:
        raise FrameError(f"{path}: no EXR frames (expected one .exr per beam)")
    layout = (1, len(files))
    default = FULL_RESOLUTION
    if (path / MANIFEST).exists():
        try:
            plan = json.loads((path / MANIFEST).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise FrameError(f"{path / MANIFEST}: not readable JSON ({exc})") from None
        if plan.get("layout"):
            layout = tuple(int(n) for n in plan["layout"])
            files = _plan_files(path, files, layout[0] * layout[1])
        default = PixelMapping.from_dict(plan.get("pixel_mapping"), path / MANIFEST) or default
    shape = mapping = None
    for f in files:
        s, own = frame_header(f)
        own = own or default
        if shape is None:
            shape, mapping, first = s, own, f
        elif s != shape:
            raise FrameError(f"{f}: frame is {s[1]} x {s[0]} pixels, {first.name} is {shape[1]} x {shape[0]}")
        elif own != mapping:
            raise FrameError(f"{f}: pixel mapping {own.as_dict()} differs from {first.name}'s {mapping.as_dict()}")
    return HDRDirectory(path=path, files=tuple(files), layout=layout, frame_shape=shape, mapping=mapping)


def _plan_files(path: Path, files: list[Path], m: int) -> list[Path]:
    named = {int(mt.group(1)): f for f in files if (mt := _BEAM_NAME.match(f.name))}
    if len(named) == len(files):
        for b in range(m):
            if b not in named:
                raise FrameError(f"{path}: beam {b} has no image (expected beam-{b:05d}.exr; the plan has {m} beams)")
        if extra := sorted(set(named) - set(range(m))):
            raise FrameError(f"{named[extra[0]]}: beam {extra[0]} is not in the plan of {m} beams")
        return [named[b] for b in range(m)]
    if len(files) != m:
        raise FrameError(f"{path}: {len(files)} EXR frames for a plan of {m} beams ({path / MANIFEST})")
    return files


def read_frame(path: str | os.PathLike, shape: tuple[int, int] | None = None) -> np.ndarray:
    """(H, W) float32 linear frame: the green channel ("G") if there is one, else the only one."""
    return read_frame_with_mapping(path, shape)[0]


def read_frame_rows(path: str | os.PathLike, shape: tuple[int, int], rows: tuple[int, int]) -> np.ndarray:
    """(r1 - r0, W) float32: rows ``rows`` (r0, r1) of :func:`read_frame`, decoding only
    the blocks that hold them (a frame must be ``shape``)."""
    return read_frame_with_mapping(path, shape, rows)[0]


def read_frame_with_mapping(path: str | os.PathLike, shape: tuple[int, int] | None = None,
                            rows: tuple[int, int] | None = None) -> tuple[np.ndarray, PixelMapping | None]:
    """:func:`read_frame` and the frame's pixel mapping from its header (None when it has none)."""
    try:
        pixels, attrs = read_exr(path, rows, shape if rows is not None else None)
    except ImageError as exc:
        raise FrameError(str(exc)) from None
    names = attrs["channels"]
    if "G" in names:
        image = pixels[:, :, names.index("G")]
    elif len(names) == 1:
        image = pixels[:, :, 0]
    else:
        raise FrameError(f"{path}: channels {names}: need a 'G' channel or a single channel")
    if rows is None and shape is not None and image.shape != tuple(shape):
        raise FrameError(f"{path}: frame is {image.shape[1]} x {image.shape[0]} pixels, expected {shape[1]} x {shape[0]}")
    return image, PixelMapping.from_attributes(attrs, path)


@dataclass(frozen=True)
class FrameScratch:
    """Decoded frames kept between two passes over an HDR directory (a combined centroids
    + build-isf run decodes every EXR once): one raw float32 file in ``directory``,
    beam b's (H, W) frame at byte offset b H W 4, written by the first pass's workers
    and read back by the second's. Reading a frame back costs a copy from the page
    cache, not a second EXR decode; one file, written and read in place, costs less
    than a file per frame (no create, header or unlink per frame).

    Which frames are there is recorded by the process that ran the first pass
    (:meth:`record`, after every worker finished); a frame that could not be written
    (the disk is full) is left out of the record and decoded again. Frames not in the
    record are never read. The directory and the file are removed by whoever made the
    directory (disk: m H W 4 bytes while both passes run).
    """

    directory: Path
    shape: tuple[int, int]

    FRAMES = "frames.f32"
    RECORD = "kept.json"

    @property
    def path(self) -> Path:
        return Path(self.directory) / self.FRAMES

    @property
    def frame_bytes(self) -> int:
        return self.shape[0] * self.shape[1] * 4

    def open(self, write: bool = False) -> int:
        """A file descriptor on the frames file (created when writing); close it with os.close."""
        return os.open(self.path, (os.O_WRONLY | os.O_CREAT) if write else os.O_RDONLY, 0o600)

    def keep(self, fd: int, beam: int, frame: np.ndarray) -> None:
        """Write beam ``beam``'s frame; raises OSError (ENOSPC: the disk is full)."""
        if frame.shape != tuple(self.shape):
            raise FrameError(f"beam {beam}: frame of {frame.shape[1]} x {frame.shape[0]} pixels, "
                             f"the scan's are {self.shape[1]} x {self.shape[0]}")
        data = memoryview(np.ascontiguousarray(frame, dtype=np.float32)).cast("B")
        offset, done = beam * self.frame_bytes, 0
        while done < len(data):
            done += os.pwrite(fd, data[done:], offset + done)

    def read(self, fd: int, beam: int, out: np.ndarray) -> np.ndarray:
        """Beam ``beam``'s frame into ``out`` ((H, W) float32)."""
        got = os.preadv(fd, [out], beam * self.frame_bytes)
        if got != self.frame_bytes:
            raise FrameError(f"{self.path}: beam {beam}: {got} of {self.frame_bytes} bytes")
        return out

    def record(self, beams: Iterable[int]) -> None:
        """Record (atomically) that these beams' frames were written in full."""
        from ilt.io.manifest import write_json

        write_json(Path(self.directory) / self.RECORD, {"shape": list(self.shape), "beams": sorted(beams)})

    def kept(self) -> frozenset[int]:
        """The beams recorded as kept; none when there is no record or it is for frames of
        another size."""
        try:
            record = json.loads((Path(self.directory) / self.RECORD).read_text())
        except (OSError, json.JSONDecodeError):
            return frozenset()
        if tuple(record.get("shape", ())) != tuple(self.shape) or not self.path.exists():
            return frozenset()
        return frozenset(int(b) for b in record.get("beams", ()))


def load_frame(path: str | os.PathLike, shape: tuple[int, int] | None = None,
               out: np.ndarray | None = None) -> np.ndarray:
    """:func:`read_frame`; with ``out`` (an array of the frame's shape) copied into it,
    converting its dtype, so that a loop over frames reuses one buffer."""
    frame = read_frame(path, shape)
    if out is None:
        return frame
    np.copyto(out, frame)
    return out
