"""``ilt report``: a self-contained HTML page of a workspace's figures and diagnostics."""

from __future__ import annotations

import click

from ilt.cli.options import emit, json_option, workspace_option


@click.command("report")
@workspace_option
@click.option("-o", "--output", type=click.Path(file_okay=False), default=None,
              help="Report directory (default WORKSPACE/report); replaced only when it is new, empty "
                   "or an earlier report.")
@json_option
def command(workspace, output, as_json):
    """Write WORKSPACE/report/index.html and the PNGs it shows: the scene with its
    spots (paper Fig. 4), T and Cn T (Fig. 5), each photo's bounce images (Fig. 6),
    the diagnostics with their warnings and the capture's statistics.

    Prints the path of index.html.
    """
    from ilt.report.page import write_report

    path = write_report(workspace, output)
    emit(as_json, {"report": str(path)}, [str(path)])
