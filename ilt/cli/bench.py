"""``ilt bench``: run time and error against a scipy baseline timed in the same run."""

from __future__ import annotations

from pathlib import Path

import click

from ilt.cli.options import emit, json_option


@click.command("bench")
@click.option("--quick", is_flag=True, help="Sizes 256, 512, 1024 only.")
@click.option("--sizes", default=None, help="Comma-separated m values (default 256,512,1024,2048,4096).")
@click.option("--scene", type=click.Choice(["m", "box", "textured", "occluded"]), default="box", show_default=True)
@click.option("--batch", type=click.IntRange(min=1), default=16, show_default=True, help="Photos decomposed at once.")
@click.option("--bounces", "n_bounces", type=click.IntRange(min=1), default=8, show_default=True)
@click.option("--repeats", type=click.IntRange(min=1), default=3, show_default=True, help="Timings per figure (median).")
@click.option("-o", "--output", type=click.Path(file_okay=False), default=None,
              help="Also write OUTPUT/bench.json and the plot OUTPUT/bench.png.")
@json_option
def command(quick, sizes, scene, batch, n_bounces, repeats, output, as_json):
    """Time operators + bounce decomposition against scipy (inv + products) and
    measure both against the simulator's exact truth. Prints a table on stderr
    (medians; ratio = ilt / scipy, below 1 is faster)."""
    from ilt import bench
    from ilt.manifest import write_json

    if sizes:
        try:
            ms = [int(s) for s in sizes.split(",")]
        except ValueError:
            raise click.BadParameter(f"not a list of integers: {sizes}", param_hint="--sizes") from None
    else:
        ms = bench.QUICK_SIZES if quick else bench.FULL_SIZES
    click.echo(bench.format_table([]), err=True)
    rows = bench.run_bench(ms, scene, batch, n_bounces, repeats,
                           progress=lambda r: click.echo(bench.format_table([r]).splitlines()[1], err=True))
    data = bench.rows_json(rows)
    paths = []
    if output:
        out = Path(output)
        out.mkdir(parents=True, exist_ok=True)
        paths = [str(write_json(out / "bench.json", {"rows": data})), str(out / "bench.png")]
        bench.plot(rows, out / "bench.png")
    emit(as_json, data, paths)
