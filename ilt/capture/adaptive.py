"""Adaptive bracketing: take only the exposures a beam needs (DESIGN.md sec. 4).

The bracket is walked from the longest exposure towards shorter ones. After each
frame, every sampled pixel is classified: well exposed (between ``low`` and ``high`` of
the saturation level), saturated (its radiance is at least ``saturation / e``), or
under-exposed. A shorter exposure adds nothing once no sampled pixel is saturated in
the frames taken: every pixel is then already measured unsaturated, with more light
than any shorter frame would collect. While pixels are saturated, the next frame is the
shortest remaining exposure that still exposes the dimmest saturated pixel at ``low``
or more of full scale, so no pixel falls into a gap between frames; exposures in
between add nothing and are skipped.

``e = t / N^2`` is the relative exposure (:attr:`ilt.capture.config.Exposure.relative`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .config import Exposure


@dataclass
class AdaptiveBracket:
    """Decides the next exposure of one beam from the frames taken so far.

    exposures: the full bracket, longest first. low, high: well-exposed range as
    fractions of the saturation level. stride: sample every stride-th pixel of the
    half-resolution green image.
    """

    exposures: tuple[Exposure, ...]
    low: float = 1 / 64
    high: float = 0.9
    stride: int = 1
    taken: list[Exposure] = field(default_factory=list)
    _lower: np.ndarray | None = None  # per sampled pixel: DN/exposure lower bound, 0 once measured
    _saturation: float = 0.0

    def first(self) -> Exposure:
        return self.exposures[0]

    def add(self, exposure: Exposure, green: np.ndarray, saturation: float, saturated: np.ndarray) -> None:
        """Record a frame: ``green`` black-subtracted DN (H/2, W/2), ``saturation`` DN,
        ``saturated`` bool mask (as :func:`ilt.io.raw.read_green` returns them)."""
        s = (slice(None, None, self.stride),) * 2
        clip = saturated[s] | (green[s] > self.high * saturation)
        bound = np.where(clip, self.high * saturation / exposure.relative, 0.0)
        # a pixel measured unsaturated in any frame is done (bound 0); a saturated one keeps
        # the tightest bound, from the shortest frame it saturated in
        self._lower = bound if self._lower is None else np.where(clip & (self._lower > 0), bound, 0.0)
        self._saturation = saturation
        self.taken.append(exposure)

    def next(self) -> Exposure | None:
        """The next exposure to take, or None when the rest add nothing."""
        remaining = [x for x in self.exposures if x.relative < self.taken[-1].relative]
        if not remaining or self._lower is None or not (self._lower > 0).any():
            return None
        dimmest = float(self._lower[self._lower > 0].min())
        fits = [x for x in remaining if dimmest * x.relative >= self.low * self._saturation]
        return min(fits, key=lambda x: x.relative) if fits else max(remaining, key=lambda x: x.relative)

    def skipped(self) -> list[Exposure]:
        return [x for x in self.exposures if x not in self.taken]
