"""Error measures against the simulator's ground truth (paper Sec. 4, Fig. 5).

The paper compares ``Cn T`` with rendered n-bounce ISFs by the squared distance
between corresponding *normalised* columns (3.45e-34 for n = 1 to 8.59e-13 for n = 3
on the "M" scene, with a forward tracer truncated at 7 bounces).
"""

from __future__ import annotations

import numpy as np

from ilt.transport.operators import CancellationOperator, bounce_images


def normalised_column_distances(computed: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Squared distances between unit-normalised columns, shape (m,) float64.

    Columns whose truth is exactly zero compare the computed column's norm relative to
    the largest column of ``computed`` instead (there is no direction to compare).
    """
    cn = np.linalg.norm(computed, axis=0)
    tn = np.linalg.norm(truth, axis=0)
    out = np.empty(computed.shape[1])
    live = tn > 0
    safe_cn = np.where(cn > 0, cn, 1.0)
    out[live] = np.sum((computed[:, live] / safe_cn[live] - truth[:, live] / tn[live]) ** 2, axis=0)
    scale = cn.max() if cn.max() > 0 else 1.0
    out[~live] = (cn[~live] / scale) ** 2
    return out


def bounce_isf_errors(
    operator: CancellationOperator, T: np.ndarray, truth: np.ndarray
) -> list[dict]:
    """The paper's Fig. 5 measure for n = 1..N.

    Parameters
    ----------
    T : (m, m) the ISF the operator was built from.
    truth : (N, m, m) true n-bounce ISFs ``A^(n-1) T1`` (any column scaling).

    Returns one dict per bounce: ``n``, ``mean`` and ``max`` squared distance.
    """
    computed = bounce_images(operator, T, n_bounces=truth.shape[0]).bounces
    rows = []
    for n, (c, t) in enumerate(zip(computed, truth), start=1):
        d = normalised_column_distances(c, t)
        rows.append({"n": n, "mean": float(d.mean()), "max": float(d.max())})
    return rows


def relative_errors(computed: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``||computed[n] - truth[n]|| / ||truth[n]||`` per bounce n, shape (N,)."""
    axes = tuple(range(1, truth.ndim))
    num = np.sqrt(np.sum((computed - truth) ** 2, axis=axes))
    den = np.sqrt(np.sum(truth**2, axis=axes))
    return num / np.where(den > 0, den, 1.0)


def noise_amplification(T: np.ndarray, noisy_T: np.ndarray, computed: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Error amplification per bounce: ``(||Ln - Ln*|| / ||Ln*||) / (||dT||_F / ||T||_F)``.

    ``computed`` and ``truth`` are (N, m[, k]) bounces from the noisy and the true T;
    a value of 5 means the n-th bounce is 5 times as wrong, relatively, as T.
    """
    relative_noise = np.linalg.norm(noisy_T - T) / np.linalg.norm(T)
    return relative_errors(computed, truth) / relative_noise
