"""``ilt simulate``: a synthetic scene as an ISF directory, with ground truth."""

from __future__ import annotations

import click

from ilt.cli.options import bounces_option, emit, force_option, json_option, output_option


@click.command("simulate")
@click.argument("scene", type=click.Choice(["m", "box", "textured", "occluded"]))
@output_option
@click.option("--beams", type=click.IntRange(min=4), default=None,
              help="Number of beams m (default: 128 for flatland scenes, 192 = 3 x 8 x 8 for box).")
@click.option("--albedo", type=click.FloatRange(0, 1, min_open=True, max_open=True), default=None,
              help="Uniform albedo (default 0.7; 'textured' varies around it).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the random parts of a scene.")
@bounces_option
@click.option("--tracer-bounces", type=click.IntRange(min=1), default=None,
              help="Render T with a forward tracer truncated at K bounces, as the paper did (K = 7); "
                   "default: exact transport.")
@force_option
@json_option
def command(scene, output, beams, albedo, seed, n_bounces, tracer_bounces, force, as_json):
    """Simulate SCENE (m, box, textured, occluded) and write its ISF directory.

    Writes T.npy, samples.csv, manifest.json, photos/ (flashlight, room light and
    projector photos as .npy sample vectors and .exr frames) and truth/ (true
    transport A, T1, n-bounce ISFs and the photos' true bounces).
    """
    from ilt.sim import make_scene
    from ilt.simulate import write_simulation

    sc = make_scene(scene, beams=beams, albedo=albedo, seed=seed)
    params = {"scene": scene, "beams": sc.m, "albedo": albedo, "seed": seed}
    path = write_simulation(sc, output, params, n_bounces=n_bounces, max_bounces=tracer_bounces, force=force)
    emit(as_json, {"output": str(path), "scene": scene, "m": sc.m, "layout": list(sc.layout)}, [str(path)])
