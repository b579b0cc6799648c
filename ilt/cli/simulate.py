"""``ilt simulate``: a synthetic scene as an ISF directory, or as camera frames, with ground truth."""

from __future__ import annotations

import click

from ilt.cli.options import (
    bounces_option,
    emit,
    force_option,
    json_option,
    output_option,
    progress_bar,
)


@click.command("simulate")
@click.argument("scene", type=click.Choice(["m", "box", "textured", "occluded"]))
@output_option
@click.option("--beams", type=click.IntRange(min=4), default=None,
              help="Number of beams m (default: 128 for flatland scenes, 192 = 3 x 8 x 8 for box; "
                   "with --frames 64 and 108).")
@click.option("--albedo", type=click.FloatRange(0, 1, min_open=True, max_open=True), default=None,
              help="Uniform albedo (default 0.7; 'textured' varies around it).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the random parts of a scene.")
@bounces_option
@click.option("--tracer-bounces", type=click.IntRange(min=1), default=None,
              help="Render T with a forward tracer truncated at K bounces, as the paper did (K = 7); "
                   "default: exact transport.")
@click.option("--frames", is_flag=True,
              help="Write rendered camera frames instead: hdr/ (one EXR per beam), photos/*.exr, truth/.")
@click.option("--spot", type=click.FloatRange(0, 1, min_open=True), default=0.05, show_default=True,
              help="With --frames: laser footprint sigma, in beam spacings (0.4: spots that fill their cells).")
@click.option("--fine", type=click.IntRange(min=1), default=16, show_default=True,
              help="With --frames: surface patches per beam spacing (the box uses fine/4 per axis: patches of "
                   "px-per-beam / (fine/4) px, 8 px at the defaults). Each patch's light is one value, so a "
                   "crease's light is flat over its nearest patch: the box's creases read by build-isf's fold "
                   "transfer want patches of 5 px or less (at 80 px a beam and fine 16 the far light's valley "
                   "splits in two; docs/fullres.md '3D folds').")
@click.option("--px-per-beam", type=click.FloatRange(min=4), default=32.0, show_default=True,
              help="With --frames: pixels between neighbouring spots.")
@click.option("--gloss", type=click.FloatRange(0, 1), default=0.0, show_default=True,
              help="Share of every surface's reflection that is glossy (a lobe about the mirror direction), "
                   "flatland scenes without --frames: a non-Lambertian scene, for the reciprocity check.")
@click.option("--patterns", type=click.IntRange(min=0), default=0, show_default=True,
              help="Without --frames: also K photos under the projector's stripes shifted by 1/K of a cycle "
                   "each (photos/patterns/, for 'ilt separate') and its fully lit photo (photos/projector-full) "
                   "with its true bounces.")
@force_option
@json_option
def command(scene, output, beams, albedo, seed, n_bounces, tracer_bounces, frames, spot, fine, px_per_beam,
            gloss, patterns, force, as_json):
    """Simulate SCENE (m, box, textured, occluded) and write its ISF directory.

    Writes T.npy, samples.csv, manifest.json, photos/ (flashlight, room light and
    projector photos as .npy sample vectors and .exr frames) and truth/ (true
    transport A, T1, n-bounce ISFs and the photos' true bounces).

    With --frames, renders what a camera sees instead (a surface finer than the beam
    grid, laser spots of chosen width, exact interreflections): hdr/beam-NNNNN.exr,
    photos/<kind>.exr, truth/spots.csv (true spot centres) and
    truth/photos/<kind>-bounces.npy (true n-bounce frames); see docs/spots-and-isf.md.
    """
    if gloss > 0 and (frames or scene == "box"):
        raise click.UsageError("--gloss is for the flatland scenes (m, textured, occluded) without --frames")
    if gloss > 0 and tracer_bounces is not None:
        raise click.UsageError("--tracer-bounces and --gloss cannot be combined: the glossy scene's T is the exact solve")
    if patterns and frames:
        raise click.UsageError("--patterns is for the exact scenes, without --frames")
    if frames:
        from ilt.sim.render import render_scene
        from ilt.workspace.simulate import write_frames

        rs = render_scene(scene, beams=beams, albedo=albedo, seed=seed, spot=spot, fine=fine,
                          px_per_beam=px_per_beam)
        params = {"scene": scene, "beams": rs.m, "albedo": albedo, "seed": seed, "spot": spot, "fine": fine,
                  "px_per_beam": px_per_beam}
        with progress_bar(rs.m, "rendering beams") as update:
            path = write_frames(rs, output, params, n_bounces=n_bounces, force=force, progress=update)
        emit(as_json, {"output": str(path), "scene": scene, "m": rs.m, "layout": list(rs.layout),
                       "frame_shape": list(rs.frame_shape)}, [str(path)])
        return
    from ilt.sim import make_scene
    from ilt.workspace.simulate import write_simulation

    sc = make_scene(scene, beams=beams, albedo=albedo, seed=seed)
    params = {"scene": scene, "beams": sc.m, "albedo": albedo, "seed": seed}
    path = write_simulation(sc, output, params, n_bounces=n_bounces, max_bounces=tracer_bounces, force=force,
                            gloss=gloss, patterns=patterns)
    emit(as_json, {"output": str(path), "scene": scene, "m": sc.m, "layout": list(sc.layout)}, [str(path)])
