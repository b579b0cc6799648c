"""``ilt bench``: run time against error for every solver, against a scipy baseline
timed in the same run."""

from __future__ import annotations

from pathlib import Path

import click

from ilt.cli.options import emit, json_option, note


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
@click.option("--sizes", callback=_list(int), help="Comma-separated m values (default 256,...,4096).")
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
@click.option("--bounces", "n_bounces", type=click.IntRange(min=1), default=8, show_default=True)
@click.option("--repeats", type=click.IntRange(min=1), default=3, show_default=True, help="Timings per figure (median).")
@click.option("-o", "--output", type=click.Path(file_okay=False), default=None,
              help="Also write OUTPUT/bench.json and the plot OUTPUT/bench.png.")
@json_option
def command(quick, sizes, scenes, noises, solvers, batch, n_bounces, repeats, output, as_json):
    """Time C1 + bounce decomposition for each solver, scene, size and noise level,
    against scipy (inv + products) and the simulator's exact truth. Prints a table on
    stderr: medians, ratio to scipy (below 1 is faster), worst bounce error, T1 error,
    closure, and the amplification of the noise in T."""
    from ilt import bench
    from ilt.manifest import write_json
    from ilt.solvers import SOLVERS

    unknown = set(solvers) - set(SOLVERS) - {"scipy", "regularised"}
    if unknown:
        raise click.BadParameter(f"unknown solver(s) {sorted(unknown)}", param_hint="--solvers")
    sizes = sizes or (bench.QUICK_SIZES if quick else bench.FULL_SIZES)
    noises = noises or ([0.0, 1e-3] if quick else [0.0, 1e-6, 1e-4, 1e-2])
    note(bench.HEADER)
    rows = bench.run_bench(sizes, scenes, noises, solvers, batch, n_bounces, repeats,
                           progress=lambda r: note(bench.format_row(r)))
    data = bench.rows_json(rows)
    paths = []
    if output:
        out = Path(output)
        out.mkdir(parents=True, exist_ok=True)
        paths = [str(write_json(out / "bench.json", {"rows": data})), str(out / "bench.png")]
        bench.plot(rows, out / "bench.png")
    emit(as_json, data, paths)
