"""``ilt demo``: the whole method on built-in simulated scenes."""

from __future__ import annotations

import click

from ilt.cli.options import emit, force_option, json_option, output_option


@click.command("demo")
@output_option
@click.option("--quick", is_flag=True, help="Fewer beams (for CI and a first look).")
@force_option
@json_option
def command(output, quick, force, as_json):
    """Run the paper's experiments on the simulated "M" and box scenes.

    Writes, per scene, OUTPUT/<scene>/isf (simulated ISF with truth),
    OUTPUT/<scene>/decompose (each photo's bounce images and preview.png, like the
    paper's Fig. 6), OUTPUT/<scene>/fig5.png (T and Cn T, like Fig. 5) and
    fig5-errors.json, and prints the Fig. 5 error table on stderr.
    """
    from ilt.demo import error_table, run_demo

    results = run_demo(output, quick=quick, force=force)
    for r in results:
        click.echo(error_table(r), err=True)
        click.echo(f"figures: {r['fig5']}  " + "  ".join(r["previews"]), err=True)
    emit(as_json, results, [r["fig5"] for r in results] + [p for r in results for p in r["previews"]])
