"""Stage manifests and content fingerprints (DESIGN.md sec. 3).

Every stage directory holds a ``manifest.json``: the stage's name, ilt's version, the
parameters, the inputs with their fingerprints and every output file with its sha256,
written last (:func:`write_manifest`). A later run recognises the directory as the
stage's own by it, and ``ilt status --verify`` re-hashes the files against it. How the
directory is written whole is :mod:`ilt.io.staged`; single files, :mod:`ilt.io.atomic`.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from ilt import __version__
from ilt.io.atomic import atomic_path

MANIFEST = "manifest.json"
#: the run record ``ilt run`` keeps beside a stage's manifest (:mod:`ilt.io.stage`)
RECORD = ".stage.json"
#: a capture's journal (:mod:`ilt.capture.log`): the raw data it names is never replaced
LOG_NAME = "capture.jsonl"


class StageError(ValueError):
    """A stage directory that cannot be written or read as asked."""


def fingerprint_file(path: str | os.PathLike, chunk: int = 1 << 22) -> str:
    """``sha256:<hex>`` of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return "sha256:" + h.hexdigest()


def fingerprint_array(a: np.ndarray) -> str:
    """``sha256:<hex>`` of an array's dtype, shape and bytes (C order)."""
    h = hashlib.sha256()
    h.update(f"{a.dtype.str}{a.shape}".encode())
    h.update(np.ascontiguousarray(a).data)
    return "sha256:" + h.hexdigest()


def fingerprint_npy(path: str | os.PathLike, chunk: int = 1 << 22) -> tuple[str, str]:
    """A C-order ``.npy`` file's :func:`fingerprint_file` and its array's
    :func:`fingerprint_array`, from one read of its bytes (the data hashed twice as it
    passes, the header once). Raises ValueError for a Fortran-order or object array."""
    file_hash, array_hash = hashlib.sha256(), hashlib.sha256()
    with open(path, "rb") as f:
        read_header = {(1, 0): np.lib.format.read_array_header_1_0,
                       (2, 0): np.lib.format.read_array_header_2_0}.get(np.lib.format.read_magic(f))
        shape, fortran, dtype = read_header(f) if read_header else ((), True, None)
        if fortran or dtype.hasobject:
            raise ValueError(f"{path}: not a C-order .npy array of numbers (format 1.0 or 2.0)")
        header = f.tell()
        f.seek(0)
        file_hash.update(f.read(header))
        array_hash.update(f"{dtype.str}{shape}".encode())
        while block := f.read(chunk):
            file_hash.update(block)
            array_hash.update(block)
    return "sha256:" + file_hash.hexdigest(), "sha256:" + array_hash.hexdigest()


def write_json(path: str | os.PathLike, data: dict) -> Path:
    """Write JSON atomically (temporary file in the same directory, fsync, rename)."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, default=_json_default) + "\n")
    return Path(path)


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot write {type(obj).__name__} to JSON")


def save_npy(path: str | os.PathLike, array: np.ndarray) -> Path:
    """``np.save`` atomically (no pickles)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, array, allow_pickle=False)
    return Path(path)


def write_manifest(
    directory: str | os.PathLike,
    stage: str,
    parameters: dict,
    inputs: dict[str, str] | None = None,
    extra: dict | None = None,
    hashed: dict[str, str] | None = None,
) -> Path:
    """Write ``directory/manifest.json``: stage, ilt version, parameters, inputs with
    fingerprints, and the fingerprint of every file written in the directory.
    ``hashed``: the :func:`fingerprint_file` of files the caller hashed already (by
    their path relative to ``directory``), not read again."""
    directory = Path(directory)
    hashed = hashed or {}
    outputs = {}
    for p in sorted(directory.rglob("*")):
        if p.is_file() and p.name != MANIFEST and not p.name.startswith("."):
            name = str(p.relative_to(directory))
            outputs[name] = hashed.get(name) or fingerprint_file(p)
    data = {
        "stage": stage,
        "ilt_version": __version__,
        "parameters": parameters,
        "inputs": inputs or {},
        "outputs": outputs,
    }
    if extra:
        data.update(extra)
    return write_json(directory / MANIFEST, data)


def read_manifest(directory: str | os.PathLike) -> dict:
    path = Path(directory) / MANIFEST
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise StageError(f"{path}: no manifest (not a stage directory written by ilt?)") from None
    except json.JSONDecodeError as exc:
        raise StageError(f"{path}: not valid JSON ({exc})") from None
