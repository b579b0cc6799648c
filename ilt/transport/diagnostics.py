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
    ``spectral_radius_A``, and ``warnings`` (sentences quoting the figures).
    """
    diag = np.diagonal(T.T if isinstance(T, IsfMatrix) else T) / operator.column_norms
    jmin = int(np.argmin(diag))
    rho = spectral_radius(operator)
    cond = 1.0 / operator.rcond
    warnings = []
    if cond > CONDITION_WARN:
        warnings.append(
            f"condition estimate of T is {cond:.3g} (> {CONDITION_WARN:.0e}): noise in T is amplified by up to that factor"
        )
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
    }


#: share of negative samples in a bounce past which a warning is raised
NEGATIVE_WARN = 0.01

#: a sample counts as negative below -NEGATIVE_FLOOR * max|L|: float32 rounding of
#: EXR data (~1e-7 relative, mildly amplified by C1) is not a physical fault
NEGATIVE_FLOOR = 1e-6

#: closure error past which a warning is raised
CLOSURE_WARN = 1e-10


def decomposition_diagnostics(photo: np.ndarray, decomposition: Decomposition) -> dict:
    """Closure error, bounce energies and negative shares of one decomposition.

    ``closure_error`` is ``||L - sum Ln - rN|| / ||L||`` (must be at rounding level);
    ``negative_share[n]`` the fraction of samples of bounce n+1 below
    ``-NEGATIVE_FLOOR * max|L|`` (physical bounce images are non-negative; noise in T
    makes some negative), ``most_negative[n]`` its smallest value over ``max|L|``.
    """
    photo = np.asarray(photo, dtype=np.float64)
    total = np.linalg.norm(photo)
    peak = float(np.abs(photo).max()) or 1.0
    rebuilt = decomposition.bounces.sum(axis=0) + decomposition.residual
    closure = float(np.linalg.norm(photo - rebuilt) / total) if total > 0 else 0.0
    axes = tuple(range(1, decomposition.bounces.ndim))
    negative = (decomposition.bounces < -NEGATIVE_FLOOR * peak).mean(axis=axes)
    most_negative = np.minimum(decomposition.bounces.min(axis=axes) / peak, 0.0)
    residual_share = float(np.linalg.norm(decomposition.residual) / total) if total > 0 else 0.0
    warnings = []
    if closure > CLOSURE_WARN:
        warnings.append(f"closure error {closure:.3g} > {CLOSURE_WARN:.0e}: the decomposition lost light")
    for n, share in enumerate(negative, start=1):
        if share > NEGATIVE_WARN:
            warnings.append(
                f"bounce {n}: {share:.1%} of samples are negative, down to {most_negative[n - 1]:.3g} of the "
                "photo's peak (noise in T or in the photo)"
            )
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
        "warnings": warnings,
    }
