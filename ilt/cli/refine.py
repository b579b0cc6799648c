"""``ilt refine``: where the next beams of a scan should land."""

from __future__ import annotations

from pathlib import Path

import click

from ilt.cli.options import (
    emit,
    force_option,
    json_option,
    require_dir,
    stage_output_option,
    workspace_option,
)


@click.command("refine")
@click.argument("isf_dir", required=False, type=click.Path(exists=True, file_okay=False))
@stage_output_option
@click.option("--beams", "beams", type=int, default=32, show_default=True,
              help="At most this many new beams, best first. On a line of spots (a flatland scan) they "
                   "come in pairs (an edge split in thirds), so an odd number places one fewer.")
@click.option("--capture", "capture", type=click.Path(exists=True, file_okay=False), default=None,
              help="The capture directory the ISF was built from, for pan/tilt and the unit's reach "
                   "(default: the workspace's capture/ when it has a manifest; none: pixels only).")
@click.option("--min-spacing", "min_spacing", type=float, default=None,
              help="No new beam closer than this many full-resolution pixels to another "
                   "(default: a quarter of the median spot spacing).")
@workspace_option
@force_option
@json_option
def command(isf_dir, output, beams, capture, min_spacing, workspace, force, as_json):
    """Decide where the next beams should land for the scan of ISF_DIR (default
    WORKSPACE/isf), and write -o (default WORKSPACE/refine).

    Where the build measured folds, their rows of spots are split first, one new beam on
    each side. Then, on a grid of spots, the neighbouring beams whose columns of T differ
    most (what they light; the noise taken off) get a new beam halfway; on a line, the
    beams whose column their neighbours predict worst get two, at the thirds (never on a
    fold halfway between them). Greedy by the expected gain; none lands outside the ISF's
    cells. Writes refine.csv (x,y in full-resolution sensor pixels,
    pan,tilt in the plan's units when the capture is known, gain; best first),
    refine.json (the indicator before and after), refine.png and manifest.json.
    Works on an ISF built from bare beam frames (pixels only). docs/refine.md.
    """
    from ilt.refine.stage import refine

    isf_dir = workspace.resolve(isf_dir, "build-isf")
    require_dir(isf_dir, "the ISF", "run 'ilt build-isf' first, or give ISF_DIR")
    if capture is None and (Path(workspace.resolve(None, "capture")) / "manifest.json").exists():
        capture = workspace.resolve(None, "capture")
    output = workspace.resolve(output, "refine")
    summary = refine(isf_dir, output, beams, capture=capture, min_spacing=min_spacing, force=force)
    emit(as_json, summary, [str(Path(output) / "refine.csv")])
