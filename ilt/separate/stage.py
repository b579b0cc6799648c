"""The separate directory: ``ilt separate PHOTOS -o OUT`` (Nayar et al. 2006, :mod:`ilt.separate.nayar`).

Writes ``direct.exr`` and ``global.exr`` (EXR inputs; the first photo's channels and pixel
attributes) or ``direct.npy`` and ``global.npy`` (.npy inputs), ``preview.png`` (the first
pattern photo, direct and global on one grey scale) and ``manifest.json`` (the photos by
their hashes, ``black``, ``patterns``).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ilt.io.exr import read_exr, write_exr
from ilt.io.manifest import fingerprint_file, save_npy, write_manifest
from ilt.io.preview import bounce_panel
from ilt.io.staged import staged_directory

from .nayar import direct_global

log = logging.getLogger(__name__)

#: header attributes of the first photo carried to the outputs (where its pixels lie)
_CARRIED = ("ilt:pixel_origin", "ilt:pixel_scale")


class SeparateError(ValueError):
    """Pattern photos that cannot be separated; the message names the file."""


def _read(path: Path) -> tuple[np.ndarray, dict]:
    if not path.is_file():
        raise SeparateError(f"{path}: no such file")
    if path.suffix.lower() == ".exr":
        try:
            return read_exr(path)
        except (OSError, ValueError) as exc:
            raise SeparateError(str(exc)) from None
    if path.suffix.lower() == ".npy":
        try:
            values = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise SeparateError(f"{path}: not a readable .npy array ({exc})") from None
        if values.dtype.kind not in "fiu":
            raise SeparateError(f"{path}: dtype {values.dtype} is not numeric")
        return values, {}
    raise SeparateError(f"{path}: unsupported input type '{path.suffix}' (use .exr frames or .npy arrays)")


def separate(photos: list[str | os.PathLike], out: str | os.PathLike, black: float = 0.0,
             force: bool = False) -> dict:
    """Split the scene under K >= 2 shifted half-on patterns (``photos``) into direct and global light.

    Every photo is read and checked (one kind, one shape, finite) before anything is
    written; ``out`` is written to a temporary directory and renamed into place.
    Returns a JSON-ready summary.
    """
    paths = [Path(p) for p in photos]
    if len(paths) < 2:
        raise SeparateError(f"need at least 2 pattern photos (shifted so that every point is lit in one and dark "
                            f"in another), got {len(paths)}")
    if len({p.resolve() for p in paths}) != len(paths):
        raise SeparateError("a pattern photo is given twice: its pixels would count as two patterns")
    if not 0.0 <= black < 1.0:
        raise SeparateError(f"--black must be in [0, 1), got {black}")
    out = Path(out)
    if out.resolve() in {p.resolve().parent for p in paths} or any(out.resolve() == p.resolve() for p in paths):
        raise SeparateError(f"{out}: is where the pattern photos are; give -o a new directory")
    kinds = {p.suffix.lower() for p in paths}
    if len(kinds) != 1:
        raise SeparateError(f"pattern photos of mixed kinds {sorted(kinds)}: give all .exr or all .npy")
    first, attributes = _read(paths[0])
    stack = np.empty((len(paths), *first.shape))
    stack[0] = first
    for k, path in enumerate(paths[1:], start=1):
        values, _ = _read(path)
        if values.shape != first.shape:
            raise SeparateError(f"{path}: shape {values.shape} differs from {paths[0]}'s {first.shape}")
        stack[k] = values
    for k, path in enumerate(paths):
        if not np.isfinite(stack[k]).all():
            raise SeparateError(f"{path}: holds a value that is not finite")
    direct, global_ = direct_global(stack, black)
    exr = kinds == {".exr"}
    with staged_directory(out, force=force) as tmp:
        if exr:
            channels = attributes.get("channels")
            carried = {k: attributes[k] for k in _CARRIED if k in attributes}
            for name, image in (("direct", direct), ("global", global_)):
                write_exr(tmp / f"{name}.exr", image, channels=channels,
                          attributes={"ilt:quantity": name, "ilt:method": "Nayar et al. 2006, max/min", **carried})
        else:
            save_npy(tmp / "direct.npy", direct)
            save_npy(tmp / "global.npy", global_)
        bounce_panel(tmp / "preview.png", {"pattern 1": _plane(first), "direct": _plane(direct),
                                           "global": _plane(global_)})
        write_manifest(tmp, "separate", {"black": black, "patterns": len(paths)},
                       inputs={str(p): fingerprint_file(p) for p in paths})
    total = float(np.sum(direct + global_))
    share = float(np.sum(direct)) / total if total > 0 else 0.0
    log.info("%d pattern photos -> %s: direct %.3g of the light, global %.3g", len(paths), out, share, 1 - share)
    return {"output": str(out), "patterns": len(paths), "black": black, "direct_share": share}


def _plane(values: np.ndarray) -> np.ndarray:
    """A 2D view for the preview: the first channel of a frame, a 1 x m strip of a vector."""
    values = np.asarray(values)
    if values.ndim == 1:
        return values[None, :]
    return values[..., 0] if values.ndim == 3 else values
