"""HDR directories (one linear EXR per beam) and running per-beam work in parallel.

An HDR directory is any directory of EXR files, one per beam, taken in the order of
their sorted names (``ilt merge`` writes ``beam-00000.exr`` ...), with an optional
``manifest.json`` carrying the beam plan's ``layout`` [rows, cols]. With a plan, the
files must be named ``beam-<index>.exr`` or be exactly rows x cols in number.

Per-beam work (centroids, columns of T) runs through a ``concurrent.futures``
executor in chunks of beams, with a bounded number of chunks in flight, so memory
holds a few frames per worker however many beams there are.
"""

from __future__ import annotations

import json
import os
import re
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from ilt.imageio import ImageError, read_exr
from ilt.manifest import MANIFEST

_BEAM_NAME = re.compile(r"^beam-(\d+)\.exr$", re.IGNORECASE)


class FrameError(ValueError):
    """An HDR directory or frame that cannot be used; the message names the file or beam."""


@dataclass(frozen=True)
class HDRDirectory:
    """The beam frames of one scan.

    files: m paths, file b is beam b of the plan; layout: (rows, cols), rows * cols == m;
    frame_shape: (H, W) pixels, the same for every file (checked from the headers).
    """

    path: Path
    files: tuple[Path, ...]
    layout: tuple[int, int]
    frame_shape: tuple[int, int]

    @property
    def m(self) -> int:
        return len(self.files)


def frame_header_shape(path: Path) -> tuple[int, int]:
    """(H, W) from an EXR header, without reading the pixels."""
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise FrameError(f"{path}: cannot read image header: {oiio.geterror()}")
    try:
        spec = inp.spec()
        if inp.format_name() != "openexr":
            raise FrameError(f"{path}: is a {inp.format_name()} file, not OpenEXR")
        return int(spec.height), int(spec.width)
    finally:
        inp.close()


def open_hdr_directory(path: str | os.PathLike) -> HDRDirectory:
    """List and check an HDR directory (headers only): every beam has an image, all the same size."""
    path = Path(path)
    if not path.is_dir():
        raise FrameError(f"{path}: not a directory of EXR frames")
    files = sorted(p for p in path.iterdir() if p.suffix.lower() == ".exr" and not p.name.startswith("."))
    if not files:
        raise FrameError(f"{path}: no EXR frames (expected one .exr per beam)")
    layout = (1, len(files))
    if (path / MANIFEST).exists():
        try:
            plan = json.loads((path / MANIFEST).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise FrameError(f"{path / MANIFEST}: not readable JSON ({exc})") from None
        if plan.get("layout"):
            layout = tuple(int(n) for n in plan["layout"])
            files = _plan_files(path, files, layout[0] * layout[1])
    shape = None
    for f in files:
        s = frame_header_shape(f)
        if shape is None:
            shape, first = s, f
        elif s != shape:
            raise FrameError(f"{f}: frame is {s[1]} x {s[0]} pixels, {first.name} is {shape[1]} x {shape[0]}")
    return HDRDirectory(path=path, files=tuple(files), layout=layout, frame_shape=shape)


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
    try:
        pixels, attrs = read_exr(path)
    except ImageError as exc:
        raise FrameError(str(exc)) from None
    names = attrs["channels"]
    if "G" in names:
        image = pixels[:, :, names.index("G")]
    elif len(names) == 1:
        image = pixels[:, :, 0]
    else:
        raise FrameError(f"{path}: channels {names}: need a 'G' channel or a single channel")
    if shape is not None and image.shape != tuple(shape):
        raise FrameError(f"{path}: frame is {image.shape[1]} x {image.shape[0]} pixels, expected {shape[1]} x {shape[0]}")
    return image


def chunks(items: Sequence, size: int) -> list[Sequence]:
    """Consecutive slices of ``items`` of at most ``size``."""
    return [items[i:i + size] for i in range(0, len(items), size)]


@contextmanager
def beam_executor(executor: Executor | None, workers: int | None) -> Iterator[Executor | None]:
    """The executor to use: the caller's, else a process pool of ``workers`` (None: all cores).

    ``workers == 1`` runs in this process (yields None).
    """
    if executor is not None:
        yield executor
        return
    workers = workers or os.cpu_count() or 1
    if workers == 1:
        yield None
        return
    with ProcessPoolExecutor(max_workers=workers) as pool:
        yield pool


def run_chunks(function: Callable, tasks: Iterable[tuple], executor: Executor | None,
               in_flight: int = 8, progress: Callable[[int], None] | None = None) -> Iterator:
    """``function(*task)`` for every task, in order, at most ``in_flight`` submitted at once.

    Each task's first item is a sequence of beams; ``progress(len(beams))`` is called
    as each finishes. With ``executor`` None everything runs here.
    """
    if executor is None:
        for task in tasks:
            result = function(*task)
            if progress:
                progress(len(task[0]))
            yield result
        return
    pending: deque = deque()
    for task in tasks:
        pending.append((len(task[0]), executor.submit(function, *task)))
        if len(pending) >= in_flight:
            n, future = pending.popleft()
            yield future.result()
            if progress:
                progress(n)
    while pending:
        n, future = pending.popleft()
        yield future.result()
        if progress:
            progress(n)
