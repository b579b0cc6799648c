"""``ilt bench``: run time against error for every solver, against a scipy baseline
timed in the same run."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import click

from ilt.cli.options import bounces_option, emit, json_option, note


def _list(kind):
    def parse(ctx, param, value):
        if value is None:
            return None
        try:
            return [kind(v) for v in value.split(",")]
        except ValueError:
            raise click.BadParameter(f"not a comma-separated list: {value}") from None
    return parse


@click.command("bench")
@click.option("--quick", is_flag=True, help="Sizes 256, 512, 1024 and noise 0, 1e-3 only (a minute or two).")
@click.option("--sizes", callback=_list(int),
              help="Comma-separated m values (default 256,...,4096). Past 16428 (the largest the simulator "
                   "builds, 265 s) only compressed runs, on a synthetic cube-corner ISF written to a "
                   "memory-mapped T.npy in the temporary directory (TMPDIR; it needs T's size of disk: 8.2 GiB at "
                   "32768); its error figure is the solve residual against T.")
@click.option("--scenes", callback=_list(str), default="box", show_default=True,
              help="Comma-separated scenes: m, box, textured, occluded.")
@click.option("--noise", "noises", callback=_list(float),
              help="Comma-separated noise levels in T, relative to max |T| (default 0,1e-6,1e-4,1e-2).")
@click.option("--solvers", callback=_list(str), default="scipy,dense,mixed,blocks,series,compressed,regularised",
              show_default=True,
              help="Comma-separated solvers; scipy (inv + products) is always timed as the baseline; "
                   "regularised (denoised T, then dense) runs on noisy T only; a solver that refuses T "
                   "(series on a dense T) gets a row saying why.")
@click.option("--batch", type=click.IntRange(min=1), default=16, show_default=True, help="Photos decomposed at once.")
@bounces_option
@click.option("--repeats", type=click.IntRange(min=1), default=3, show_default=True, help="Timings per figure (median).")
@click.option("--draws", type=click.IntRange(min=0), default=8, show_default=True,
              help="Noise draws for the bias/variance study of regularisation (0: skip it).")
@click.option("-o", "--output", type=click.Path(file_okay=False), default=None,
              help="Also write OUTPUT/bench.json and the plot OUTPUT/bench.png.")
@json_option
def command(quick, sizes, scenes, noises, solvers, batch, n_bounces, repeats, draws, output, as_json):
    """Time C1 + bounce decomposition for each solver, scene, size and noise level,
    against scipy (inv + products) and the simulator's exact truth. Prints a table on
    stderr: medians, ratio to scipy (below 1 is faster), worst bounce error, T1 error,
    closure, and the amplification of the noise in T.

    With `regularised` among the solvers and noise above 0, a second table gives bias
    against variance: on each scene at the smallest size, DRAWS independent noise
    draws of T, inverted plainly (width 0) and after filtering at each width; bias
    (mean estimate against the truth), spread (the draws about their mean) and error,
    and how often the filter `--regularise` applies passed the discrepancy principle."""
    from ilt.evaluate import bench
    from ilt.io.manifest import write_json
    from ilt.transport.solvers import SOLVERS

    unknown = set(solvers) - set(SOLVERS) - {"scipy", "regularised"}
    if unknown:
        raise click.BadParameter(f"unknown solver(s) {sorted(unknown)}", param_hint="--solvers")
    sizes = sizes or (bench.QUICK_SIZES if quick else bench.FULL_SIZES)
    noises = noises or ([0.0, 1e-3] if quick else [0.0, 1e-6, 1e-4, 1e-2])
    note(bench.HEADER)
    rows = bench.run_bench(sizes, scenes, noises, solvers, batch, n_bounces, repeats,
                           progress=lambda r: note(bench.format_row(r)))
    bv = []
    if draws and "regularised" in solvers and any(n > 0 for n in noises):
        note(bench.BV_HEADER)
        for scene in scenes:
            for noise in (n for n in noises if n > 0):
                case = bench.bias_variance_case(scene, min(sizes), noise, draws, batch, n_bounces)
                for r in case:
                    note(bench.format_bv_row(r))
                bv.extend(case)
    data = bench.rows_json(rows)
    paths = []
    if output:
        out = Path(output)
        out.mkdir(parents=True, exist_ok=True)
        paths = [str(write_json(out / "bench.json", {"rows": data, "bias_variance": [asdict(r) for r in bv]})),
                 str(out / "bench.png")]
        bench.plot(rows, out / "bench.png", bv)
    emit(as_json, data, paths)
