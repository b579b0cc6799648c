"""Full-resolution n-bounce images of a photo (docs/fullres.md).

The sample-level recursion (:func:`ilt.transport.operators.bounce_images`) splits a
photo's cell integrals; the fine operator (:mod:`ilt.isf.fine`) spreads each bounce of
indirect light over its cell's pixels, and the direct image is what is left of the
photo. No solve beyond the sample level's: every image comes from the recursion's own
``r_n`` and ``L_(n+1) / t1``, and integrates over every cell to the sample-level bounce
(but where a cell's photo holds less light than its indirect light: below).
The rim, the pixels just outside every cell (:func:`ilt.isf.fine.rim`), takes the
indirect light of the nearest pixel inside, up to the photo's own.

No pixel inside a cell holds more indirect light than the photo does (:class:`PhotoBound`):
a cell's plane knows nothing of the pixels in it that are background past a silhouette,
partly background, or in a shadow of the photo's own light, and where its light is more
than the photo's the rest of the cell's pixels take the excess, so every image still
integrates over the cell to its sample-level bounce.
"""

from __future__ import annotations

import numpy as np

from ilt.isf.fine import FineOperator


def full_resolution(fine: FineOperator, photo: np.ndarray, decomposition, t1: np.ndarray,
                    excluded: np.ndarray | None = None, weights: np.ndarray | None = None,
                    neighbour_slopes: bool = True, report: dict | None = None,
                    photo_noise=None) -> dict[str, np.ndarray]:
    """The photo's full-resolution bounce images (module docstring).

    photo : (H, W) or (H, W, c) float32, on the cells' grid; decomposition : its
    :class:`ilt.transport.operators.Decomposition` (cell integrals, (m,) or (m, c)); t1 : (m,) the
    operator's diagonal of T1 for the ISF's T; excluded : (H, W) bool pixels left out
    (saturated): no coverage; weights : (N, m[, c]) the beam weights of each bounce's
    re-emitted light, ``T^-1 r_n`` (default ``L_(n+1) / t1``, the paper's; with a spill
    matrix the caller's, from the unmixed recursion, :mod:`ilt.isf.spill`).
    neighbour_slopes : give the cells the build kept flat, in each bounce image, the limited
    slope of their neighbours' means of that bounce (:mod:`ilt.isf.slopes`); False: flat.
    Returns {"bounce-1" .. "bounce-N", "indirect", "residual", "coverage"}: (H, W[, c])
    float32 images; ``photo = bounce-1 + ... + bounce-N + residual`` at every pixel.
    Coverage is 1 inside cells, :data:`RIM_COVERAGE` on the rim, 0 elsewhere.

    The rim: a pixel outside every cell within :data:`ilt.isf.fine.RIM_PX` of one takes
    each ``Phi_n`` of the nearest pixel inside, scaled by ``s``, the lesser of ``photo /
    Phi_0`` there (no more light than the photo holds) and the photo's ratio to that
    pixel's (a pixel partly background past a silhouette holds that share of it), clipped
    to [0, 1]: the indirect light is smooth. Its bounce 1 is the rest of the photo. At the
    faint rim of a scan's light the lit test lets pixels in or out by the noise; they got
    no bounces at all, and held most of the error of bounce 1 (docs/fullres.md "The
    rim"). Where the photo is dark (background past a silhouette) ``s`` is 0 and so are
    the bounces.

    Inside cells: :class:`PhotoBound` (``Phi_0`` no more than the photo, the excess given to
    the cell's other pixels); ``report`` (a dict), when given, gets ``bounded_pixels``: how
    many pixels inside cells held more indirect light than the photo, and ``bound``: what
    bounded them. ``photo_noise``: the photo's own noise, a model a channel, or a function of
    the photo that measures it (:func:`photo_noise_models`: called only when some pixel's
    ``Phi_0`` is over the photo itself); the bound is then the photo plus
    :data:`BOUND_SIGMAS` of its sigma, so that its noise stays in bounce 1.
    Memory: two fields of the pixels inside cells in float64 at a time, and the outputs.
    """
    image = np.asarray(photo)
    shape, m, count = image.shape, fine.geometry.m, decomposition.count
    flat = image.reshape(shape[0] * shape[1], -1)
    bounces = np.asarray(decomposition.bounces).reshape(count, m, -1)
    residual = bounces.sum(axis=0) + np.asarray(decomposition.residual).reshape(m, -1)   # r_0 = L
    weights = bounces / t1[None, :, None] if weights is None else np.asarray(weights).reshape(count, m, -1)
    per_cell = fine.per_cell(weights).reshape(-1, m, count, flat.shape[1])
    basis = fine.geometry.basis(fine.degree)
    slopes = fine.neighbour_slopes(basis) if neighbour_slopes else None
    area = np.maximum(fine.geometry.area, 1.0)[:, None]
    inside = fine.geometry.inside
    excluded = None if excluded is None or not excluded.any() else excluded.reshape(-1)
    rim, nearest = fine.rim

    def image_of(values_inside, values_rim, outside=None):
        full = np.zeros(flat.shape, np.float32) if outside is None else outside.astype(np.float32)
        full[inside] = values_inside
        full[rim] = values_rim
        if excluded is not None:
            full[excluded] = 0.0 if outside is None else outside[excluded]
        return full.reshape(shape)

    # flat cells: each bounce's plane from its own cell means (ilt/isf/slopes.py), so that bounce n's
    # image gets the plane of bounce n's light; Phi_n's is the sum of the later bounces' and r_N's
    planes = [None] * count
    if slopes is not None:
        later = slopes.coefficients((residual - bounces.sum(axis=0)) / area)   # r_N's
        for n in range(count - 1, -1, -1):
            planes[n] = later
            if n:
                later = later + slopes.coefficients(bounces[n] / area)
    out = {}
    previous = previous_rim = scale = bound = None
    for n in range(count):
        residual = residual - bounces[n]                               # r_(n+1)
        terms = per_cell[:, :, n] if planes[n] is None else _add_planes(per_cell[:, :, n], planes[n])
        phi = fine.field(residual, terms, basis)                       # Phi_n
        if n == 0:
            bound, models = _photo_bound(flat[inside], phi, fine.geometry.label, m,
                                         None if excluded is None else excluded[inside], photo_noise, image,
                                         inside)
            if report is not None:
                report.update(bounded_pixels=bound.bounded_pixels, bound="the photo" if models is None else
                              f"the photo + {BOUND_SIGMAS:g} sigma of its own noise")
        phi = bound.apply(phi)
        if n == 0:
            scale = _rim_scale(flat[rim], phi[nearest], flat[inside[nearest]])   # s, of each rim pixel
        phi_rim = scale * phi[nearest]
        if n == 0:
            out["bounce-1"] = image_of(flat[inside] - phi, flat[rim] - phi_rim)
            out["indirect"] = image_of(phi, phi_rim)
        else:
            out[f"bounce-{n + 1}"] = image_of(previous - phi, previous_rim - phi_rim)
        previous, previous_rim = phi, phi_rim
    out["residual"] = image_of(previous, previous_rim, flat)
    coverage = fine.coverage().reshape(-1)
    coverage[rim] = RIM_COVERAGE
    if excluded is not None:
        coverage[excluded] = 0.0
    out["coverage"] = coverage.reshape(fine.shape)
    return {name: out[name] for name in [f"bounce-{n}" for n in range(1, count + 1)]
            + ["indirect", "residual", "coverage"]}


#: coverage.exr's value on the rim (inside cells: 1)
RIM_COVERAGE = 0.5

#: a pixel's indirect light is bounded by its photo plus this many of the photo's own noise
#: sigmas (:func:`photo_noise_models`): a bound at the noisy photo itself cut each pixel where the
#: noise read low, and carried the photo's noise into every bounce past the first
BOUND_SIGMAS = 3.0
#: bisection steps for each cell's give-back factor (on log c; the last step is exact)
BISECTIONS = 40


def photo_noise_models(image: np.ndarray) -> list | None:
    """Each channel's noise of a photo (H, W[, c]), from the photo's own pixels: its
    variance against its level as build-isf measures a beam frame's
    (:func:`ilt.isf.noise.fit_frame_noise`: residuals from the 4 neighbours' mean, binned
    by level; a :class:`~ilt.isf.noise.FrameNoise` or None a channel). None where no
    channel shows noise (a noise-free render)."""
    from ilt.isf.noise import fit_frame_noise

    image = np.asarray(image)
    planes = image.reshape(image.shape[0], image.shape[1], -1)
    height = planes.shape[0]
    # a large photo is fitted on bands of 16 rows every 64 (each its own frame to the fit, which
    # samples at most 250,000 pixels anyway): a quarter of the filtering
    bands = [slice(0, height)] if planes.shape[0] * planes.shape[1] <= 4_000_000 else \
        [slice(r, r + 16) for r in range(0, height - 15, 64)]
    models = [fit_frame_noise([planes[b, :, c] for b in bands]) for c in range(planes.shape[2])]
    return models if any(model is not None for model in models) else None


class PhotoBound:
    """Each pixel's indirect light inside a cell no more than the photo's light there.

    A cell's ``Phi_0`` (the indirect light, all bounces past the first) is its mean and a
    plane: it knows nothing of a pixel in it that is background past the scene's silhouette
    (the lit test, which judges local means, lets in about 2 px of it at a bright edge when
    the frames are noisy), partly background, or in a shadow of the photo's own light. There
    it can hold more than the photo, and bounce 1 goes negative by as much as the others are
    too bright. Light is never negative, so ``Phi_0 <= max(photo, 0)``, plus ``margin`` (3
    sigma of a noisy photo's own noise, which belongs in bounce 1).

    Each pixel with positive ``Phi_0`` more than its photo keeps the share ``rho = photo /
    Phi_0`` of every field ``Phi_n`` (the later bounces and the residual are its own light
    too). In a cell whose photo can hold all of its indirect light, what the bounded pixels
    gave up of each field goes to the cell's other pixels, where the bounded ``Phi_0`` is
    ``min(c Phi_0, photo)``, ``c >= 1`` the one factor that keeps the cell's sum, each
    field's in proportion to what ``Phi_0`` gained there: every image still integrates over
    every cell to its sample-level bounce. A cell whose photo holds less light in all than
    its indirect light (the sample level's own bounce 1 negative there) has no such ``c``:
    its pixels keep ``rho`` of each field and nothing more, and its integrals are the
    bounded ones. Saturated pixels (``excluded``) are left as they are.

    photo, phi0 : (n, c) at the pixels inside cells; label : (n,) their cells; margin :
    (n, c) or None, added to ``max(photo, 0)`` (the photo's noise, :data:`BOUND_SIGMAS`).
    """

    def __init__(self, photo: np.ndarray, phi0: np.ndarray, label: np.ndarray, m: int,
                 excluded: np.ndarray | None = None, margin: np.ndarray | None = None):
        self.label, self.m = label, m
        self.rho = np.ones(phi0.shape)
        self.share = np.zeros(phi0.shape)          # of a kept cell's change, per pixel (sums to 1)
        self.kept = np.zeros((m, phi0.shape[1]), bool)
        self.any = False                           # a pixel over the photo in some channel
        for c in range(phi0.shape[1]):
            a, p = np.asarray(phi0[:, c], np.float64), np.maximum(np.asarray(photo[:, c], np.float64), 0.0)
            if margin is not None:
                p = p + margin[:, c]
            over = a > p
            if excluded is not None:
                over &= ~excluded
            if not over.any():
                continue
            self.any = True
            touched = np.zeros(m, bool)
            touched[label[over]] = True
            pick = touched[label] & (a > 0)
            if excluded is not None:
                pick &= ~excluded
            sel = np.flatnonzero(pick)
            lab, aa, pp = label[sel], a[sel], p[sel]
            self.rho[sel, c] = np.minimum(aa, pp) / aa
            total, room = np.bincount(lab, aa, m), np.bincount(lab, pp, m)
            feasible = touched & (room >= total)
            held = feasible[lab]          # the give-back only where a cell's photo can hold its light
            every = bool(held.all())
            lab_h, aa_h, pp_h = (lab, aa, pp) if every else (lab[held], aa[held], pp[held])
            gained_h = np.maximum(np.minimum(self._factor(lab_h, aa_h, pp_h, total)[lab_h] * aa_h, pp_h)
                                  - np.minimum(aa_h, pp_h), 0.0)
            if every:
                gained = gained_h
            else:
                gained = np.zeros(sel.size)
                gained[held] = gained_h
            weight = np.bincount(lab, gained, m)
            self.share[sel, c] = np.where(weight[lab] > 0, gained / np.where(weight[lab] > 0, weight[lab], 1.0), 0.0)
            self.kept[:, c] = feasible & (weight > 0)

    def _factor(self, lab, aa, pp, total) -> np.ndarray:
        """(m,) c of each cell: ``sum min(c a, p) = sum a`` (where the photo can hold it).
        A pixel with ``p < a`` is bounded at every ``c >= 1``: its ``p`` is a constant of the
        cell's sum, and the bisection runs on the others only."""
        m = self.m
        ratio = pp / aa
        top = np.zeros(m)
        np.maximum.at(top, lab, ratio)
        fixed = ratio < 1.0
        base = np.bincount(lab[fixed], pp[fixed], m)
        lab, aa, pp = lab[~fixed], aa[~fixed], pp[~fixed]
        lo, hi = np.zeros(m), np.log(np.maximum(top, 1.0))
        for _ in range(BISECTIONS):               # on log c, every cell at once
            mid = 0.5 * (lo + hi)
            low = base + np.bincount(lab, np.minimum(np.exp(mid)[lab] * aa, pp), m) < total
            lo, hi = np.where(low, mid, lo), np.where(low, hi, mid)
        # exact on the pixels the bisection's c bounds: the rest share what those leave
        capped = np.exp(hi)[lab] * aa >= pp
        free = np.bincount(lab, np.where(capped, 0.0, aa), m)
        rest = total - base - np.bincount(lab, np.where(capped, pp, 0.0), m)
        return np.maximum(np.where(free > 0, rest / np.where(free > 0, free, 1.0), np.exp(hi)), 1.0)

    @property
    def bounded_pixels(self) -> int:
        """The pixels over the photo (in any channel)."""
        return int(np.count_nonzero((self.rho < 1).any(axis=1)))

    def apply(self, phi: np.ndarray) -> np.ndarray:
        """``Phi_n`` (n, c) bounded: ``rho`` of it per pixel, each kept cell's loss given back."""
        if not self.any:
            return phi
        out = phi * self.rho
        for c in range(phi.shape[1]):
            if not self.kept[:, c].any():
                continue
            change = np.bincount(self.label, phi[:, c] - out[:, c], self.m)
            out[:, c] += np.where(self.kept[:, c], change, 0.0)[self.label] * self.share[:, c]
        return out


def _photo_bound(photo, phi0, label, m, excluded, photo_noise, image, inside):
    """:class:`PhotoBound` of ``Phi_0`` and the photo's noise models it used (None: none).
    ``photo_noise`` a function is called on ``image`` only when some pixel is over the
    photo itself: a margin can only take pixels out of the bound. ``inside``: the indices of
    ``photo``'s pixels in ``image``'s flattened grid."""
    models = photo_noise
    if callable(photo_noise):
        over = np.asarray(phi0) > np.maximum(np.asarray(photo, np.float64), 0.0)
        if excluded is not None:
            over &= ~excluded[:, None]
        models = photo_noise(image) if over.any() else None
    margin = None if models is None else _margin(image, inside, models)
    return PhotoBound(photo, phi0, label, m, excluded, margin), models


def _margin(image: np.ndarray, inside, models: list) -> np.ndarray:
    """(n, c) :data:`BOUND_SIGMAS` of the noise sigma of each pixel ``inside`` the cells, 0
    in a channel without a model. The sigma is the model's at the pixel's level, not at its
    own reading: under a path tracer's noise, whose sigma is a share of the light, a pixel
    that read low got a margin as low and was cut, and the photo's noise went into every
    later bounce (the M's flashlight bounce 2 at 4 samples: 0.10 of its light from the
    photo's noise alone). The level is the median of the 5 x 5 square about the pixel
    (:data:`ilt.isf.noise.LEVEL_WINDOW`; the model's bins are by that square's mean): where
    the light is even, the two agree to the noise's skew; beside an edge the median keeps
    the pixel's own side, so the background past a silhouette, dark beside bright surfaces,
    is still bounded at its own dark level (the mean took half the surface's light there)."""
    import cv2

    from ilt.isf.noise import LEVEL_WINDOW

    planes = np.asarray(image).reshape(image.shape[0], image.shape[1], -1)
    out = np.zeros((len(inside), len(models)))
    for c, model in enumerate(models):
        if model is not None:
            median = cv2.medianBlur(np.ascontiguousarray(planes[..., c], np.float32), LEVEL_WINDOW)
            level = np.maximum(median.reshape(-1)[inside].astype(np.float64), 0.0)
            out[:, c] = BOUND_SIGMAS * np.sqrt(np.maximum(model.pixel_variance(level), 0.0))
    return out


def _rim_scale(photo: np.ndarray, phi0: np.ndarray, photo_inside: np.ndarray) -> np.ndarray:
    """(n, c) the share of the nearest inside pixel's indirect light each rim pixel takes:
    ``photo / phi0`` (no more than the photo holds) and ``photo / photo_inside`` (a pixel
    partly background past a silhouette holds that share of its neighbour's light), the
    lesser, clipped to [0, 1]; 0 where ``phi0`` or ``photo_inside`` is not positive."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.minimum(np.where(phi0 > 0, photo / np.where(phi0 > 0, phi0, 1.0), 0.0),
                           np.where(photo_inside > 0, photo / np.where(photo_inside > 0, photo_inside, 1.0), 0.0))
    return np.clip(ratio, 0.0, 1.0)


def _add_planes(terms: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """``terms`` (K, m, c) with the ``dx``, ``dy`` planes (2, m, c) added to its first two."""
    out = terms.copy()
    out[:2] += planes.astype(out.dtype)
    return out
