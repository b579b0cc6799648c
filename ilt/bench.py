"""Run time and error of the operators + decomposition against a bare scipy baseline.

For each size m: build a simulated scene, then time (median of repeats, same process)

- ``ilt``: ``cancellation_operator(T)`` (getrf + in-place trtri, diag(T^-1) from the
  factors) and ``bounce_images`` of a batch of photos;
- ``scipy``: ``scipy.linalg.inv(T)`` (getrf + getri), ``C1 = T1 T^-1`` formed
  explicitly, then the bounce recursion with matrix products;

and the error of each against the simulator's exact truth: ``max_n ||Ln - Ln*|| /
||Ln*||`` over the batch, and the relative error of ``diag(T1)``.
"""

from __future__ import annotations

import statistics
import time
import tracemalloc
from dataclasses import asdict, dataclass

import numpy as np
import scipy.linalg

from ilt.evaluate import relative_errors
from ilt.sim import ILLUMINATIONS, make_scene
from ilt.transport import bounce_images, cancellation_operator

QUICK_SIZES = (256, 512, 1024)
FULL_SIZES = (256, 512, 1024, 2048, 4096)


@dataclass
class BenchRow:
    scene: str
    m: int
    batch: int
    bounces: int
    ilt_seconds: float
    scipy_seconds: float
    ratio: float
    ilt_peak_mib: float
    scipy_peak_mib: float
    ilt_bounce_error: float
    scipy_bounce_error: float
    ilt_t1_error: float
    scipy_t1_error: float


def _ilt(T, photos, n_bounces):
    op = cancellation_operator(T)
    return op.t1, bounce_images(op, photos, n_bounces).bounces


def _scipy(T, photos, n_bounces):
    inv = scipy.linalg.inv(T)
    t1 = 1.0 / np.diag(inv)
    C1 = t1[:, None] * inv
    r, out = photos.copy(), []
    for _ in range(n_bounces):
        ln = C1 @ r
        r -= ln
        out.append(ln)
    return t1, np.stack(out)


def _median_time(fn, repeats: int, *args):
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


def bench_size(scene_name: str, m: int, batch: int = 16, n_bounces: int = 8, repeats: int = 3) -> BenchRow:
    scene = make_scene(scene_name, beams=m)
    T, scale = scene.isf()
    t1_true = scene.direct / scale
    photos, truth = scene_batch(scene, batch, n_bounces)
    ilt_s, (ilt_t1, ilt_b) = _median_time(_ilt, repeats, T, photos, n_bounces)
    sp_s, (sp_t1, sp_b) = _median_time(_scipy, repeats, T, photos, n_bounces)
    return BenchRow(
        scene=scene_name, m=scene.m, batch=batch, bounces=n_bounces,
        ilt_seconds=ilt_s, scipy_seconds=sp_s, ratio=ilt_s / sp_s,
        ilt_peak_mib=_peak_mib(_ilt, T, photos, n_bounces),
        scipy_peak_mib=_peak_mib(_scipy, T, photos, n_bounces),
        ilt_bounce_error=float(relative_errors(ilt_b, truth).max()),
        scipy_bounce_error=float(relative_errors(sp_b, truth).max()),
        ilt_t1_error=float(np.max(np.abs(ilt_t1 - t1_true) / t1_true)),
        scipy_t1_error=float(np.max(np.abs(sp_t1 - t1_true) / t1_true)),
    )


def format_table(rows: list[BenchRow]) -> str:
    head = (f"{'scene':>6} {'m':>5} {'ilt s':>8} {'scipy s':>8} {'ratio':>6} {'ilt MiB':>8} {'scipy MiB':>9} "
            f"{'ilt err':>9} {'scipy err':>9} {'ilt T1 err':>10}")
    lines = [head]
    for r in rows:
        lines.append(
            f"{r.scene:>6} {r.m:>5} {r.ilt_seconds:>8.3f} {r.scipy_seconds:>8.3f} {r.ratio:>6.2f} "
            f"{r.ilt_peak_mib:>8.0f} {r.scipy_peak_mib:>9.0f} {r.ilt_bounce_error:>9.1e} "
            f"{r.scipy_bounce_error:>9.1e} {r.ilt_t1_error:>10.1e}"
        )
    return "\n".join(lines)


def plot(rows: list[BenchRow], path) -> None:
    """Run time against m (log-log) and error against run time, one curve per solver."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import NullFormatter

    from ilt.manifest import atomic_path

    fig = Figure(figsize=(10, 4))
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(1, 2)
    ms = [r.m for r in rows]
    for label, t, e in (("ilt (getrf + trtri)", "ilt_seconds", "ilt_bounce_error"),
                        ("scipy (inv + products)", "scipy_seconds", "scipy_bounce_error")):
        ax1.loglog(ms, [getattr(r, t) for r in rows], "o-", label=label)
        ax2.loglog([getattr(r, t) for r in rows], [max(getattr(r, e), 1e-17) for r in rows], "o-", label=label)
    ax1.set(xlabel="m (beams)", ylabel="seconds (median)",
            title=f"operators + {rows[0].bounces} bounces, batch of {rows[0].batch}")
    ax1.set_xticks(ms, labels=[str(m) for m in ms])
    ax1.xaxis.set_minor_formatter(NullFormatter())
    ax2.set(xlabel="seconds (median)", ylabel="max relative bounce error", title="error against run time")
    for ax in (ax1, ax2):
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)


def run_bench(sizes, scene: str = "box", batch: int = 16, n_bounces: int = 8, repeats: int = 3, progress=None):
    rows = []
    for m in sizes:
        rows.append(bench_size(scene, m, batch, n_bounces, repeats))
        if progress:
            progress(rows[-1])
    return rows


def rows_json(rows: list[BenchRow]) -> list[dict]:
    return [asdict(r) for r in rows]
