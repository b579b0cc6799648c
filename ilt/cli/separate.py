"""``ilt separate``: direct and global light from photos under shifted patterns (Nayar et al. 2006)."""

from __future__ import annotations

import click

from ilt.cli.options import emit, force_option, json_option, output_option


@click.command("separate")
@click.argument("photos", nargs=-1, required=True, type=click.Path(dir_okay=False))
@output_option
@click.option("--black", type=click.FloatRange(0, 1, max_open=True), default=0.0, show_default=True,
              help="Brightness of an 'off' projector pixel over an 'on' one (the projector's black level).")
@force_option
@json_option
def command(photos, output, black, force, as_json):
    """Split a scene into direct and global light from PHOTOS taken under shifted binary
    patterns with half of the projector's pixels on (Nayar et al., SIGGRAPH 2006).

    Per pixel, the brightest photo holds the direct light and half the global, the
    darkest half the global: direct = max - min, global = 2 min (with --black b:
    (max - min) / (1 - b) and 2 (min - b max) / (1 - b^2)). The patterns must be finer than the
    scene's global light varies and shifted so that every point is lit in one photo
    and dark in another (stripes shifted through one period in 4 or more steps).
    Holds for any reflectance: a cross-check of ilt's bounce 1 and indirect part on a
    glossy scene. Writes direct.exr and global.exr (.npy for .npy inputs),
    preview.png and manifest.json into -o.
    """
    from ilt.separate.stage import separate

    summary = separate(list(photos), output, black=black, force=force)
    emit(as_json, summary, [summary["output"]])
