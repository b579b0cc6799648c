"""The decompose stage: photos (EXR frames or sample vectors) to n-bounce images.

Operators are built once per ISF and cached on disk, keyed by the fingerprint of T,
so decomposing the next photo of the same scene costs only the solves.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import scipy.sparse

from ilt.decompose.fullres import full_resolution, photo_noise_models
from ilt.decompose.noise import MAX_M, bounce_sigma, draws_for, entry_noise, photo_model, photo_noise
from ilt.io.exr import ImageError, read_exr, write_exr
from ilt.io.frames import FrameError, PixelMapping
from ilt.io.manifest import (
    MANIFEST,
    StageError,
    fingerprint_array,
    fingerprint_file,
    read_manifest,
    save_npy,
    write_json,
    write_manifest,
)
from ilt.io.preview import bounce_panel
from ilt.io.staged import staged_directory
from ilt.isf.cells import integrate, mosaic
from ilt.isf.directory import ISF
from ilt.isf.fine import FINE_DIR, FineError, FineOperator, load_fine
from ilt.isf.lambertian import LAMBERTIAN_FILE, read_lambertian
from ilt.isf.layout import sample_frame, splat, vector_to_image
from ilt.isf.noise import NOISE_FILE, read_entry_variance, read_noise
from ilt.isf.fold_transfer import FILE as FOLD_FILE, apply_corrections
from ilt.isf.spill import SPILL_FILE, Unmixing
from ilt.transport.compressed import grid_points
from ilt.transport.diagnostics import decomposition_diagnostics, operator_diagnostics
from ilt.transport.operators import (
    CancellationOperator,
    bounce_images,
    cancellation_operator,
)
from ilt.transport.regularise import diagonal_raise, raise_diagonal, regularise_isf
from ilt.transport.scan import TransportError, scan_isf
from ilt.transport.solvers import build_operator, choose_solver, estimate_noise

log = logging.getLogger(__name__)

_CACHE_ARRAYS = ("factors", "perm", "t1_unit", "column_norms")


class NotLambertian(ValueError):
    """T fails a check that the cancellation theorem needs (reciprocity, spectral radius < 1)."""


class InputError(ValueError):
    """A photo that cannot be decomposed with the ISF at hand; names the file."""


def default_cache_dir() -> Path:
    """``$ILT_CACHE_DIR``, else ``$XDG_CACHE_HOME/ilt``, else ``~/.cache/ilt``."""
    if os.environ.get("ILT_CACHE_DIR"):
        return Path(os.environ["ILT_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "ilt"


def load_operator(
    T: np.ndarray,
    cache_dir: Path | None,
    solver: str = "auto",
    noise: float | None = None,
    layout: tuple[int, int] | None = None,
    regularise: bool | None = None,
    beams: np.ndarray | None = None,
    points: np.ndarray | None = None,
    fingerprint: str | None = None,
    executor=None,
    noise_source: str = "given",
    cells: np.ndarray | None = None,
    variance: np.ndarray | None = None,
):
    """``C1`` for ``T`` and its diagnostics; dense operators come from the cache when
    the same T (and regularisation) was seen before.

    ``solver``: auto, dense, mixed, blocks, series or compressed (:mod:`ilt.transport.solvers`).
    ``noise``: sigma of T relative to its unit columns (also the floor below which
    blocks and series drop entries, and compressed's tolerance); None measures it from
    T's negative entries when it can. ``points`` (m, 2): where each sample is seen in
    the camera frame, which compressed orders its tree by (points near in the image are
    near in the scene, far more often than neighbours on the plan's grid are: the box's
    top rank at m = 3072 is 216 by pixels, 521 by grid); without them, ``layout`` and
    ``beams`` (plan beam of each row) place the samples on the plan's grid.
    ``regularise``: denoise T first (:mod:`ilt.transport.regularise`; needs the noise, and
    ``cells`` or the plan's full grid ``layout``); None (auto): when it can and the
    dense copies fit (:func:`auto_regularise`), else T as measured and why in the notes.
    ``cells`` (H, W): the ISF's cell labels; the filter then smooths along the cells that
    share a pixel edge instead of the plan's grid, on the light per pixel of each cell
    (found here, only when T is filtered), at the width of least estimated risk
    (:func:`~ilt.transport.regularise.choose_width`) given ``variance`` (m, m), each
    unit-column entry's (build-isf's ``T_var.npy``), else ``noise`` squared. Returns the
    operator and a JSON-ready dict of diagnostics with
    ``solver``, ``solver_reason``, ``noise``, ``cached`` and ``fingerprint`` (and the
    ``series`` or ``compressed`` figures of those solvers, build included).
    ``fingerprint``: T's :func:`~ilt.io.manifest.fingerprint_array` when the caller has it.
    ``executor``: a cluster's (:func:`ilt.parallel.cluster.executor_for`), where ``compressed``
    compresses its blocks; the other solvers ignore it.
    """
    # "-lut": the factors' layout (those of T's transpose, :class:`ilt.transport.operators.CancellationOperator`);
    # entries ilt wrote before, the factors of T itself, are not read as such
    m = T.shape[0]
    key = (fingerprint or fingerprint_array(np.asarray(T))).split(":", 1)[1] + "-lut"
    # one pass (scan_isf) checks T and measures its column norms and negative entries
    # (the noise): the IsfMatrix handed to the solver choice, the build and the
    # diagnostics. Not made for a dense operator with the noise given and T not to be
    # regularised, which may be in the cache: that reads T only for its fingerprint (a
    # cache miss scans it to factorise)
    has_neighbours = cells is not None or (layout is not None and layout[0] * layout[1] == m)
    # by default only with the noise known (build-isf's, from the frames, or given): negative
    # entries of T are not all noise (a T of no physical scene has them too)
    why_not = None if regularise else "--no-regularise" if regularise is False else \
        auto_regularise(m, noise, has_neighbours)
    if noise is None or why_not is None or solver != "dense":
        T = scan_isf(T)
    measured = estimate_noise(T) if noise is None else noise
    notes = {
        "noise": measured,
        "noise_source": noise_source if noise is not None else
        ("measured from negative entries of T" if measured is not None else "unknown (give --noise)"),
    }
    if regularise and measured is None:
        raise TransportError("regularising needs the noise level of T and T has no negative entries "
                             "to measure it from: give --noise")
    if regularise and not has_neighbours:
        raise TransportError(f"regularising needs the ISF's cells (cells.exr) or the plan's full grid layout; "
                             f"this ISF has no cells and layout {layout} for m = {m} (beams were dropped?)")
    if why_not is not None:
        if noise is None and measured is not None and why_not.startswith("its noise"):
            why_not = ("its noise is only estimated from its negative entries, which need not all be noise "
                       "(--regularise uses it; --noise gives it)")
        notes.update(regularisation=f"T left as measured: {why_not}", regularisation_width=0.0)
    else:
        neighbours, areas = (None, None) if cells is None else (_neighbours(cells), _cell_areas(cells, m))
        regularised, reg = regularise_isf(T, None if neighbours is not None else layout, measured, width=None,
                                          pairs=neighbours, variance=variance, areas=areas)
        T = scan_isf(regularised)  # another matrix: scanned once more
        along = "the cells' neighbours" if neighbours is not None else "the plan's grid"
        notes.update(regularisation=f"{reg.describe()}, along {along}", regularisation_width=reg.width)
        if reg.risks is not None:   # each width's estimated risk (relative to T's noise), what chose it
            notes.update(regularisation_risks=[{k: (bool(v) if k == "past_the_noise" else float(v))
                                                for k, v in row.items()} for row in reg.risks])
        key += f"-reg{reg.width:g}-{measured:.3e}" + ("-cells" if neighbours is not None else "") + \
            ("-px" if reg.per_pixel else "")
    name, reason = choose_solver(T, measured) if solver == "auto" else (solver, f"asked for {solver}")
    notes.update(fingerprint="sha256:" + key.split("-")[0])
    if executor is not None and name != "compressed":
        log.info("the %s solver runs in this process: the cluster (--scheduler) compresses T's blocks for the "
                 "compressed solver only", name)
    if name != "dense":
        log.info("building the %s operator (m = %d): %s", name, m, reason)
        if points is None and name == "compressed" and (layout is None or min(layout) == 1):
            log.warning("no sample positions (samples.csv) and no 2D plan: the compressed solver orders the "
                        "tree by sample index, whose blocks can have several times the rank of an order by "
                        "pixels (972 against 143 at m = 12288); put samples.csv beside T.npy")
        points = grid_points(layout, m, beams) if points is None else points
        op, why = build_operator(T, name, measured, reason, points=points, executor=executor)
        figures = {op.solver: op.figures} if op.solver in ("series", "compressed") else {}
        return op, {**operator_diagnostics(T, op), **notes, "solver": op.solver, "solver_reason": why,
                    "rcond": op.rcond, "cached": False, **figures}
    notes.update(solver="dense", solver_reason=reason)
    entry = cache_dir / "operators" / key if cache_dir is not None else None
    if entry is not None and (entry / "diagnostics.json").exists():
        try:
            op, diagnostics = _read_cached_operator(entry, m)
            log.info("operators for T %s… read from the cache %s", key[:12], entry)
            return op, {**diagnostics, **notes, "cached": True}
        except (OSError, ValueError, KeyError) as exc:
            log.info("ignoring the operator cache %s (%s); rebuilding it", entry, exc)
    log.info("factorising T (m = %d)", m)
    T = scan_isf(T)
    op = cancellation_operator(T)
    diagnostics = {**operator_diagnostics(T, op), "rcond": op.rcond}
    if entry is not None:
        try:
            _remove_unchecked_entry(entry)
            with staged_directory(entry, force=True) as tmp:
                for name in _CACHE_ARRAYS:
                    save_npy(tmp / f"{name}.npy", getattr(op, name))
                write_json(tmp / "diagnostics.json", diagnostics)
                write_manifest(tmp, "operators", {"m": m})  # each file's sha256, checked on load
        except (OSError, StageError) as exc:
            log.warning("could not cache the operators in %s (%s)", entry, exc)
    return op, {**diagnostics, **notes, "cached": False}


def _remove_unchecked_entry(entry: Path) -> None:
    """Remove a cache entry an older ilt wrote without manifest.json (so without the
    sha256 of its files) when it holds only the cache's own files: it cannot be
    checked, and a directory without a manifest is not one ilt replaces."""
    own = {f"{name}.npy" for name in _CACHE_ARRAYS} | {"diagnostics.json"}
    if not entry.is_dir() or (entry / MANIFEST).exists() or {p.name for p in entry.iterdir()} - own:
        return
    for p in entry.iterdir():
        p.unlink()
    entry.rmdir()


class _HashingReader:
    """A binary file read through sha256: ``np.load`` reads it in chunks (it is no real
    file to numpy), so the array and its hash come from one read of the bytes."""

    def __init__(self, f):
        self._f, self.hash = f, hashlib.sha256()

    def read(self, n=-1):
        data = self._f.read(n)
        self.hash.update(data)
        return data

    def seek(self, *args):  # np.load peeks at the magic string, then seeks back to the start
        self.hash = hashlib.sha256()
        return self._f.seek(*args)

    def tell(self):
        return self._f.tell()


def _read_cached_operator(entry: Path, m: int) -> tuple[CancellationOperator, dict]:
    """The operator in a cache entry, every file checked against the sha256 its
    manifest.json recorded and every array against the shape of an (m, m) T.
    ValueError (or OSError, KeyError) says what is wrong; the caller rebuilds."""
    outputs = read_manifest(entry)["outputs"]
    arrays = {}
    for name in _CACHE_ARRAYS:
        with open(entry / f"{name}.npy", "rb") as f:
            reader = _HashingReader(f)
            arrays[name] = np.load(reader, allow_pickle=False)
            reader.read()  # bytes after the array are part of the file too
        if "sha256:" + reader.hash.hexdigest() != outputs.get(f"{name}.npy"):
            raise ValueError(f"{name}.npy differs from the sha256 its manifest.json recorded")
        shape = (m, m) if name == "factors" else (m,)
        if arrays[name].shape != shape:
            raise ValueError(f"{name}.npy has shape {arrays[name].shape}, T needs {shape}")
    text = (entry / "diagnostics.json").read_bytes()
    if "sha256:" + hashlib.sha256(text).hexdigest() != outputs.get("diagnostics.json"):
        raise ValueError("diagnostics.json differs from the sha256 its manifest.json recorded")
    diagnostics = json.loads(text)
    op = CancellationOperator(
        factors=np.asfortranarray(arrays["factors"]), perm=arrays["perm"], t1_unit=arrays["t1_unit"],
        column_norms=arrays["column_norms"], rcond=diagnostics["rcond"],
    )
    return op, diagnostics


@dataclass(frozen=True)
class Photo:
    """One input: its sample vector(s) and how to show results.

    values : (m,) or (m, k) float64; channels : names of the k columns (or None);
    frame : True when it came from a camera frame (results are also splatted back);
    image : the frame itself, (H, W, k) float32 (None for sample vectors);
    saturated : (H, W) bool pixels its merge found saturated in every exposure (None: none known).
    """

    name: str
    path: Path
    values: np.ndarray
    channels: list[str] | None
    frame: bool
    image: np.ndarray | None = None
    saturated: np.ndarray | None = None


def _saturated_mask(path: Path, shape) -> np.ndarray | None:
    """The ``<stem>.saturated.png`` that ``ilt merge`` writes beside a photo, as (H, W) bool."""
    import cv2

    mask_path = path.with_suffix(".saturated.png")
    if not mask_path.exists():
        return None
    mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
    if mask is None or mask.shape != tuple(shape):
        raise InputError(f"{mask_path}: not a {shape[1]} x {shape[0]} mask of {path.name}'s saturated pixels")
    return mask > 0


def read_photo(path: str | os.PathLike, isf: ISF) -> Photo:
    """Read an EXR frame or a ``.npy`` of sample vectors, shape (m,) or (m, k).

    A frame is integrated over the ISF's cells when it has them (``cells.exr``, the
    same cells T was built on), else read at the ISF's sample pixels. It must be on the
    ISF's frame grid: same size and, when its header says, the same pixel mapping (a
    photo merged like the beam frames); a header without a mapping is not checked.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        try:
            values = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise InputError(f"{path}: not a readable .npy array ({exc})") from None
        if values.ndim not in (1, 2) or values.shape[0] != isf.m:
            raise InputError(
                f"{path}: shape {values.shape} does not match the ISF's m = {isf.m} samples "
                f"(expected ({isf.m},) or ({isf.m}, k))"
            )
        if not np.issubdtype(values.dtype, np.number):
            raise InputError(f"{path}: dtype {values.dtype} is not numeric")
        values = values.astype(np.float64)
        channels, frame, image, saturated = None, False, None, None
    elif suffix == ".exr":
        if isf.samples is None:
            raise InputError(f"{path}: an EXR photo needs the ISF's samples.csv to know which pixels to read")
        try:
            image, attrs = read_exr(path)
        except ImageError as exc:
            raise InputError(str(exc)) from None
        if isf.frame_shape is not None and tuple(image.shape[:2]) != tuple(isf.frame_shape):
            raise InputError(
                f"{path}: frame is {image.shape[1]} x {image.shape[0]} pixels, the ISF was captured at "
                f"{isf.frame_shape[1]} x {isf.frame_shape[0]}"
            )
        if isf.cells is not None and image.shape[:2] != isf.cells.shape:
            raise InputError(f"{path}: frame is {image.shape[1]} x {image.shape[0]} pixels, the ISF's cells "
                             f"are {isf.cells.shape[1]} x {isf.cells.shape[0]}")
        try:
            own = PixelMapping.from_attributes(attrs, path)
        except FrameError as exc:
            raise InputError(str(exc)) from None
        if own is not None and own != isf.mapping:
            raise InputError(f"{path}: pixel mapping {own.as_dict()} differs from the ISF's "
                             f"{isf.mapping.as_dict()}; decompose photos on the grid of the beam frames")
        try:
            if isf.cells is not None:
                values = integrate(image, isf.cells, isf.m)
            else:
                values = sample_frame(image, isf.grid_samples).astype(np.float64)
        except ValueError as exc:
            raise InputError(f"{path}: {exc}") from None
        channels = list(attrs.get("channels", []))
        if values.ndim == 2 and values.shape[1] == 1:
            values = values[:, 0]
        frame = True
        saturated = _saturated_mask(path, image.shape[:2])
    else:
        raise InputError(f"{path}: unsupported input type '{suffix}' (use .exr frames or .npy sample vectors)")
    if not np.all(np.isfinite(values)):
        i = int(np.argwhere(~np.isfinite(values))[0][0])
        raise InputError(f"{path}: sample {i} is not finite")
    return Photo(name=path.stem, path=path, values=values, channels=channels or None, frame=frame, image=image,
                 saturated=saturated if saturated is not None and saturated.any() else None)


def _images(values: np.ndarray, isf: ISF, frame: bool) -> dict[str, np.ndarray]:
    """The picture(s) of a sample vector: ``layout`` always, ``frame`` for frame inputs
    (a mosaic of cells, each painted with its value per pixel, when the ISF has cells;
    else the values splatted at the sample pixels)."""
    out = {"layout": vector_to_image(values, isf.layout, isf.beams)}
    if frame:
        out["frame"] = (mosaic(values, isf.cells) if isf.cells is not None
                        else splat(values, isf.grid_samples, isf.frame_shape))
    return out


def write_decomposition(
    directory: Path, photo: Photo, isf: ISF, decomposition, diagnostics: dict, fine: FineOperator | None = None,
    t1: np.ndarray | None = None, weights: np.ndarray | None = None,
) -> None:
    """Fill ``directory`` with one photo's results (see docs/formats.md): with a fine
    operator (and a frame input), the full-resolution images at the top and the
    sample-level ones in ``samples/``; else the sample-level ones only."""
    save_npy(directory / "bounces.npy", decomposition.bounces)
    save_npy(directory / "residual.npy", decomposition.residual)
    samples = directory / "samples"
    samples.mkdir()
    named = {"photo": photo.values}
    named.update({f"bounce-{n}": b for n, b in enumerate(decomposition.bounces, start=1)})
    named["indirect"] = decomposition.indirect
    named["residual"] = decomposition.residual
    channels = photo.channels
    verdict = diagnostics.get("lambertian")
    marked = {} if verdict is None else {"ilt:lambertian": str(verdict["verdict"]),
                                         "ilt:lambertian_accepted": int(bool(verdict.get("accepted")))}
    for name, values in named.items():
        for kind, image in _images(values, isf, photo.frame).items():
            suffix = "" if kind == "layout" else ".frame"
            attributes = {"ilt:source": str(photo.path.name), "ilt:quantity": name, **marked}
            if kind == "frame":
                attributes.update(isf.mapping.attributes())
            write_exr(samples / f"{name}{suffix}.exr", image, channels=channels, attributes=attributes)
    first = (lambda v: v) if photo.values.ndim == 1 else (lambda v: v[:, 0])
    panels = {"photo": first(photo.values)}
    panels.update({f"L{n}": first(b) for n, b in enumerate(decomposition.bounces, start=1)})
    panels["indirect"] = first(decomposition.indirect)
    bounce_panel(samples / "preview.png", {k: vector_to_image(v, isf.layout, isf.beams) for k, v in panels.items()})
    if fine is not None and photo.image is not None:
        bound = {}
        # the photo's own noise (measured when needed) widens the bound: it stays in bounce 1
        images = full_resolution(fine, photo.image, decomposition, t1, photo.saturated, weights, report=bound,
                                 photo_noise=photo_noise_models)
        if "full_resolution" in diagnostics:
            # the pixels whose cell's indirect light was more than the photo held there (ilt.decompose.fullres.PhotoBound)
            diagnostics["full_resolution"].update(bound)
        for name, image in images.items():
            attributes = {"ilt:source": str(photo.path.name), "ilt:quantity": name, **isf.mapping.attributes(),
                          **marked}
            write_exr(directory / f"{name}.exr", image, channels=["Y"] if name == "coverage" else channels,
                      attributes=attributes)
        shown = {"photo": photo.image[:, :, 0]}
        shown.update({k.replace("-", " "): images[k][:, :, 0] for k in images if k.startswith("bounce-")
                      and int(k[7:]) <= PREVIEW_BOUNCES})
        shown["indirect"] = images["indirect"][:, :, 0]
        bounce_panel(directory / "preview.png", shown)
    else:
        shutil.copyfile(samples / "preview.png", directory / "preview.png")
    write_json(directory / "summary.json", diagnostics)


#: full-resolution bounce images drawn in preview.png (all are written as EXR)
PREVIEW_BOUNCES = 3


def _full_resolution_summary(photo: Photo, fine: FineOperator | None, why: str) -> dict:
    if not photo.frame:
        return {"written": False, "reason": "a sample vector has no pixels"}
    if fine is None:
        return {"written": False, "reason": why}
    saturated = int(photo.saturated.sum()) if photo.saturated is not None else 0
    covered = fine.geometry.inside.size - (int(photo.saturated.ravel()[fine.geometry.inside].sum()) if saturated else 0)
    rim = fine.rim[0]
    rim_count = rim.size - (int(photo.saturated.ravel()[rim].sum()) if saturated else 0)
    # the cells the build kept flat take the limited slope of their neighbours' means (ilt/isf/slopes.py)
    flat = int(fine.flat_cells.sum()) if fine.degree >= 1 else fine.geometry.m
    return {"written": True, "degree": fine.degree, "pixels": int(photo.image.shape[0] * photo.image.shape[1]),
            "coverage": covered / (photo.image.shape[0] * photo.image.shape[1]),
            "rim": rim_count / (photo.image.shape[0] * photo.image.shape[1]), "saturated_pixels": saturated,
            "flat_cells": flat, "flat_cell_slopes": "neighbours" if fine.degree >= 1 else "none"}


def decompose(
    isf: ISF,
    inputs: list[str | os.PathLike],
    out: str | os.PathLike,
    n_bounces: int = 8,
    tol: float = 0.0,
    cache_dir: Path | None = None,
    force: bool = False,
    solver: str = "auto",
    noise: float | None = None,
    regularise: bool | None = None,
    samples_only: bool = False,
    executor=None,
    spill: bool = True,
    accept_non_lambertian: bool = False,
    shown_as: str | os.PathLike | None = None,
    fold_transfer: bool = True,
) -> list[dict]:
    """Decompose every input into ``out/<stem>/``; returns one summary per input.

    A T that the reciprocity check of build-isf judged "not lambertian"
    (``lambertian.json``, :mod:`ilt.isf.lambertian`) or whose bounce series diverges
    (spectral radius of ``A = I - C1`` >= 1) is refused (:class:`NotLambertian`, nothing
    written) unless ``accept_non_lambertian``; then every summary.json and EXR records
    the verdict.

    ``spill``: when the ISF measured its spots' direct light in other cells
    (``spill.npz``, :mod:`ilt.isf.spill`), split ``(I + Q)^-1 p`` with the operator of
    ``(I + Q)^-1 T`` and mix the bounces back (``False``: the paper's diagonal ``T1``).

    ``fold_transfer``: when the ISF measured the light its cells send across the scene's
    folds spread over each cell (``fold_transfer.npz``, :mod:`ilt.isf.fold_transfer`), add it
    to that T (``False``: T as measured, each cell's light sent from its spot).

    ``solver``, ``noise`` and ``regularise`` choose how ``C1`` is built (see
    :func:`load_operator`). EXR photos are also split at full resolution when the ISF
    has a fine operator (:mod:`ilt.isf.fine`), unless ``samples_only``; saturated
    pixels (``<stem>.saturated.png`` beside the photo, as ``ilt merge`` writes it) are
    left out of the full-resolution images and counted.

    All inputs are read and checked before anything is written, so a bad input leaves
    no output behind. Each ``out/<stem>`` is written to a temporary directory and
    renamed into place on its own: a failure leaves the photos before it complete, and
    a run again skips those (a log line each) whose ``out/<stem>`` records the same
    photo, T and parameters; an ``out/<stem>`` made otherwise needs ``force``.
    ``executor``: where the compressed solver compresses T's blocks (:func:`load_operator`);
    no output depends on it. ``shown_as``: the directory the log lines name instead of
    ``out`` (the final one, when ``out`` is a temporary that will be renamed to it).

    Each bounce sample's noise is measured (:mod:`ilt.decompose.noise`) and the negatives
    and noise of the bounces are judged by it (:func:`decomposition_diagnostics`): a
    warning per problem, an INFO line when all is well.
    """
    photos = [read_photo(p, isf) for p in inputs]
    stems = [p.name for p in photos]
    if len(set(stems)) != len(stems):
        raise InputError(f"two inputs share a name ({stems}); their results would collide in {out}")
    out = Path(out)
    shown = Path(shown_as) if shown_as is not None else out
    fingerprint = fingerprint_array(np.asarray(isf.T))
    parameters = decompose_parameters(isf, n_bounces, tol, solver, noise, regularise, samples_only, spill,
                                      accept_non_lambertian, fold_transfer)
    verdict = _lambertian_verdict(isf, accept_non_lambertian)
    hashes = {photo.name: fingerprint_file(photo.path) for photo in photos}   # each photo read once
    done = {}
    for photo in photos:
        if (out / photo.name).exists() and not force:
            wanted = {hashes[photo.name], fingerprint}
            previous = previous_result(out / photo.name, parameters, wanted)
            if previous is None:
                raise InputError(f"{out / photo.name} exists and was not made from {photo.path} with these "
                                 "options and this ISF; use --force to replace it")
            done[photo.name] = previous
    todo = [p for p in photos if p.name not in done]
    for photo in photos:
        if photo.name in done:
            log.info("%s: %s is already decomposed with these options; kept", photo.path, shown / photo.name)
    if not todo:
        return [done[p.name] for p in photos]
    fine, why = None, "--samples-only"
    if not samples_only and any(p.frame for p in todo):
        try:
            fine, why = load_fine(isf, fingerprint)
        except FineError as exc:
            raise InputError(str(exc)) from None
        if fine is None:
            log.info("%s", why)
    noise_source = "given"
    if noise is None:   # the frames' noise, carried into T by build-isf (ilt.isf.noise), when it measured it
        noise, noise_source = frames_noise(isf.path)
    with contextlib.ExitStack() as stack:
        spilled = _unmixing(isf, spill)
        T_op = isf.T if spilled is None else _unmixed_T(isf, spilled, cache_dir, stack)
        folded = _fold_corrections(isf, fold_transfer)
        if folded is not None:
            T_op = _folded_T(T_op, folded, spilled is not None, cache_dir, stack)
        variance = read_entry_variance(Path(isf.path).parent, isf.m) if noise_source != "given" else None
        T_op, diagonal = _debiased_diagonal(T_op, variance, spilled is not None or folded is not None, cache_dir,
                                            stack)
        try:
            op, op_diag = load_operator(T_op, cache_dir, solver, noise, isf.layout, regularise, isf.beams,
                                        isf.samples,
                                        fingerprint=fingerprint if spilled is None and diagonal is None
                                        and folded is None else None,
                                        executor=executor, noise_source=noise_source,
                                        cells=isf.cells if regularise is not False else None,
                                        variance=variance)
        except TransportError as exc:
            raise TransportError(f"{isf.path}: {exc}") from None
        if diagonal is not None:
            op_diag["diagonal_debiased"] = diagonal
        if folded is not None:
            op_diag["fold_transfer"] = {"entries": int(len(folded[0])), "columns": int(np.unique(folded[1]).size)}
            log.info("%s: the light %d cells send across the scene's folds, spread over each cell (%s), is added "
                     "to T's %d columns before inverting", isf.path, len(folded[0]), FOLD_FILE,
                     int(np.unique(folded[1]).size))
        if spilled is not None:
            Q = spilled.Q
            op_diag["spill"] = {"entries": int(Q.nnz), "mean_share": float(Q.sum() / isf.m),
                                "operator_of": "(I + Q)^-1 T", "fingerprint": op_diag["fingerprint"]}
            log.info("%s: the spots' direct light in other cells (%d entries, %.2g of a spot's on average) "
                     "is taken out of T before inverting", isf.path, Q.nnz, Q.sum() / isf.m)
        verdict = _diverging(isf, op_diag, verdict, accept_non_lambertian)
        decompositions = {photo.name: _split(op, spilled, photo.values, n_bounces, tol) for photo in todo}
        sigmas = _bounce_noise(isf, spilled, todo, decompositions, op_diag, op_diag.get("regularisation_width", 0) > 0)
        for w in op_diag["warnings"]:
            moot = sigmas is not None and w == op_diag.get("condition_warning")
            log.log(logging.INFO if moot else logging.WARNING, "%s: %s%s", isf.path, w,
                    " (the bounces' own noise, measured below, is what it did)" if moot else "")
        created = not out.exists()
        summaries = {}
        try:
            for photo in todo:
                dec, weights = decompositions[photo.name]
                diag = decomposition_diagnostics(photo.values, dec, None if sigmas is None else sigmas[photo.name],
                                                 where=_sample_names(isf, photo),
                                                 unjudged=op_diag["bounce_noise"].get("reason", ""))
                for w in diag["warnings"]:
                    log.warning("%s: %s", photo.path, w)
                for note in diag["notes"]:
                    log.info("%s: %s", photo.path, note)
                full = fine is not None and photo.frame
                summary = {
                    "input": str(photo.path),
                    "input_fingerprint": hashes[photo.name],
                    "isf": str(isf.path),
                    "operators": op_diag,
                    "decomposition": diag,
                    "full_resolution": _full_resolution_summary(photo, fine, why),
                }
                if verdict is not None:
                    summary["lambertian"] = verdict
                if full and photo.saturated is not None:
                    log.warning("%s: %d saturated pixels (values are lower bounds) left out of the full-resolution "
                                "images (coverage 0, all residual); shorter exposures in its bracket keep them",
                                photo.path, int(photo.saturated.sum()))
                with staged_directory(out / photo.name, force=force) as tmp:
                    write_decomposition(tmp, photo, isf, dec, summary, fine if full else None, op.t1, weights)
                    write_manifest(
                        tmp, "decompose", parameters,
                        inputs={str(photo.path): summary["input_fingerprint"], str(isf.path): fingerprint},
                    )
                log.info("%s -> %s (%s)", photo.path, shown / photo.name, diag["stop_reason"])
                summaries[photo.name] = {**summary, "output": str(out / photo.name)}
        except BaseException:
            if created and out.exists() and not any(out.iterdir()):
                out.rmdir()
            raise
        del op, T_op   # before the stack removes a memory-mapped unmixed T
    return [done.get(p.name) or summaries[p.name] for p in photos]


def _bounce_noise(isf: ISF, spilled: Unmixing | None, photos: list[Photo], decompositions: dict,
                  op_diag: dict, regularise: bool) -> dict[str, np.ndarray] | None:
    """Each photo's bounce sigma (:func:`ilt.decompose.noise.bounce_sigma`), recorded in
    ``op_diag["bounce_noise"]``; None (and the reason, at INFO) when it cannot be measured."""
    if isf.m > MAX_M:
        why = f"m = {isf.m} > {MAX_M}: the draws would cost {draws_for(isf.m)} factorisations of T"
    else:
        T_std, source = entry_noise(isf, op_diag.get("noise"), op_diag.get("noise_source", "given"))
        why = None if T_std is not None else source
    if why is not None:
        log.info("%s: the bounces are not judged against their noise (%s)", isf.path, why)
        op_diag["bounce_noise"] = {"measured": False, "reason": why}
        return None
    start = time.perf_counter()
    T = np.asarray(isf.T, dtype=np.float64)
    model = photo_model(isf)   # read once for all photos
    stds = [photo_noise(isf, p.values, p.frame, model) if model else None for p in photos]
    try:
        sigmas = bounce_sigma(
            T, T_std, [decompositions[p.name][0] for p in photos], [p.values for p in photos],
            lambda op, values, n: _split(op, spilled, values, n, 0.0)[0], stds,
            transform=None if spilled is None else spilled.unmix)
    except TransportError as exc:
        log.info("%s: the bounces are not judged against their noise (%s)", isf.path, exc)
        op_diag["bounce_noise"] = {"measured": False, "reason": str(exc)}
        return None
    seconds = time.perf_counter() - start
    draws = draws_for(isf.m)
    op_diag["bounce_noise"] = {
        "measured": True, "draws": draws, "seconds": seconds, "T_noise": source,
        "photo_noise": "the beam frames' noise model (noise.json)" if any(s is not None for s in stds) else None,
        "regularised": "the draws are split without regularisation: an upper bound" if regularise else None}
    log.info("%s: the bounces' noise from %d draws of T%s (%.2g s)", isf.path, draws,
             " and of the photos" if any(s is not None for s in stds) else "", seconds)
    return {p.name: s for p, s in zip(photos, sigmas)}


def _sample_names(isf: ISF, photo: Photo):
    """How the messages name sample i: the pixel where it is seen (full-frame sensor
    pixels) for a frame, its row and plan beam for a sample vector."""
    if photo.frame and isf.samples is not None:
        return lambda i: f"pixel ({isf.samples[i][0]:.0f}, {isf.samples[i][1]:.0f})"
    beams = isf.beams
    return lambda i: f"sample {i}" + (f" (plan beam {int(beams[i])})" if beams is not None else "")


def _spill_used(isf: ISF, spill: bool) -> bool:
    """Whether the split takes the ISF's spill out: asked, measured and not empty."""
    return bool(spill and isf.spill is not None and isf.spill.nnz)


def _unmixing(isf: ISF, spill: bool) -> Unmixing | None:
    """``I + Q`` of the ISF's spill matrix, factorised (None: not used, :func:`_spill_used`)."""
    return Unmixing(isf.spill) if _spill_used(isf, spill) else None


def _unmixed_T(isf: ISF, spilled: Unmixing, cache_dir, stack: contextlib.ExitStack) -> np.ndarray:
    """``(I + Q)^-1 T``: for a memory-mapped T, a memory map in a temporary directory beside
    the operator cache (``stack`` removes it), written a block of columns at a time."""
    if not isinstance(isf.T, np.memmap):
        return spilled.unmix(np.asarray(isf.T))
    return spilled.unmix(isf.T, out=_scratch_map(isf.T.shape, "ilt-unmixed-", cache_dir, stack))


def _fold_corrections(isf: ISF, fold_transfer: bool):
    """(rows, cols, values) of the ISF's ``fold_transfer.npz`` when asked for and not empty, else None."""
    path = Path(isf.path).parent / FOLD_FILE
    if not fold_transfer or not path.exists():
        return None
    try:
        corrections = scipy.sparse.load_npz(path).tocoo()
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: not readable ({exc}); run ilt build-isf again") from None
    if corrections.shape != (isf.m, isf.m):
        raise InputError(f"{path}: shape {corrections.shape}, but {isf.path} has m = {isf.m}: built for another "
                         "T; run ilt build-isf again")
    if corrections.nnz == 0:
        return None
    return corrections.row.astype(np.int64), corrections.col.astype(np.int64), corrections.data


def _folded_T(T, corrections, owned: bool, cache_dir, stack: contextlib.ExitStack) -> np.ndarray:
    """T with the fold corrections (:func:`ilt.isf.fold_transfer.apply_corrections`): in place
    when ``owned`` (the spill's unmixed T), else a copy (a memory map beside the operator
    cache for a memory-mapped T, as :func:`_unmixed_T`)."""
    if not owned:
        out = _scratch_map(T.shape, "ilt-folded-", cache_dir, stack) if isinstance(T, np.memmap) \
            else np.empty(T.shape)
        out[...] = T
        T = out
    return apply_corrections(T, *corrections)


def _scratch_map(shape, prefix: str, cache_dir, stack: contextlib.ExitStack) -> np.memmap:
    """A float64 memory map of ``shape`` in a temporary directory beside the operator cache
    (the system's temporary directory without one), removed when ``stack`` closes: a copy
    of a memory-mapped T that is not held in memory."""
    scratch = stack.enter_context(tempfile.TemporaryDirectory(
        prefix=prefix, dir=cache_dir if cache_dir and Path(cache_dir).is_dir() else None))
    return np.lib.format.open_memmap(Path(scratch) / "T.npy", mode="w+", dtype=np.float64, shape=shape)


def _split(op, spilled: Unmixing | None, values: np.ndarray, n_bounces: int, tol: float):
    """The bounces of sample vectors and, with a spill, the beam weights of each bounce's
    re-emitted light for the full-resolution images (:func:`ilt.decompose.fullres.full_resolution`):
    the recursion on ``(I + Q)^-1 values``, its bounces and residual mixed back by ``I + Q``."""
    if spilled is None:
        return bounce_images(op, values, n_bounces=n_bounces, tol=tol), None
    unmixed = bounce_images(op, spilled.unmix(values), n_bounces=n_bounces, tol=tol)
    t1 = op.t1[None, :, None] if unmixed.bounces.ndim == 3 else op.t1[None, :]
    bounces = np.moveaxis(spilled.mix(np.moveaxis(unmixed.bounces, 0, 1)), 1, 0)
    total = np.linalg.norm(values, axis=0)
    norms = np.linalg.norm(bounces, axis=1) / np.where(total > 0, total, 1.0)
    mixed = replace(unmixed, bounces=bounces, residual=spilled.mix(unmixed.residual), relative_norms=norms)
    return mixed, unmixed.bounces / t1


def frames_noise(isf_dir) -> tuple[float | None, str]:
    """T's noise (RMS, unit columns) as build-isf measured it from the beam frames
    (``noise.json`` beside T.npy), and where it came from; (None, ...) when it did not."""
    if isf_dir is None:
        return None, "given"
    isf_dir = Path(isf_dir)
    isf_dir = isf_dir if isf_dir.is_dir() else isf_dir.parent   # an ISF's path is its T.npy
    try:
        record = read_noise(isf_dir)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    if record is None or not record["entry_sigma"] > 0:
        return None, "given"
    return float(record["entry_sigma"]), f"measured from the beam frames ({isf_dir / NOISE_FILE})"


def decompose_parameters(isf: ISF, n_bounces: int = 8, tol: float = 0.0, solver: str = "auto",
                         noise: float | None = None, regularise: bool | None = None, samples_only: bool = False,
                         spill: bool = True, accept_non_lambertian: bool = False,
                         fold_transfer: bool = True) -> dict:
    """What a photo's ``manifest.json`` records as the parameters of its decomposition:
    the options, and the fine operator, spill matrix and fold corrections used by their
    files' hashes (None: none; the fold corrections only when used), so a re-run after
    ``fine/``, ``spill.npz`` or ``fold_transfer.npz`` was built or rebuilt is not taken for
    one already done."""
    directory = Path(isf.path).parent
    manifest = directory / FINE_DIR / MANIFEST
    fine = None if samples_only or not manifest.exists() else fingerprint_file(manifest)
    out = {"bounces": n_bounces, "tol": tol, "solver": solver, "noise": noise,
           "regularise": "auto" if regularise is None else regularise,
           "samples_only": samples_only, "fine": fine,
           "spill": fingerprint_file(directory / SPILL_FILE) if _spill_used(isf, spill) else None,
           "accept_non_lambertian": accept_non_lambertian}
    if fold_transfer and (directory / FOLD_FILE).exists():
        out["fold_transfer"] = fingerprint_file(directory / FOLD_FILE)
    return out


def _lambertian_verdict(isf: ISF, accept: bool) -> dict | None:
    """build-isf's reciprocity verdict on T (None: the ISF has none); refused when "not lambertian"."""
    directory = Path(isf.path).parent
    try:
        verdict = read_lambertian(directory)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    if verdict is None:
        return None
    if verdict.get("verdict") == "not lambertian":
        if not accept:
            raise NotLambertian(f"{directory / LAMBERTIAN_FILE}: not lambertian: {verdict.get('reason', '')}; "
                                "the cancellation theorem needs a Lambertian scene, so the bounces would be wrong: "
                                "nothing written (--accept-non-lambertian writes them, marked)")
        log.warning("%s: not lambertian (%s): writing the bounces as asked, each marked with the verdict",
                    directory / LAMBERTIAN_FILE, verdict.get("reason", ""))
    return {"verdict": verdict.get("verdict"), "reason": verdict.get("reason"), "accepted": accept,
            "reciprocity_residual": verdict.get("reciprocity_residual"), "noise_floor": verdict.get("noise_floor")}


def _diverging(isf: ISF, op_diag: dict, verdict: dict | None, accept: bool) -> dict | None:
    """Refuse a T whose bounce series diverges (spectral radius of A >= 1) unless accepted; the verdict to record."""
    rho = op_diag.get("spectral_radius_A")
    if rho is None or rho < 1:
        return verdict
    what = (f"spectral radius of A = I - C1 is {rho:.4g} >= 1: the bounce series diverges, so T is not the ISF of "
            "a Lambertian scene that conserves energy (glossy or specular surfaces, flare, noise in T or a wrong spot)")
    if not accept:
        raise NotLambertian(f"{isf.path}: {what}: nothing written (--accept-non-lambertian writes the bounces, marked)")
    return {**(verdict or {"verdict": "undecided", "reason": "no lambertian.json"}), "accepted": True,
            "spectral_radius_A": rho}


def previous_result(directory: Path, parameters: dict, inputs: set[str]) -> dict | None:
    """The summary of an earlier decomposition in ``directory`` when its manifest records
    ``parameters`` and exactly the fingerprints ``inputs`` (photo and T), else None."""
    try:
        manifest = read_manifest(directory)
        summary = json.loads((directory / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    if manifest.get("parameters") != parameters or set(manifest.get("inputs", {}).values()) != inputs:
        return None
    return {**summary, "output": str(directory), "skipped": True}


def not_decomposed(out: str | os.PathLike, isf: ISF, photos: list[str | os.PathLike], **options) -> str | None:
    """Why ``out`` does not hold a decomposition of every one of ``photos`` with this ISF
    and these options (``n_bounces``, ``tol``, ``solver``, ``noise``, ``regularise``,
    ``samples_only``, as :func:`decompose` takes them): the photos it lacks, and for
    those it holds otherwise, the parameters that differ. None when it holds them all,
    as ``ilt decompose`` run by hand leaves them. Reads each photo and T once, for
    their fingerprints."""
    out = Path(out)
    parameters = decompose_parameters(isf, **options)
    fingerprint = fingerprint_array(np.asarray(isf.T))
    lacking = []
    for photo in map(Path, photos):
        directory, photo_hash = out / photo.stem, fingerprint_file(photo)
        if previous_result(directory, parameters, {photo_hash, fingerprint}) is not None:
            continue
        try:
            manifest = read_manifest(directory)
        except (OSError, StageError):
            lacking.append(f"{photo.name} not decomposed")
            continue
        recorded, inputs = manifest.get("parameters", {}), set(manifest.get("inputs", {}).values())
        changed = [f"{k} {recorded.get(k)!r} (wanted {v!r})" for k, v in parameters.items() if recorded.get(k) != v]
        if changed:
            lacking.append(f"{photo.name} decomposed with {', '.join(changed)}")
        elif photo_hash not in inputs:
            lacking.append(f"{photo.name} changed since it was decomposed")
        elif fingerprint not in inputs:
            lacking.append(f"{photo.name} decomposed with another T")
        else:
            lacking.append(f"{directory / 'summary.json'} is not readable")
    return "; ".join(lacking) or None


__all__ = ["decompose", "read_photo", "load_operator", "InputError", "TransportError", "default_cache_dir"]


#: ``--regularise`` by default up to this m: measured to m = 768 (docs/numerics.md), and
#: the width's choice holds about eight m x m float64 arrays (1.3 GB at m = 4096)
AUTO_REGULARISE_MAX_M = 4096


def auto_regularise(m: int, noise: float | None, neighbours: bool) -> str | None:
    """Why T is not denoised by default (None: it is). It is when its noise is known
    (measured by build-isf from the frames, or given), the samples have neighbours to
    smooth along (cells, or the plan's full grid) and m is at most
    :data:`AUTO_REGULARISE_MAX_M`: on the noisy sweep's flatland scans at 384 beams the
    bounces' error fell by a quarter, and by at most 0.3% either way at 48 (docs/numerics.md)."""
    if noise is None or not noise > 0:
        return "its noise is unknown (build-isf measured none in the frames; --noise gives it)"
    if not neighbours:
        return "no cells and no full grid plan to smooth along"
    if m > AUTO_REGULARISE_MAX_M:
        return f"m = {m} > {AUTO_REGULARISE_MAX_M} (--regularise asks for it)"
    return None


def _debiased_diagonal(T, variance, owned: bool, cache_dir, stack: contextlib.ExitStack):
    """T with each diagonal entry raised by its variance over itself
    (:func:`~ilt.transport.regularise.diagonal_raise`) and the record; T itself and None when
    that is nothing. ``owned``: T is this decompose's own copy (the spill's unmixed T), raised
    in place; a memory-mapped T is copied to a memory map beside the operator cache
    (``stack`` removes it), as :func:`_unmixed_T` does: T is not held twice in memory."""
    raise_by, record = diagonal_raise(T, variance)
    if raise_by is None:
        return T, None
    out = None
    if owned:
        out = T
    elif isinstance(T, np.memmap):
        out = _scratch_map(T.shape, "ilt-debiased-", cache_dir, stack)
    return raise_diagonal(T, raise_by, out), record


def _cell_areas(cells: np.ndarray, m: int) -> np.ndarray | None:
    """(m,) the pixels of each cell of the label image ``cells``, or None with an empty one."""
    labels = np.asarray(cells)
    areas = np.bincount(labels[labels >= 0].astype(np.int64), minlength=m)[:m]
    return areas if np.all(areas > 0) else None


def _neighbours(cells: np.ndarray) -> np.ndarray:
    """(e, 2) the cells of the label image ``cells`` that share a pixel edge."""
    from ilt.isf.fine import adjacent_cells
    return adjacent_cells(cells)
