"""Run time against error: solvers of ``C1`` + bounce decomposition, timed in one process.

For each scene, size m and noise level sigma (Gaussian, relative to max |T|) the
benchmark times, as the median of repeats,

- ``scipy``: the bare baseline, ``scipy.linalg.inv(T)`` (getrf + getri), ``C1 = T1 T^-1``
  formed, then the bounce recursion with matrix products;
- each ilt solver (``dense``, ``mixed``, ``blocks``, ``series``, ``compressed``; see
  :mod:`ilt.transport.solvers`): build the operator and split a batch of photos into N bounces
  (``compressed`` to the true sigma, its tree ordered by the sample pixels); for noisy T also
  ``regularised`` (:mod:`ilt.transport.regularise`, with the true sigma, then ``dense``). A
  solver that refuses T (``series`` on a dense T) gets a row saying why, no figures;

and measures each against the simulator's exact truth: the worst relative error of
any bounce ``max_n ||Ln - Ln*|| / ||Ln*||``, the error per bounce, the pooled error of
all bounces together ``||L - L*|| / ||L*||`` (stacked: weighted by each bounce's
energy, where the worst bounce is usually the faintest), the relative error
of ``diag(T1)``, the closure error, the error amplification (bounce error over the
relative noise in T) and the peak memory it allocates (tracemalloc).

Sizes past the simulator (:data:`SIMULATED_MAX_M`) run ``compressed`` alone on a
memory-mapped synthetic ISF (:func:`kernel_case`).
"""

from __future__ import annotations

import math
import os
import statistics
import threading
import time
import tracemalloc
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import scipy.linalg

from ilt.evaluate.errors import relative_errors
from ilt.sim import ILLUMINATIONS, make_scene
from ilt.transport.operators import bounce_images
from ilt.transport.regularise import BiasVariance, regularise_isf
from ilt.transport.scan import TransportError
from ilt.transport.solvers import build_operator

QUICK_SIZES = (256, 512, 1024)
#: the largest m simulated: the box's dense T, A and truth (~6 m x m float64 arrays,
#: 12 GiB at m = 16428, 265 s on the 2-core machine); past it, :func:`kernel_case`
SIMULATED_MAX_M = 16428
#: the scene name of :func:`kernel_case`'s rows
KERNEL_SCENE = "corner"
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
    solve_residual: float | None = None  # past the simulator: ||T_n x - b|| / ||b|| of the photos' solves
    note: str | None = None


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


def kernel_case(m: int, noise: float = 0.0, solvers=SOLVERS, batch: int = 16, n_bounces: int = 8,
                repeats: int = 3, seed: int = 0) -> list[BenchRow]:
    """m past the simulator (:data:`SIMULATED_MAX_M`): ``compressed`` alone, on the
    cube-corner kernel ISF of :mod:`ilt.sim.kernel` (m rounded to 3 n^2) written to a
    memory-mapped ``T.npy`` in a temporary directory (``TMPDIR``; it needs T's size of
    disk) with noise of ``noise`` per entry (its largest entry is 1); the
    other solvers get a row saying why they did not run. There is no simulator truth:
    the figure is the relative residual of the photos' solves against T itself, and
    the peak memory is the process's resident memory while it runs, the pages of the
    mapped T included."""
    import tempfile

    from ilt.sim.kernel import corner_kernel_isf, corner_points
    from ilt.transport.compressed import unit_column_product

    n = max(1, round(math.sqrt(m / 3)))
    rows = [BenchRow(scene=KERNEL_SCENE, m=3 * n * n, noise=noise, solver=name, batch=batch, bounces=n_bounces,
                     refused=f"m = {3 * n * n} is past the simulator (m <= {SIMULATED_MAX_M}): only compressed "
                             "runs there, on a memory-mapped T")
            for name in dict.fromkeys(("scipy", *solvers))
            if name != "compressed" and not (name == "regularised" and noise == 0)]
    if "compressed" not in solvers:
        return rows
    with tempfile.TemporaryDirectory(prefix="ilt-bench-") as tmp:
        T = corner_kernel_isf(Path(tmp) / "T.npy", n, noise=noise, seed=seed + 1)
        points = corner_points(n)[0]
        photos = np.random.default_rng(seed).uniform(size=(T.shape[0], batch))

        def run():
            op, _ = build_operator(T, "compressed", noise or None, points=points)
            return op, bounce_images(op, photos, n_bounces)

        with PeakResident() as peak:
            seconds, (op, dec) = median_time(run, repeats)
        residual = photos - unit_column_product(T, 1.0 / op.column_norms, op.solve(photos))
        closure = np.linalg.norm(photos - dec.bounces.sum(axis=0) - dec.residual) / np.linalg.norm(photos)
        rows.append(BenchRow(
            scene=KERNEL_SCENE, m=T.shape[0], noise=noise, solver="compressed", batch=batch, bounces=n_bounces,
            seconds=seconds, peak_mib=peak.mib, closure_error=float(closure),
            solve_residual=float(np.linalg.norm(residual) / np.linalg.norm(photos)),
            note=(f"T.npy {T.nbytes / 2**20:.0f} MiB memory-mapped; peak resident {peak.mib:.0f} MiB "
                  f"({peak.mib * 2**20 / T.nbytes:.2f}x T, its pages included); {op.describe()}")))
        del T, op
    return rows


class PeakResident:
    """The process's peak resident memory (MiB) while the block runs, sampled from
    ``/proc/self/statm`` every 20 ms (Linux; None elsewhere): unlike tracemalloc it
    counts the pages of a memory-mapped file the process reads."""

    def __init__(self):
        self.mib, self._stop = None, threading.Event()

    def _sample(self):
        page = os.sysconf("SC_PAGE_SIZE")
        while True:
            with open("/proc/self/statm") as f:
                self.mib = max(self.mib or 0.0, int(f.read().split()[1]) * page / 2**20)
            if self._stop.wait(0.02):
                return

    def __enter__(self):
        self._thread = threading.Thread(target=self._sample, daemon=True) if os.path.exists("/proc/self/statm") else None
        if self._thread:
            self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        if self._thread:
            self._thread.join()


def run_bench(sizes, scenes=("box",), noises=(0.0,), solvers=SOLVERS, batch: int = 16, n_bounces: int = 8,
              repeats: int = 3, progress=None) -> list[BenchRow]:
    """Every case, a row per solver; sizes past :data:`SIMULATED_MAX_M` run once (not
    per scene) as :func:`kernel_case`."""
    cases = [(bench_case, scene, m) for scene in scenes for m in sizes if m <= SIMULATED_MAX_M]
    cases += [(kernel_case, None, m) for m in sizes if m > SIMULATED_MAX_M]
    rows = []
    for fn, scene, m in cases:
        for noise in noises:
            args = (m, noise, solvers, batch, n_bounces, repeats)
            case = fn(scene, *args) if scene else fn(*args)
            rows.extend(case)
            if progress:
                for r in case:
                    progress(r)
    return rows


@dataclass(frozen=True)
class BiasVarianceRow(BiasVariance):
    """:class:`ilt.transport.regularise.BiasVariance` of one filter width on one case."""

    scene: str = ""
    m: int = 0
    noise: float = 0.0
    draws: int = 0


def bias_variance_case(scene_name: str, m: int, noise: float, draws: int = 8, batch: int = 16,
                       n_bounces: int = 8, seed: int = 0) -> list[BiasVarianceRow]:
    """Bias and variance of the bounces, plain and at every filter width, over ``draws``
    noise draws of sigma = ``noise`` x max |T| on one scene."""
    from ilt.transport.regularise import bias_variance

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
    if r.bounce_error is None:  # past the simulator: no truth
        return (f"{r.scene:>8} {r.m:>5} {r.noise:>7.0e} {r.solver:>11} {r.seconds:>8.3f} {'':>6} {r.peak_mib or 0:>6.0f} "
                f"solve residual {r.solve_residual:.1e}, closure {r.closure_error:.1e}; {r.note}")
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

    from ilt.io.atomic import atomic_path

    fig = Figure(figsize=(16.5 if bias_variance else 11, 4.5))
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 3 if bias_variance else 2)
    ax1, ax2 = axes[:2]
    if bias_variance:
        _plot_bias_variance(axes[2], bias_variance)
    untrue = [r for r in rows if not r.refused and r.bounce_error is None]  # past the simulator
    rows = [r for r in rows if not r.refused and r.bounce_error is not None]
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
    for r in (r for r in untrue if r.noise == 0):
        ax1.loglog([r.seconds], [max(r.solve_residual, 1e-17)], "s", color="k",
                   label=f"{r.solver}, memory-mapped {r.scene} (solve residual)")
        ax1.annotate(str(r.m), (r.seconds, r.solve_residual), fontsize=7, alpha=0.6)
    ax1.set(xlabel="seconds (median)", ylabel="worst relative bounce error",
            title="run time against error (noise-free; labels: m)")
    ax2.set(xlabel="noise in T (relative to max |T|)", ylabel="relative error (solid: all bounces; dashed: worst)",
            title=f"error against noise (m = {max(r.m for r in rows)})" if rows else "error against noise")
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
