"""``ilt centroids``: one sub-pixel laser spot per beam frame, with QA flags."""

from __future__ import annotations

import click

from ilt.cli.options import (
    cluster_options,
    emit,
    force_option,
    json_option,
    progress_bar,
    require_dir,
    stage_option,
    stage_output_option,
    workers_option,
    workspace_option,
)
from ilt.workspace.options import CENTROIDS


@click.command("centroids")
@click.argument("hdr_dir", required=False, type=click.Path(exists=True, file_okay=False))
@stage_output_option
@click.option("--dark", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Dark frame (EXR on the frames' grid) to subtract from HDR frames (default: a robust local "
                   "background level; a capture directory's own dark frames are always used).")
@stage_option(CENTROIDS["threshold"], show_default=True, help="Spot threshold, fraction of the peak above background.")
@stage_option(CENTROIDS["min_snr"], show_default=True,
              help="Flag 'none' when the peak is below this many noise sigmas.")
@stage_option(CENTROIDS["max_second"], show_default=True,
              help="Flag 'multiple' when a second spot has this fraction of the first's flux.")
@stage_option(CENTROIDS["max_elongation"], show_default=True, help="Flag 'elongated' above this axis ratio.")
@stage_option(CENTROIDS["large_factor"], show_default=True,
              help="Flag 'large' above this multiple of the median spot area.")
@stage_option(CENTROIDS["max_area"], help="Flag 'large' above this many pixels.")
@stage_option(CENTROIDS["saturation"], help="Sensor clipping level in frame units (default: detect a flat top).")
@stage_option(CENTROIDS["roi"], help="Region of interest x0,y0,x1,y1 in full-frame sensor pixels.")
@stage_option(CENTROIDS["refine"], help="Refine each centroid with a 2D Gaussian fit.")
@workers_option
@cluster_options
@workspace_option
@force_option
@json_option
def command(hdr_dir, output, dark, threshold, min_snr, max_second, max_elongation, large_factor, max_area,
            saturation, roi, refine, workers, cluster, workspace, force, as_json):
    """Find the laser spot of every beam frame in HDR_DIR (one EXR per beam, sorted by
    name, optional manifest.json with the plan's layout), or of every beam of a capture
    directory at its shortest exposure, less its dark frame (the paper's choice).

    Writes spots.csv (beam,x,y,flux,peak,area,flags; x, y in full-frame sensor
    pixels, centres at integer coordinates, (0, 0) the top-left, whatever the frames'
    resolution), sum.exr (sum of the frames), overlay.png and manifest.json into -o
    (default WORKSPACE/spots). Flagged
    beams are listed on stderr; build-isf drops them.
    """
    from ilt.parallel.cluster import executor_for
    from ilt.spots.find import SpotParameters
    from ilt.spots.stage import run_centroids

    hdr_dir, output = workspace.resolve(hdr_dir, "merge"), workspace.resolve(output, "centroids")
    require_dir(hdr_dir, "the HDR frames", "run 'ilt merge' first, or give HDR_DIR")

    if roi is not None:
        try:
            roi = tuple(float(v) for v in roi.split(","))
            assert len(roi) == 4
        except (ValueError, AssertionError):
            raise click.BadParameter(f"not x0,y0,x1,y1: {roi}", param_hint="--roi") from None
    params = SpotParameters(threshold=threshold, min_snr=min_snr, max_second=max_second,
                            max_elongation=max_elongation, large_factor=large_factor, max_area=max_area,
                            saturation=saturation, roi=roi, refine=refine)

    with executor_for(cluster, workers) as executor, progress_bar(_count(hdr_dir), "centroids") as update:
        summary = run_centroids(hdr_dir, output, params, dark=dark, executor=executor, workers=workers,
                                progress=update, force=force)
    emit(as_json, summary, [summary["output"]])


def _count(hdr_dir) -> int:
    """Beams to expect, for the progress bar: EXR frames, else beam directories of a capture."""
    from pathlib import Path

    from ilt.io.beams import BEAM_GLOB

    path = Path(hdr_dir)
    return sum(1 for p in path.iterdir() if p.suffix.lower() == ".exr") or \
        sum(1 for p in path.glob(BEAM_GLOB) if p.is_dir())
