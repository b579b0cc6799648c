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
samples that happen to read low.

Saturated samples get zero weight; so do near-black samples (expected signal below
``black_floor`` DN) except each pixel's longest unsaturated one, so dark pixels still
get an estimate. Given which samples are clipped, the variance of the result,
``1 / sum_k w_k``, is to first order the Cramer-Rao bound of the samples kept;
`cramer_rao_bound` averages that bound over the clipping pattern (a sample whose mean
sits at its clip level is lost half the time, whatever the estimator does with it,
unless it uses the clip itself as information: see docs/hdr.md).
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
    slope: Callable[[np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge K exposures of one view into a linear radiance image.

    Parameters
    ----------
    frames : K arrays (h, w) (or (h, w, C)), black-subtracted DN, float32 or float64
        (float32 frames are merged in float32 without a copy).
    exposures : (K,) relative exposures e_k = t_k / N_k^2 in seconds at f/1, or
        measured ones (from calibration); any positive scale.
    saturated : K bool masks, True where the sample is clipped; or give ``saturation``,
        (K,) DN thresholds (sample >= threshold is clipped). Neither: nothing clipped.
    noise : the sensor's NoiseModel (gain e-/DN, read noise DN).
    response : inverse response f on normalised values, f(1) = 1 (Mitsunaga & Nayar
        1999, Eq. 3), applied to ``frame / full_scale``; None for linear RAW data.
    black_floor : DN below which a sample is near-black (default ``noise.floor``).
    dark : (h, w) black-subtracted DN of a dark frame, subtracted from every frame.
    slope : f' on normalised values, for 8/16-bit frames through a ``response``: the
        noise is then the code's (read noise and 1/12 DN^2 of quantisation, in codes),
        carried through f, ``v_k = f'(M_k)^2 (s^2 + 1/12)`` in linear DN, with ``M_k`` the
        code the first-pass radiance predicts (not the sample's own); shot noise as above.

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
    floor = float(noise.floor if black_floor is None else black_floor)
    dtype = np.float32 if all(f.dtype == np.float32 for f in frames) else np.float64
    radiance = np.empty(shape, np.float32)
    count = np.empty(shape, np.uint8)
    all_clipped = np.empty(shape, bool)
    row = int(np.prod(shape[1:], dtype=np.int64))
    step = max(1, STRIP_SAMPLES // max(row, 1))
    any_unclipped = bright = False
    code_slope = None if slope is None else _CodeSlope(slope, response)  # its table once a merge
    for r0 in range(0, shape[0], step):
        rows = slice(r0, r0 + step)
        u, b = _merge_rows(
            [f[rows] for f in frames], e,
            [_clipped(k, frames[k], rows, saturated, saturation) for k in range(K)],
            noise, response, full_scale, floor, None if dark is None else dark[rows], dtype,
            radiance[rows], count[rows], all_clipped[rows], code_slope)
        any_unclipped |= u
        bright |= b
    if not any_unclipped:
        raise MergeError("every pixel of every frame is saturated")
    if not bright:
        raise MergeError(f"every frame is black: no sample above the noise floor ({floor:.3g} DN)")
    return radiance, count, all_clipped


#: samples per frame merged at a time: a strip of rows whose temporaries stay in cache
STRIP_SAMPLES = 1 << 15


def _merge_rows(frames, e, clipped, noise, response, full_scale, floor, dark, dtype,
                radiance, count, all_clipped, code_slope=None) -> tuple[bool, bool]:
    """`merge_bracket` on a strip of rows, written into ``radiance``, ``count`` and
    ``all_clipped`` (views); returns (any sample unclipped, any sample above ``floor``)."""
    K = len(frames)
    shape = frames[0].shape
    order = np.argsort(-e, kind="stable")  # longest first: "longest unclipped" is the first seen
    linear = [_linearise(frames[k], dark, response, full_scale, dtype) for k in range(K)]
    unclipped = [~c for c in clipped]

    # first pass: read-noise weights e^2 / s^2 (common factor dropped). Masks multiply
    # rather than select: numpy's where= is ten times slower than a product
    num, den, tmp = (np.zeros(shape, dtype) for _ in range(3))
    any_unclipped = np.zeros(shape, bool)
    bright = False
    for k in order:
        ek = float(e[k])  # a Python float: a numpy float64 scalar would promote float32 work
        keep = unclipped[k].astype(dtype)
        np.multiply(linear[k], ek, out=tmp)
        tmp *= keep
        num += tmp
        keep *= ek**2
        den += keep
        any_unclipped |= unclipped[k]
        bright = bright or bool(np.any(unclipped[k] & (linear[k] > floor)))
    x0 = _ratio(num, den)

    # second pass: inverse-variance weights at the first-pass X; near-black is judged by the
    # expected signal x0 e_k, not by the sample itself, so noise does not pick the samples.
    # w_k / e_k = e_k / v_k = sites / (x0 / g + (s^2 + 1/12) / e_k); sites drops out
    signal = np.maximum(x0, 0) * float(1 / noise.gain)
    read = float(noise.read_noise**2 + 1 / 12)
    num[:] = 0.0
    den[:] = 0.0
    count[...] = 0
    seen = np.zeros(shape, bool)
    weight = np.empty(shape, dtype)
    for k in order:
        ek = float(e[k])
        use = (x0 > floor / ek) | ~seen  # near-black only where a longer sample exists
        seen |= unclipped[k]
        use &= unclipped[k]
        if code_slope is None:
            np.add(signal, read / ek, out=weight)
        else:  # codes through f: the read and quantisation variance scaled by f'^2
            predicted = np.clip(x0 * (ek / full_scale), 0.0, 1.0)
            np.add(signal, read * code_slope(predicted) ** 2 / ek, out=weight)
        np.divide(use, weight, out=weight)
        np.multiply(weight, linear[k], out=tmp)
        num += tmp
        weight *= ek
        den += weight
        count += use
    radiance[...] = _ratio(num, den, fallback=x0)
    np.logical_not(any_unclipped, out=all_clipped)
    if all_clipped.any():
        k_min = order[-1]
        radiance[all_clipped] = linear[k_min][all_clipped] / e[k_min]
    return bool(any_unclipped.any()), bright


class _CodeSlope:
    """f'(M) at the code M whose f(M) is a given normalised linear value: f is monotone,
    so M is read off a table of f (made once) by interpolation."""

    def __init__(self, slope, response):
        self.slope = slope
        self.grid = np.linspace(0.0, 1.0, 1025)
        self.table = np.maximum.accumulate(np.asarray(response(self.grid), dtype=np.float64))

    def __call__(self, linear: np.ndarray) -> np.ndarray:
        m = np.interp(linear, self.table, self.grid)
        return np.maximum(np.asarray(self.slope(m), dtype=np.float64), 1e-3).astype(linear.dtype, copy=False)


def _ratio(num, den, fallback=None) -> np.ndarray:
    """num / den, and ``fallback`` (else 0) where den is 0."""
    empty = den == 0
    out = num / np.where(empty, 1, den)
    if empty.any():
        out[empty] = 0 if fallback is None else fallback[empty]
    return out


def _linearise(frame, dark, response, full_scale, dtype) -> np.ndarray:
    z = np.asarray(frame, dtype=dtype)
    if dark is not None:
        z = z - dark.astype(dtype, copy=False)
    if response is not None:
        z = (response(np.clip(z / full_scale, 0.0, None)) * full_scale).astype(dtype, copy=False)
    return z


def _clipped(k, raw, rows: slice, saturated, saturation) -> np.ndarray:
    """Clipped samples of frame ``k`` (``raw``) in ``rows``."""
    if saturated is not None:
        return np.broadcast_to(np.asarray(saturated[k], bool), raw.shape)[rows]
    if saturation is not None:
        return np.asarray(raw[rows]) >= saturation[k]
    return np.zeros(raw[rows].shape, bool)


def cramer_rao_bound(radiance, exposures, saturation, noise: NoiseModel = NoiseModel(),
                     black_floor: float | None = None) -> np.ndarray:
    """Smallest variance (DN/s at f/1)^2 of an unbiased estimate of ``radiance`` from the
    unclipped samples, averaged over which samples clip.

    Given the set S of unclipped samples, independent Gaussian samples
    Z_k ~ N(X e_k, v_k(X)) have Fisher information
    ``I_S = sum_{k in S} e_k^2 / v_k + (dv_k/dX)^2 / (2 v_k^2)`` (near-black samples
    left out as `merge_bracket` does: expected level below ``black_floor`` DN where a
    longer unclipped sample exists). A green sample clips when either of its two
    photosites reaches ``saturation[k]`` DN, with probability
    ``p_k = 1 - Phi((saturation[k] - X e_k) / sd_k)^2``; the bound is
    ``E_S[1 / I_S]`` over the 2^U patterns of the samples with 1e-9 < p_k < 1 - 1e-9.
    It does not credit the clip itself as information (a censored-data estimator could).
    ``radiance`` any shape; returns the same shape.
    """
    from scipy.special import ndtr

    x = np.asarray(radiance, dtype=np.float64)
    e = np.asarray(exposures, dtype=np.float64)
    sat = np.broadcast_to(np.asarray(saturation, dtype=np.float64), e.shape)
    floor = noise.floor if black_floor is None else black_floor
    level = x[..., None] * e  # (..., K)
    v = noise.variance(level)
    info_k = e**2 / v + (e / noise.gain / noise.sites) ** 2 / (2 * v**2)
    site_sd = np.sqrt(v * noise.sites)
    p_clip = 1.0 - ndtr((sat - level) / site_sd) ** 2
    uncertain = (p_clip > 1e-9) & (p_clip < 1 - 1e-9)
    order = np.argsort(-e, kind="stable")
    rows = zip(uncertain.reshape(-1, len(e)), p_clip.reshape(-1, len(e)),
               level.reshape(-1, len(e)), info_k.reshape(-1, len(e)))
    bound = [_expected_inverse_information(np.flatnonzero(u), p, lv, ik, order, floor)
             for u, p, lv, ik in rows]
    return np.reshape(bound, x.shape)


def _expected_inverse_information(uncertain, p_clip, level, info_k, order, floor) -> float:
    """E[1 / I_S] of one pixel over the clip patterns of its ``uncertain`` samples."""
    total = 0.0
    for bits in range(1 << len(uncertain)):
        kept = p_clip <= 1e-9
        prob = 1.0
        for b, k in enumerate(uncertain):
            clipped = bool(bits >> b & 1)
            kept[k] = not clipped
            prob *= p_clip[k] if clipped else 1.0 - p_clip[k]
        info, seen = 0.0, False
        for k in order:
            if kept[k] and (level[k] > floor or not seen):
                info += info_k[k]
            seen = seen or kept[k]
        total += prob / info if info > 0 else np.inf
    return total
