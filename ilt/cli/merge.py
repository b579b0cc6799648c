"""``ilt merge``: RAW (or 8/16-bit) brackets to linear float EXR, one per beam (docs/hdr.md)."""

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
    workers_option,
    workspace_option,
)
from ilt.workspace.options import MERGE


@click.command("merge")
@click.argument("inputs", nargs=-1, metavar="[CAPTURE_DIR | RAW_FILES...]", type=click.Path())
@click.option("-o", "--output", default=None, type=click.Path(),
              help="HDR directory to write (default WORKSPACE/hdr; an .exr file with --bracket).")
@click.option("--bracket", is_flag=True,
              help="RAW_FILES are the frames of one hand-shot bracket (RAW, or 8/16-bit TIFF/PNG/JPEG "
                   "with --response).")
@click.option("--times", default=None,
              help="Exposure times of the --bracket files, e.g. 1/15,1/30; they override EXIF (with a warning "
                   "where EXIF differs by more than 1/6 stop) and serve files whose EXIF has none or 0.")
@click.option("--dark", type=click.Path(dir_okay=False), default=None, help="Dark frame for --bracket.")
@click.option("--response", "response_path", type=click.Path(dir_okay=False), default=None,
              help="response.json from ilt calibrate (default: linear, nominal exposures).")
@stage_option(MERGE["gain"], show_default=True, help="Sensor gain in electrons per DN (noise model of the weights).")
@stage_option(MERGE["read_noise"], show_default=True,
              help="Read noise in DN per photosite (noise model of the weights).")
@stage_option(MERGE["margin"], show_default=True,
              help="Samples within this fraction of the white level count as saturated.")
@stage_option(MERGE["color"], help="Merge linear camera RGB (R, G, B channels) instead of green.")
@stage_option(MERGE["compression"], show_default=True,
              help="Lossless EXR compression; zip:1 is deflate at its fastest level "
                   "(noisy float data compresses little more at higher levels).")
@workers_option
@cluster_options
@workspace_option
@force_option
@json_option
def command(inputs, output, bracket, times, dark, response_path, gain, read_noise, margin, color,
            compression, workers, cluster, workspace, force, as_json):
    """Merge each beam's RAW bracket of CAPTURE_DIR (default WORKSPACE/capture) into
    beam-NNNNN.exr of the HDR directory -o (default WORKSPACE/hdr).

    Dark frame subtracted, inverse response applied, noise-optimal weights
    (inverse variance), saturated and near-black samples left out. Beside each EXR:
    .valid.png (count of samples used) and .saturated.png (saturated in every frame).
    With --bracket, RAW_FILES are one bracket's frames and -o names the .exr (its
    directory is made if missing); 8/16-bit TIFF, PNG or JPEG frames are merged pixel by
    pixel through --response (required for 8-bit), --gain and --read-noise then in codes.
    """
    from ilt.hdr.merge import NoiseModel
    from ilt.hdr.stages import MergeOptions, load_response, merge_capture, merge_files
    from ilt.io.exposure import parse_times

    if bracket and (not inputs or output is None):
        raise click.UsageError("--bracket needs the RAW_FILES and -o PHOTO.exr")
    inputs = inputs or (workspace.resolve(None, "capture"),)
    output = workspace.resolve(output, "merge")
    response = load_response(response_path) if response_path else None
    options = MergeOptions(NoiseModel(gain, read_noise), response, margin, color, compression)
    if bracket:
        path, summary = merge_files(list(inputs), output, options,
                                    parse_times(times) if times else None, dark, force)
    else:
        if len(inputs) != 1 or times or dark:
            raise click.UsageError("give one CAPTURE_DIR (or --bracket RAW_FILES...); "
                                   "--times and --dark are for --bracket")
        require_dir(inputs[0], "the capture", "run 'ilt capture' first, or give CAPTURE_DIR")
        params = {"gain": gain, "read_noise": read_noise, "margin": margin, "color": color,
                  "compression": compression, "response": response_path}
        from ilt.hdr.bracket import list_beams
        from ilt.parallel.cluster import executor_for

        beams = len(list_beams(inputs[0]))
        with executor_for(cluster, workers) as executor, progress_bar(beams, "merge") as update:
            path, summary = merge_capture(inputs[0], output, options, executor=executor, workers=workers,
                                          force=force, parameters=params, progress=update)
    emit(as_json, summary, [str(path)])
