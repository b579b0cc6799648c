"""``ilt demo``: the whole rig on built-in simulated scenes."""

from __future__ import annotations

import click

from ilt.cli.options import emit, json_option, note, output_option


@click.command("demo")
@output_option
@click.option("--quick", is_flag=True, help="Fewer beams (for CI and a first look).")
@click.option("--force", is_flag=True, help="Re-run every stage (the demo otherwise skips what is up to date).")
@json_option
def command(output, quick, force, as_json):
    """Run the simulated rig and the paper's experiments on the "M" and box scenes.

    Per scene, OUTPUT/<scene>/ is an `ilt run` workspace: the emulated pan-tilt unit
    and the simulated camera scan the scene into DNG brackets, then merge, centroids,
    build-isf and decompose of three photos, with OUTPUT/<scene>/report/index.html.
    OUTPUT/<scene>/exact/ holds the exact-ISF Fig. 5 experiment (fig5.png,
    fig5-errors.json). OUTPUT/report/index.html links them all; the Fig. 5 error
    tables go to stderr. Running it again skips what is up to date. OUTPUT must be
    new, empty or an earlier demo's output (marked by its manifest.json).
    """
    from ilt.workspace.demo import error_table, run_demo

    results = run_demo(output, quick=quick, force=force)
    for r in results:
        note(error_table(r))
    note(f"ilt: demo: figures in {output}/report/index.html (and {output}/<scene>/report/)")
    emit(as_json, results, [f"{output}/report/index.html"] + [r["report"] for r in results])
