"""Run time against error: solvers of ``C1`` + bounce decomposition, timed in one process.

For each scene, size m and noise level sigma (Gaussian, relative to max |T|) the
benchmark times, as the median of repeats,

- ``scipy``: the bare baseline, ``scipy.linalg.inv(T)`` (getrf + getri), ``C1 = T1 T^-1``
  formed, then the bounce recursion with matrix products;
- each ilt solver (``dense``, ``mixed``, ``blocks``, ``series``, ``compressed``; see
  :mod:`ilt.solvers`): build the operator and split a batch of photos into N bounces
  (``compressed`` to the true sigma, on the scene's grid order); for noisy T also
  ``regularised`` (:mod:`ilt.regularise`, with the true sigma, then ``dense``). A
  solver that refuses T (``series`` on a dense T) gets a row saying why, no figures;

and measures each against the simulator's exact truth: the worst relative error of
any bounce ``max_n ||Ln - Ln*|| / ||Ln*||``, the error per bounce, the pooled error of
all bounces together ``||L - L*|| / ||L*||`` (stacked: weighted by each bounce's
energy, where the worst bounce is usually the faintest), the relative error
of ``diag(T1)``, the closure error, the error amplification (bounce error over the
relative noise in T) and the peak memory it allocates (tracemalloc).
"""

from __future__ import annotations

import statistics
import time
import tracemalloc
from dataclasses import asdict, dataclass

import numpy as np
import scipy.linalg

from ilt.evaluate import relative_errors
from ilt.regularise import BiasVariance, regularise_isf
from ilt.sim import ILLUMINATIONS, make_scene
from ilt.solvers import build_operator
from ilt.transport import TransportError, bounce_images

QUICK_SIZES = (256, 512, 1024)
FULL_SIZES = (256, 512, 1024, 2048, 4096)
SOLVERS = ("scipy", "dense", "mixed", "blocks", "series", "compressed", "regularised")


@dataclass
class BenchRow:
    """One solver on one case; a solver that refused T has ``refused`` (its reason)
    and no figures."""

    scene: str
    m: int
    noise: float
    solver: str
    batch: int
    bounces: int
    seconds: float | None = None
    ratio_to_scipy: float | None = None
    peak_mib: float | None = None
    bounce_error: float | None = None
    bounce_errors: list | None = None
    pooled_error: float | None = None
    t1_error: float | None = None
    closure_error: float | None = None
    amplification: float | None = None
    refused: str | None = None


def _scipy(T, photos, n_bounces):
    inv = scipy.linalg.inv(T)
    t1 = 1.0 / np.diag(inv)
    C1 = t1[:, None] * inv
    r, out = photos.copy(), []
    for _ in range(n_bounces):
        ln = C1 @ r
        r -= ln
        out.append(ln)
    return t1, np.stack(out), r


def _solver(name, layout=None, noise=0.0, samples=None):
    def run(T, photos, n_bounces):
        if name == "regularised":  # denoise T (edge-aware filter, discrepancy principle), then dense
            T = regularise_isf(T, layout, noise)[0]
        if name == "compressed":  # to the noise floor, ordered by the sample pixels, as `ilt decompose --noise`
            op, _ = build_operator(T, name, noise or None, points=samples)
        else:
            op, _ = build_operator(T, "dense" if name == "regularised" else name)
        dec = bounce_images(op, photos, n_bounces)
        return op.t1, dec.bounces, dec.residual
    return run


def median_time(fn, repeats: int, *args):
    """(median seconds of ``repeats`` calls of ``fn(*args)``, the last result)."""
    times, result = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn(*args)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), result


def _peak_mib(fn, *args) -> float:
    tracemalloc.start()
    try:
        fn(*args)
        return tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()


def scene_batch(scene, batch: int, n_bounces: int, seed: int = 0):
    """A batch of photos (m, batch) under the scene's illuminations with random
    non-negative mixtures, and their true bounces (N, m, batch)."""
    direct = np.stack([scene.illumination(kind) for kind in ILLUMINATIONS], axis=1)
    weights = np.random.default_rng(seed).uniform(0, 1, (direct.shape[1], batch))
    l1 = direct @ weights
    truth = [l1]
    for _ in range(n_bounces - 1):
        truth.append(scene.A @ truth[-1])
    truth = np.stack(truth)
    photos = np.linalg.solve(np.eye(scene.m) - scene.A, l1)
    return photos, truth


def bench_case(scene_name: str, m: int, noise: float = 0.0, solvers=SOLVERS, batch: int = 16,
               n_bounces: int = 8, repeats: int = 3, seed: int = 0) -> list[BenchRow]:
    """One scene, size and noise level: a row per solver, the scipy baseline first."""
    scene = make_scene(scene_name, beams=m)
    T, scale = scene.isf()
    t1_true = scene.direct / scale
    photos, truth = scene_batch(scene, batch, n_bounces, seed)
    noisy = T + noise * np.abs(T).max() * np.random.default_rng(seed + 1).normal(size=T.shape) if noise else T
    relative_noise = np.linalg.norm(noisy - T) / np.linalg.norm(T)
    rows, baseline = [], None
    for name in ("scipy", *[s for s in solvers if s != "scipy"]):
        if name == "regularised" and noise == 0:
            continue  # nothing to remove
        fn = _scipy if name == "scipy" else _solver(name, scene.layout, noise * np.abs(T).max(), scene.samples)
        try:
            seconds, (t1, bounces, residual) = median_time(fn, repeats, noisy, photos, n_bounces)
        except TransportError as exc:
            rows.append(BenchRow(scene=scene_name, m=scene.m, noise=noise, solver=name, batch=batch,
                                 bounces=n_bounces, refused=str(exc)))
            continue
        baseline = seconds if name == "scipy" else baseline
        errors = relative_errors(bounces, truth)
        closure = np.linalg.norm(photos - bounces.sum(axis=0) - residual) / np.linalg.norm(photos)
        rows.append(BenchRow(
            scene=scene_name, m=scene.m, noise=noise, solver=name, batch=batch, bounces=n_bounces,
            seconds=seconds, ratio_to_scipy=seconds / baseline, peak_mib=_peak_mib(fn, noisy, photos, n_bounces),
            bounce_error=float(errors.max()), bounce_errors=errors.tolist(),
            pooled_error=float(np.linalg.norm(bounces - truth) / np.linalg.norm(truth)),
            t1_error=float(np.max(np.abs(t1 - t1_true) / t1_true)),
            closure_error=float(closure),
            amplification=float(errors.max() / relative_noise) if relative_noise > 0 else 0.0,
        ))
    return rows


def run_bench(sizes, scenes=("box",), noises=(0.0,), solvers=SOLVERS, batch: int = 16, n_bounces: int = 8,
              repeats: int = 3, progress=None) -> list[BenchRow]:
    rows = []
    for scene in scenes:
        for m in sizes:
            for noise in noises:
                case = bench_case(scene, m, noise, solvers, batch, n_bounces, repeats)
                rows.extend(case)
                if progress:
                    for r in case:
                        progress(r)
    return rows


@dataclass(frozen=True)
class BiasVarianceRow(BiasVariance):
    """:class:`ilt.regularise.BiasVariance` of one filter width on one case."""

    scene: str = ""
    m: int = 0
    noise: float = 0.0
    draws: int = 0


def bias_variance_case(scene_name: str, m: int, noise: float, draws: int = 8, batch: int = 16,
                       n_bounces: int = 8, seed: int = 0) -> list[BiasVarianceRow]:
    """Bias and variance of the bounces, plain and at every filter width, over ``draws``
    noise draws of sigma = ``noise`` x max |T| on one scene."""
    from ilt.regularise import bias_variance

    scene = make_scene(scene_name, beams=m)
    T, _ = scene.isf()
    photos, truth = scene_batch(scene, batch, n_bounces, seed)
    rows = bias_variance(T, scene.layout, photos, truth, noise * np.abs(T).max(), draws=draws, seed=seed + 1)
    return [BiasVarianceRow(scene=scene_name, m=scene.m, noise=noise, draws=draws, **asdict(r)) for r in rows]


BV_HEADER = (f"{'scene':>8} {'m':>5} {'noise':>7} {'width':>6} {'chosen':>6} {'bias':>9} {'spread':>9} "
             f"{'error':>9}   (pooled over bounces, relative to the truth)")


def format_bv_row(r: BiasVarianceRow) -> str:
    return (f"{r.scene:>8} {r.m:>5} {r.noise:>7.0e} {r.width:>6g} {r.chosen:>3}/{r.draws:<2} {r.pooled_bias:>9.2e} "
            f"{r.pooled_spread:>9.2e} {r.pooled_error:>9.2e}")


HEADER = (f"{'scene':>8} {'m':>5} {'noise':>7} {'solver':>11} {'seconds':>8} {'/scipy':>6} {'MiB':>6} "
          f"{'bounce err':>10} {'pooled':>8} {'T1 err':>8} {'closure':>8} {'amplif':>7}")


def format_row(r: BenchRow) -> str:
    if r.refused:
        return f"{r.scene:>8} {r.m:>5} {r.noise:>7.0e} {r.solver:>11} refused: {r.refused}"
    return (f"{r.scene:>8} {r.m:>5} {r.noise:>7.0e} {r.solver:>11} {r.seconds:>8.3f} {r.ratio_to_scipy:>6.2f} "
            f"{r.peak_mib:>6.0f} {r.bounce_error:>10.2e} {r.pooled_error:>8.1e} {r.t1_error:>8.1e} {r.closure_error:>8.1e} "
            f"{r.amplification:>7.2f}")


def format_table(rows: list[BenchRow]) -> str:
    return "\n".join([HEADER, *map(format_row, rows)])


def plot(rows: list[BenchRow], path, bias_variance: list[BiasVarianceRow] = ()) -> None:
    """Left: run time against error, one curve per solver (log-log), points along m.
    Middle: worst bounce error against the noise in T, one curve per solver. Right
    (with ``bias_variance`` rows): bias and spread against the filter width, per noise."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from ilt.manifest import atomic_path

    fig = Figure(figsize=(16.5 if bias_variance else 11, 4.5))
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 3 if bias_variance else 2)
    ax1, ax2 = axes[:2]
    if bias_variance:
        _plot_bias_variance(axes[2], bias_variance)
    rows = [r for r in rows if not r.refused]
    solvers = list(dict.fromkeys(r.solver for r in rows))
    clean = [r for r in rows if r.noise == 0]
    for solver in solvers:
        pts = [(r.seconds, max(r.bounce_error, 1e-17), r.m) for r in sorted(clean, key=lambda r: r.m)
               if r.solver == solver]
        if pts:
            ax1.loglog([p[0] for p in pts], [p[1] for p in pts], "o-", label=solver)
            for s, e, m in pts:
                ax1.annotate(str(m), (s, e), fontsize=7, alpha=0.6)
        noisy = sorted((r.noise, r.bounce_error, r.pooled_error) for r in rows if r.solver == solver and r.noise > 0
                       and r.m == max(x.m for x in rows))
        if noisy:  # solid: the whole decomposition (pooled); dashed: its worst bounce
            line, = ax2.loglog([p[0] for p in noisy], [p[2] for p in noisy], "o-", label=solver)
            ax2.loglog([p[0] for p in noisy], [p[1] for p in noisy], "x--", color=line.get_color(), alpha=0.6)
    ax1.set(xlabel="seconds (median)", ylabel="worst relative bounce error",
            title="run time against error (noise-free; labels: m)")
    ax2.set(xlabel="noise in T (relative to max |T|)", ylabel="relative error (solid: all bounces; dashed: worst)",
            title=f"error against noise (m = {max(r.m for r in rows)})")
    for ax in (ax1, ax2):
        ax.grid(True, which="both", alpha=0.3)
        if ax.has_data():
            ax.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)


def rows_json(rows: list[BenchRow]) -> list[dict]:
    return [asdict(r) for r in rows]


def _plot_bias_variance(ax, rows: list[BiasVarianceRow]) -> None:
    """Bias (solid) and spread (dashed) of the bounces against the filter width, one
    colour per case; a ring marks the width regularise_isf applied most."""
    cases = list(dict.fromkeys((r.scene, r.m, r.noise) for r in rows))
    for k, case in enumerate(cases):
        pts = sorted((r for r in rows if (r.scene, r.m, r.noise) == case), key=lambda r: r.width)
        colour = f"C{k % 10}"
        x = [r.width for r in pts]
        label = f"{case[0]} m={case[1]} noise {case[2]:g}"
        ax.semilogy(x, [r.pooled_bias for r in pts], "-o", color=colour, ms=3, label=label + ": bias")
        ax.semilogy(x, [r.pooled_spread for r in pts], "--", color=colour, label="spread")
        pick = max(pts, key=lambda r: r.chosen)
        ax.semilogy([pick.width], [pick.pooled_error], "o", mfc="none", mec=colour, ms=10)
    ax.set(xlabel="filter width (layout steps; 0 = plain inversion)", ylabel="relative to the true bounces",
           title="bias and spread (ring: the width applied)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
