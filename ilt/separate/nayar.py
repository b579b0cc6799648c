"""Nayar, Krishnan, Grossberg & Raskar, "Fast Separation of Direct and Global Components of a
Scene using High Frequency Illumination" (SIGGRAPH 2006), Sec. 3-4: the max/min estimator.

Under a binary pattern with half of the projector's pixels on, a scene point lit by the
pattern sees ``L+ = Ld + (1 + b) / 2 Lg`` and one in the dark ``L- = b Ld + (1 + b) / 2 Lg``,
where b is the brightness of an "off" projector pixel (0 for an ideal projector) and the
global light ``Lg`` (interreflections, subsurface scattering, volumetric light) is half of
what the fully lit scene receives, when the pattern's frequency is high against the
global light's variation (their Eq. 3). Over patterns shifted so that every point is lit in
some and dark in others, ``L+ = max`` and ``L- = min`` per pixel, and

    Ld = (L+ - L-) / (1 - b),     Lg = 2 (L- - b L+) / (1 - b^2)      (their Eq. 4 with b).

It holds for any reflectance (gloss too), unlike the cancellation theorem.
"""

from __future__ import annotations

import numpy as np


def direct_global(stack: np.ndarray, black: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Direct and global light from K >= 2 photos under shifted half-on patterns.

    stack: (K, ...) float, linear photos, the same pixels in each; black: b in [0, 1),
    an "off" projector pixel's brightness over an "on" one's.
    Returns (direct, global), each of ``stack.shape[1:]``, float64; ``direct + global``
    is the fully lit photo's estimate (``max + min`` when b = 0).
    """
    stack = np.asarray(stack, dtype=np.float64)
    if stack.ndim < 2 or stack.shape[0] < 2:
        raise ValueError(f"need at least 2 pattern photos stacked on the first axis, got shape {stack.shape}")
    if not 0.0 <= black < 1.0:
        raise ValueError(f"black must be in [0, 1), got {black}")
    high, low = stack.max(axis=0), stack.min(axis=0)
    return (high - low) / (1.0 - black), 2.0 * (low - black * high) / (1.0 - black**2)
