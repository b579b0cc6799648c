"""Whether a result can be trusted (DESIGN.md sec. 4): figures of an operator (condition,
smallest diagonal of T, spectral radius of ``A = I - C1``) and of a decomposition
(closure, negatives in each bounce), each with warnings that quote them.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.linalg import ArpackError, ArpackNoConvergence, LinearOperator, eigs

from ilt.transport.operators import CancellationOperator, Decomposition
from ilt.transport.scan import IsfMatrix

#: condition estimate past which results are flagged as unreliable
CONDITION_WARN = 1e10

#: relative accuracy of ``spectral_radius_A`` (ARPACK's stopping test, below)
RHO_TOL = 1e-3

#: Krylov basis size of that estimate: the dominant eigenvalue of a scene's ``A`` (the
#: Perron root of a non-negative matrix) stands apart, so a small basis finds it in a
#: few applies of ``C1``; each apply reads all the factors (4.8 s at m = 12288 took
#: ARPACK's default basis of 20 and tolerance 1e-8)
RHO_NCV = 6

#: within this of 1 the estimate is refined to ``RHO_REFINED_TOL``, so ``rho >= 1``
#: (the warning) is decided as sharply as a tight estimate decides it
RHO_REFINE_BAND = 10 * RHO_TOL

RHO_REFINED_TOL = 1e-8


def spectral_radius(operator: CancellationOperator, seed: int = 0, tol: float = RHO_TOL) -> float:
    """Largest ``|eigenvalue|`` of ``A = I - C1`` from matrix-vector products (ARPACK).

    For a physical scene ``A = P K`` is non-negative with row sums < 1, so the value is
    < 1 and the bounce series converges; >= 1 means ``T`` is not a Lambertian ISF
    (noise, flare, a bad spot).

    Accuracy: ARPACK stops when the Ritz pair's residual is at most ``tol`` times the
    value, ``||A x - rho x|| <= tol rho ||x||``: ``rho`` is an eigenvalue of a matrix
    within ``tol rho`` of A (relative error ``tol`` where A's dominant eigenvector is
    well conditioned, as a Perron vector is). A value within ``RHO_REFINE_BAND`` of 1
    is recomputed to ``RHO_REFINED_TOL``.
    """
    m = operator.m
    if m <= 2:
        C1 = operator.apply(np.eye(m))
        return float(np.max(np.abs(np.linalg.eigvals(np.eye(m) - C1))))
    a = LinearOperator((m, m), matvec=lambda x: x - operator.apply(np.ravel(x)), dtype=np.float64)
    v0 = np.random.default_rng(seed).uniform(0.5, 1.0, m)
    # a loose tolerance with a small basis; ARPACK needs 2 < ncv <= m (k = 1)
    ncv = min(m, RHO_NCV if tol > RHO_REFINED_TOL else 20)
    try:
        vals = eigs(a, k=1, which="LM", v0=v0, tol=tol, ncv=ncv, maxiter=max(1000, 10 * m),
                    return_eigenvectors=False)
    except (ArpackNoConvergence, ArpackError):
        return _power_iteration(operator, v0)
    rho = float(np.max(np.abs(vals)))
    if tol > RHO_REFINED_TOL and abs(rho - 1) <= RHO_REFINE_BAND:
        return spectral_radius(operator, seed, tol=RHO_REFINED_TOL)
    return rho


def _power_iteration(operator: CancellationOperator, v: np.ndarray, steps: int = 500) -> float:
    rate = 0.0
    v = v / np.linalg.norm(v)
    for _ in range(steps):
        w = v - operator.apply(v)
        rate = float(np.linalg.norm(w))
        if rate == 0:
            return 0.0
        v = w / rate
    return rate


def operator_diagnostics(T: np.ndarray | IsfMatrix, operator: CancellationOperator) -> dict:
    """Figures that say whether ``C1`` can be trusted (DESIGN.md sec. 4).

    Returns a JSON-ready dict: ``m``, ``condition_estimate`` (1-norm, of the
    column-normalised T), ``min_diagonal`` (of the column-normalised T) and its beam,
    ``spectral_radius_A``, and ``warnings`` (sentences quoting the figures); ``condition_warning``
    is the one of them that is about noise (a bound on its amplification), which
    ``ilt decompose`` logs at INFO when it measured the bounces' noise itself.
    """
    diag = np.diagonal(T.T if isinstance(T, IsfMatrix) else T) / operator.column_norms
    jmin = int(np.argmin(diag))
    rho = spectral_radius(operator)
    cond = 1.0 / operator.rcond
    warnings = []
    condition = None
    if cond > CONDITION_WARN:
        condition = (f"condition estimate of T is {cond:.3g} (> {CONDITION_WARN:.0e}): noise in T is amplified by up "
                     "to that factor")
        warnings.append(condition)
    if diag[jmin] <= 0:
        warnings.append(
            f"T[{jmin}, {jmin}] = {diag[jmin]:.3g} <= 0: beam {jmin} does not light its own sample pixel"
        )
    if rho >= 1:
        warnings.append(
            f"spectral radius of A = I - C1 is {rho:.6g} >= 1: the bounce series diverges, "
            "T is not the ISF of a physical Lambertian scene (glossy or specular reflectance, flare, noise in T "
            "or a wrong spot)"
        )
    return {
        "m": operator.m,
        "condition_estimate": cond,
        "min_diagonal": float(diag[jmin]),
        "min_diagonal_beam": jmin,
        "spectral_radius_A": rho,
        "warnings": warnings,
        # the one warning about what noise could do: moot once the bounces' noise is measured
        "condition_warning": condition,
    }


#: a sample counts as negative below -NEGATIVE_FLOOR * max|L|: float32 rounding of
#: EXR data (~1e-7 relative, mildly amplified by C1) is not a physical fault
NEGATIVE_FLOOR = 1e-6

#: a bounce's negatives warn when they hold more than this share of its 2-norm: a
#: negative sample is wrong by at least its own size, so the bounce is at least that
#: wrong (the cells' discretisation leaves 0.1-4% on healthy scans, a glossy scene 11-56%)
NEGATIVE_WARN = 0.10

#: ... and when its worst sample is below -NEGATIVE_Z sigma of its own noise (when known):
#: past what the noise of T and of the photo can make of a non-negative bounce
NEGATIVE_Z = 5.0

#: bounces 1 and 2 warn when their noise (when known) exceeds this share of their 2-norm
NOISE_WARN = 0.20

#: the bounces NOISE_WARN watches: the higher ones hold little light and are noisier by nature
NOISE_WATCHED = 2

#: closure error past which a warning is raised
CLOSURE_WARN = 1e-10


def _bounce_range(bounces: list[int]) -> str:
    if len(bounces) == 1:
        return f"bounce {bounces[0]}"
    if bounces == list(range(bounces[0], bounces[-1] + 1)):
        return f"bounces {bounces[0]}-{bounces[-1]}"
    return "bounces " + ", ".join(map(str, bounces))


def decomposition_diagnostics(photo: np.ndarray, decomposition: Decomposition, sigma: np.ndarray | None = None,
                              where=None, unjudged: str = "the noise of T is not known: give --noise") -> dict:
    """Closure error, bounce energies, negatives and noise of one decomposition.

    ``closure_error`` is ``||L - sum Ln - rN|| / ||L||`` (must be at rounding level);
    ``negative_share[n]`` the fraction of samples of bounce n+1 below
    ``-NEGATIVE_FLOOR * max|L|`` and ``most_negative[n]`` its smallest value over
    ``max|L|``; ``negative_energy[n]`` the 2-norm of its negative part over its own
    2-norm (a lower bound on its relative error: physical bounce images are non-negative).

    ``sigma``: each bounce sample's noise (the shape of ``decomposition.bounces``, from
    :func:`ilt.decompose.noise.bounce_sigma`), or None when unknown. With it,
    ``noise_share[n]`` is bounce n+1's noise over its 2-norm and ``worst_sigma[n]`` its
    most negative sample in units of that sample's sigma. ``where(i)`` names sample i in
    the messages (a pixel), default "sample i"; ``unjudged``: why sigma is None, for them.

    ``warnings``: one sentence per problem, for the user to act on: negatives past
    :data:`NEGATIVE_WARN` (and, with sigma, past :data:`NEGATIVE_Z` sigma), bounces 1-2
    noisier than :data:`NOISE_WARN`, a closure error; ``notes``: the same figures in one
    sentence when all is well (an INFO line).
    """
    photo = np.asarray(photo, dtype=np.float64)
    bounces = decomposition.bounces
    total = np.linalg.norm(photo)
    peak = float(np.abs(photo).max()) or 1.0
    rebuilt = bounces.sum(axis=0) + decomposition.residual
    closure = float(np.linalg.norm(photo - rebuilt) / total) if total > 0 else 0.0
    axes = tuple(range(1, bounces.ndim))
    N = bounces.shape[0]
    flat = bounces.reshape(N, -1)
    negative = (bounces < -NEGATIVE_FLOOR * peak).mean(axis=axes)
    most_negative = np.minimum(bounces.min(axis=axes) / peak, 0.0)
    norms = np.linalg.norm(flat, axis=1)
    safe = np.where(norms > 0, norms, 1.0)
    negative_energy = np.linalg.norm(np.minimum(flat, 0.0), axis=1) / safe
    residual_share = float(np.linalg.norm(decomposition.residual) / total) if total > 0 else 0.0
    where = where or (lambda i: f"sample {i}")
    samples = bounces.shape[1] if bounces.ndim > 1 else 1
    out = {}
    warnings, notes = [], []
    if closure > CLOSURE_WARN:
        warnings.append(f"closure error {closure:.3g} > {CLOSURE_WARN:.0e}: the decomposition lost light")
    if sigma is not None:
        s = np.asarray(sigma, dtype=np.float64).reshape(N, -1)
        noise_share = np.linalg.norm(s, axis=1) / safe
        z = np.where(flat < 0, flat / np.maximum(s, 1e-12 * peak), 0.0)
        worst = np.argmin(z, axis=1)
        worst_z = z[np.arange(N), worst]
        flagged = [n + 1 for n in range(N) if negative_energy[n] > NEGATIVE_WARN and worst_z[n] < -NEGATIVE_Z]
        out.update(noise_share=noise_share.tolist(), worst_sigma=worst_z.tolist())
    else:
        worst = np.argmin(flat, axis=1)
        flagged = [n + 1 for n in range(N) if negative_energy[n] > NEGATIVE_WARN]
    if flagged:
        n = max(flagged, key=lambda k: negative_energy[k - 1])
        i = int(worst[n - 1]) // (flat.shape[1] // samples)
        if sigma is not None:
            worst_text = f"bounce {n}, {worst_z[n - 1]:.3g} sigma at {where(i)}"
            beyond = "beyond the noise"
        else:
            worst_text = f"bounce {n}, {flat[n - 1].min() / peak:.3g} of the photo's peak at {where(i)}"
            beyond = f"(not judged against their noise: {unjudged})"
        warnings.append(
            f"{_bounce_range(flagged)} {'holds' if len(flagged) == 1 else 'hold'} negatives {beyond}: at least {negative_energy[n - 1]:.0%} of bounce "
            f"{n} is wrong (worst: {worst_text}); T does not match this scene: see the report's spots and "
            "isf/lambertian.png")
    if sigma is not None:
        noisy = [n + 1 for n in range(min(N, NOISE_WATCHED)) if noise_share[n] > NOISE_WARN]
        if noisy:
            n = max(noisy, key=lambda k: noise_share[k - 1])
            its = "its" if len(noisy) == 1 else f"bounce {n}'s"
            warnings.append(
                f"{_bounce_range(noisy)} {'is' if len(noisy) == 1 else 'are'} noisy: {its} noise is "
                f"{noise_share[n - 1]:.0%} of its signal; longer exposures, more frames per beam or --regularise "
                "lower it")
    if not warnings:
        k = int(np.argmax(negative_energy))
        parts = []
        if sigma is not None:
            parts.append(f"noise {noise_share.min():.2g}-{noise_share.max():.2g} of each bounce")
        if negative_energy[k] > 0:
            parts.append(f"negatives at most {negative_energy[k]:.2g} of a bounce (bounce {k + 1}; warned past "
                         f"{NEGATIVE_WARN:.0%})")
        notes.append("bounces as expected: " + ("; ".join(parts) if parts else "no negatives"))
    if decomposition.stopped_early:
        stop = f"stopped after bounce {decomposition.count}: ||Ln||/||L|| < tol = {decomposition.tol:g}"
    else:
        stop = f"computed all {decomposition.count} requested bounces"
    return {
        "bounces": decomposition.count,
        "requested_bounces": decomposition.requested,
        "stopped_early": decomposition.stopped_early,
        "stop_reason": stop,
        "relative_norms": np.asarray(decomposition.relative_norms).tolist(),
        "residual_share": residual_share,
        "closure_error": closure,
        "negative_share": negative.tolist(),
        "most_negative": most_negative.tolist(),
        "negative_energy": negative_energy.tolist(),
        **out,
        "noise_judged": sigma is not None,
        "warnings": warnings,
        "notes": notes,
    }
