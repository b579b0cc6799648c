"""Merge a bracket of linear exposures into one radiance image with noise-optimal weights.

Noise model of a black-subtracted green sample Z_k (mean of ``sites`` photosites) of a
pixel with radiance X (DN per second at f/1 per photosite) at relative exposure
e_k = t_k / N_k^2 (s):

    E[Z_k] = X e_k,   Var[Z_k] = v_k = (X e_k / g + s^2 + 1/12) / sites

with g the gain (e-/DN), s the read noise (DN) and 1/12 the quantisation variance.
The inverse-variance (best linear unbiased) estimate is

    X = sum_k w_k (Z_k / e_k) / sum_k w_k,   w_k = e_k^2 / v_k,

the issue's ``w = t^2 / (g t X + s_read^2)`` in DN units. v_k is evaluated at X from a
first pass (read-noise weights), not at each sample's own value, which would favour
samples that happen to read low. Saturated samples get zero weight; so do near-black
samples (expected signal below ``black_floor`` DN) except each pixel's longest
unsaturated one, so dark pixels still get an estimate. Its
variance ``1 / sum_k w_k`` is, to first order, the Cramer-Rao bound of the model
(`cramer_rao_bound` adds the information in the signal-dependent variance).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np


class MergeError(ValueError):
    """A bracket that cannot be merged; the message names the file or beam at fault."""


@dataclass(frozen=True)
class NoiseModel:
    """gain: electrons per DN; read_noise: DN (standard deviation, per photosite);
    sites: photosites averaged into one sample (2 for the green of a Bayer cell)."""

    gain: float = 1.0
    read_noise: float = 2.0
    sites: int = 2

    def variance(self, signal: np.ndarray) -> np.ndarray:
        """Var[Z] in DN^2 for a mean signal in DN (>= 0)."""
        return (np.maximum(signal, 0) / self.gain + (self.read_noise**2 + 1 / 12)) / self.sites

    @property
    def floor(self) -> float:
        """Default near-black threshold: two standard deviations of a black sample."""
        return 2.0 * float(np.sqrt(self.variance(np.zeros(()))))


def merge_bracket(
    frames: Sequence[np.ndarray],
    exposures: Sequence[float],
    saturated: Sequence[np.ndarray] | None = None,
    *,
    saturation: Sequence[float] | None = None,
    noise: NoiseModel = NoiseModel(),
    response: Callable[[np.ndarray], np.ndarray] | None = None,
    full_scale: float | None = None,
    black_floor: float | None = None,
    dark: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge K exposures of one view into a linear radiance image.

    Parameters
    ----------
    frames : K arrays (h, w) (or (h, w, C)), black-subtracted DN.
    exposures : (K,) relative exposures e_k = t_k / N_k^2 in seconds at f/1, or
        measured ones (from calibration); any positive scale.
    saturated : K bool masks, True where the sample is clipped; or give ``saturation``,
        (K,) DN thresholds (sample >= threshold is clipped). Neither: nothing clipped.
    noise : the sensor's NoiseModel (gain e-/DN, read noise DN).
    response : inverse response f on normalised values, f(1) = 1 (Mitsunaga & Nayar
        1999, Eq. 3), applied to ``frame / full_scale``; None for linear RAW data.
    black_floor : DN below which a sample is near-black (default ``noise.floor``).
    dark : (h, w) black-subtracted DN of a dark frame, subtracted from every frame.

    Returns
    -------
    radiance : (h, w) float32, DN per second at f/1 (per photosite). Pixels saturated in
        every frame hold the lower bound from the shortest exposure.
    valid_count : (h, w) uint8, samples that carried weight.
    saturated_mask : (h, w) bool, saturated in every frame (value is a lower bound).

    Raises MergeError when no pixel has a usable sample (all saturated or all black).
    """
    K = len(frames)
    e = np.asarray(exposures, dtype=np.float64)
    if K == 0 or e.shape != (K,) or not (e > 0).all():
        raise MergeError(f"need one positive exposure per frame, got {e.tolist()} for {K} frames")
    shape = frames[0].shape
    if any(f.shape != shape for f in frames):
        raise MergeError(f"frames differ in shape: {[f.shape for f in frames]}")
    if response is not None and not full_scale:
        raise MergeError("a response needs the full_scale (DN) its values are normalised by")
    floor = noise.floor if black_floor is None else black_floor
    order = np.argsort(-e)  # longest first: the running first pass meets the best sample first

    num = np.zeros(shape, np.float64)
    den = np.zeros(shape, np.float64)
    unsat_longer = np.zeros(shape, bool)
    bright = np.zeros(shape, bool)
    samples = []
    for k in order:
        z = _linearise(frames[k], dark, response, full_scale)
        usable = ~_clipped(k, z, frames[k], saturated, saturation)
        longest = usable & ~unsat_longer  # the pixel's longest unsaturated sample
        unsat_longer |= usable
        bright |= usable & (z > floor)
        # first pass: read-noise weights e^2 / s^2 (common factor dropped)
        num += np.where(usable, e[k] * z, 0.0)
        den += np.where(usable, e[k] ** 2, 0.0)
        samples.append((k, z, usable, longest))
    unsat_any = unsat_longer
    if not unsat_any.any():
        raise MergeError("every pixel of every frame is saturated")
    if not bright.any():
        raise MergeError(f"every frame is black: no sample above the noise floor ({floor:.3g} DN)")
    x0 = np.divide(num, den, out=np.zeros(shape), where=den > 0)

    # second pass: inverse-variance weights at the first-pass X; near-black is judged by the
    # expected signal x0 e_k, not by the sample itself, so noise does not pick the samples
    num[:] = 0.0
    den[:] = 0.0
    count = np.zeros(shape, np.uint8)
    for k, z, usable, longest in samples:
        expected = x0 * e[k]
        use = usable & ((expected > floor) | longest)
        w = np.where(use, e[k] / noise.variance(expected), 0.0)  # w_k / e_k
        num += w * z
        den += w * e[k]
        count += use
    radiance = np.divide(num, den, out=np.zeros(shape), where=den > 0)

    all_clipped = ~unsat_any
    if all_clipped.any():
        k_min = int(np.argmin(e))
        z = _linearise(frames[k_min], dark, response, full_scale)
        radiance[all_clipped] = z[all_clipped] / e[k_min]
    return radiance.astype(np.float32), count, all_clipped


def _linearise(frame, dark, response, full_scale) -> np.ndarray:
    z = np.asarray(frame, dtype=np.float64)
    if dark is not None:
        z = z - dark
    if response is not None:
        z = response(np.clip(z / full_scale, 0.0, None)) * full_scale
    return z


def _clipped(k, z, raw, saturated, saturation) -> np.ndarray:
    if saturated is not None:
        return np.asarray(saturated[k], bool)
    if saturation is not None:
        return np.asarray(raw) >= saturation[k]
    return np.zeros(z.shape, bool)


def cramer_rao_bound(radiance, exposures, saturation, noise: NoiseModel = NoiseModel()) -> np.ndarray:
    """Smallest variance (DN/s at f/1)^2 of any unbiased estimate of ``radiance``.

    For independent Gaussian samples Z_k ~ N(X e_k, v_k(X)) the Fisher information is
    ``sum_k e_k^2 / v_k + (dv_k/dX)^2 / (2 v_k^2)``, over the unsaturated samples
    (mean below ``saturation[k]`` DN). ``radiance`` any shape; returns the same shape.
    """
    x = np.asarray(radiance, dtype=np.float64)
    info = np.zeros(x.shape)
    for ek, sat in zip(np.asarray(exposures, float), np.broadcast_to(saturation, (len(exposures),))):
        v = noise.variance(x * ek)
        dv = ek / noise.gain / noise.sites
        info += np.where(x * ek < sat, ek**2 / v + dv**2 / (2 * v**2), 0.0)
    return np.divide(1.0, info, out=np.full(x.shape, np.inf), where=info > 0)
