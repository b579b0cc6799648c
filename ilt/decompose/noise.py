"""How much of each bounce sample is noise: Monte Carlo draws of T and of the photo.

A measured T carries each entry's noise (``T_var.npy``, :mod:`ilt.isf.noise`, or one
sigma for all entries: given, or measured from T's negative entries), and a photo
carries its pixels' (the beam frames' noise model applied to its cell sums: the same
camera and merge). A bounce sample's noise is what the decomposition makes of them,
through the inverse of T and the recursion: far from linear in T for the higher bounces,
and different at every sample. :func:`bounce_sigma` measures it the direct way: ``draws``
copies of T and of each photo, each with one draw of their noise added, are decomposed
again with a dense operator, and the spread of their bounces about the photo's own is
each sample's sigma (:func:`ilt.transport.diagnostics.decomposition_diagnostics` judges
negatives and noise shares by it).

The cost is ``draws`` dense factorisations of T per run (shared by every photo), so the
draws stop at :data:`MAX_M` samples; past it the bounces are not judged against noise
(an INFO line says so).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ilt.isf.directory import ISF
from ilt.isf.noise import T_VAR_FILE, FrameNoise, cell_variance, read_noise
from ilt.transport.operators import (
    CancellationOperator,
    Decomposition,
    cancellation_operator,
)
from ilt.transport.scan import TransportError

#: largest m whose bounces are judged against noise (dense draws: 8 of them cost 1.5 s at
#: m = 2048, 10 s at m = 4096, 6.5x the decomposition itself; benchmarks/bench_bounce_noise.py)
MAX_M = 2048

#: draws at small m, and the fewest at MAX_M (each costs a factorisation of T)
DRAWS = 24
MIN_DRAWS = 8


def draws_for(m: int) -> int:
    """Draws at ``m`` samples: :data:`DRAWS` up to m = 512, then half as many at each
    doubling of m, and at least :data:`MIN_DRAWS` (a sigma from 8 draws is within about
    25% of the true one, which a 5-sigma test can afford)."""
    return int(max(MIN_DRAWS, min(DRAWS, round(DRAWS * 512 / max(m, 1)))))


#: from this m on the draws are factorised in float32: half the time, and its rounding
#: (1e-7 times T's condition) is far below the noise it measures (predicted / true error
#: 0.98-1.06 at m = 1024 either way: benchmarks/bench_bounce_noise.py)
FLOAT32_M = 1024


def _factorised(T: np.ndarray, m: int) -> CancellationOperator:
    if m >= FLOAT32_M:
        try:
            return cancellation_operator(T, dtype=np.float32)
        except TransportError:     # too ill-conditioned for float32: this draw in float64
            pass
    return cancellation_operator(T)


def bounce_sigma(
    T: np.ndarray,
    T_std: np.ndarray | float,
    references: Sequence[Decomposition],
    values: Sequence[np.ndarray],
    split: Callable[[CancellationOperator, np.ndarray, int], Decomposition],
    values_std: Sequence[np.ndarray | None] | None = None,
    transform: Callable[[np.ndarray], np.ndarray] | None = None,
    draws: int | None = None,
    seed: int = 0,
) -> list[np.ndarray]:
    """Each bounce sample's noise (sigma, the shape of its reference's ``bounces``) for
    every photo.

    T (m, m) unit columns; T_std: its entries' sigma, (m, m) or one number; references:
    each photo's decomposition with T; values: the photos' sample vectors, and
    values_std their sigma (None: noise-free); split(operator, values, n) decomposes
    ``values`` into n bounces as the references were; transform: what is done to T
    before its operator is built (the spill's unmixing), None for nothing.
    """
    m = T.shape[0]
    draws = draws_for(m) if draws is None else int(draws)
    rng = np.random.default_rng(seed)
    values_std = [None] * len(values) if values_std is None else list(values_std)
    sums = [np.zeros_like(ref.bounces) for ref in references]
    used = 0
    for _ in range(draws):
        kind = np.float32 if m >= FLOAT32_M else np.float64
        drawn = np.asarray(T, dtype=np.float64) + np.asarray(T_std) * rng.standard_normal((m, m), dtype=kind)
        drawn = drawn if transform is None else transform(drawn)
        try:
            op = _factorised(drawn, m)
        except TransportError:   # a draw T cannot be inverted (noise as large as T): not counted
            continue
        used += 1
        for k, (ref, v, s) in enumerate(zip(references, values, values_std)):
            v = v if s is None else v + s * rng.standard_normal(v.shape)
            dec = split(op, v, ref.count)
            sums[k] += (dec.bounces - ref.bounces) ** 2
    if used < 2:
        raise TransportError("the noise of T is as large as T: no draw of it can be inverted")
    return [np.sqrt(s / used) for s in sums]


def entry_noise(isf: ISF, noise: float | None, source: str) -> tuple[np.ndarray | float | None, str]:
    """The sigma of T's entries for the draws, and where it came from: ``noise`` when the
    user gave it, else build-isf's ``T_var.npy`` (each entry's own), else ``noise``
    as measured (from the beam frames or T's negative entries); (None, why) when unknown."""
    directory = Path(isf.path).parent
    if source != "given" or noise is None:
        path = directory / T_VAR_FILE
        if path.exists():
            T_var = np.load(path, mmap_mode="r")
            if T_var.shape == (isf.m, isf.m):
                return np.sqrt(np.maximum(np.asarray(T_var, dtype=np.float64), 0.0)), f"{path}"
    if noise is not None and noise > 0:
        return float(noise), source
    return None, "the noise of T is not known (no T_var.npy, no --noise, no negative entries in T)"


def photo_model(isf: ISF) -> tuple[FrameNoise, np.ndarray] | None:
    """The beam frames' noise model (``noise.json``) and each cell's pixel count (ones for
    point sampling), read once for every photo of a run; None without a model."""
    try:
        record = read_noise(Path(isf.path).parent)
    except ValueError:
        return None
    if record is None:
        return None
    area = (np.bincount(isf.cells[isf.cells >= 0].ravel(), minlength=isf.m)[:isf.m] if isf.cells is not None
            else np.ones(isf.m))
    return FrameNoise.from_record(record), area


def photo_noise(isf: ISF, values: np.ndarray, frame: bool, model=None) -> np.ndarray | None:
    """Sigma of a photo's samples: the beam frames' noise model applied to the photo's
    cell sums (a photo taken and merged like the beam frames); None for a sample vector
    or an ISF without a noise model. ``model``: :func:`photo_model`'s, when the caller has it."""
    if not frame:
        return None
    model = photo_model(isf) if model is None else model
    if model is None:
        return None
    noise, area = model
    level = np.maximum(np.asarray(values, dtype=np.float64), 0.0)
    shaped = level if level.ndim == 2 else level[:, None]
    return np.sqrt(cell_variance(noise, shaped, area)).reshape(level.shape)


__all__ = ["MAX_M", "bounce_sigma", "draws_for", "entry_noise", "photo_model", "photo_noise"]
