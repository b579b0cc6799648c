"""``ilt build-isf``: beam frames and their spots into the impulse scatter matrix T."""

from __future__ import annotations

import click

from ilt.cli.centroids import _count
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
from ilt.workspace.options import BUILD_ISF


@click.command("build-isf")
@click.argument("hdr_dir", required=False, type=click.Path(exists=True, file_okay=False))
@click.argument("spots_dir", required=False, type=click.Path(exists=True, file_okay=False))
@stage_output_option
@stage_option(BUILD_ISF["sampling"], show_default=True,
              help="cell: integrate each frame over every spot's cell; point: read the centroid pixel (the paper).")
@stage_option(BUILD_ISF["min_separation"], show_default=True,
              help="Drop a spot closer than this many pixels to a kept one.")
@stage_option(BUILD_ISF["lit_fraction"], show_default=True,
              help="Pixels whose frame sum is below this fraction of its median at the spots are outside every "
                   "cell (on noisy frames it must also stand above its noise). Raise it where spots/sum.exr shows "
                   "lens flare around the scene.")
@stage_option(BUILD_ISF["max_cell_radius"],
              help="Cells also end this many frame pixels from their spot (default: no limit; cells end "
                   "where the scan's light does, above the frames' noise, whatever the spot spacing).")
@stage_option(BUILD_ISF["fine_degree"], show_default=True,
              help="Also build fine/, the operator of full-resolution bounce images (cell sampling): the "
                   "indirect light of every beam frame as a polynomial of this degree inside each cell, "
                   "fitted in the same pass (0: flat cells; 2 stores 5 m^2 float32 against 2 m^2 for 1).")
@stage_option(BUILD_ISF["no_fine"], help="Do not build fine/: 'ilt decompose' then splits photos at the "
                                        "m samples only.")
@stage_option(BUILD_ISF["fold_cells"], show_default=True,
              help="End the cells at the scene's concave folds, where the light of the beams farther than a "
                   "spot spacing has a valley above the frames' noise (frames without noise: above the photon "
                   "noise of 2e4 e- at their brightest pixel, each frame's disc tapered off to 2 spacings) and "
                   "at least 15% below that light a spacing either side (the dips it makes by itself, once a "
                   "spacing, are shallower). It "
                   "reads each frame again over its spot's rows only (docs/fullres.md, 'A spot on a fold').")
@stage_option(BUILD_ISF["fold_transfer"], show_default=True,
              help="With fold cells, also measure the light the cells beside each fold send across it spread "
                   "over the cell, not from its spot alone (fold_transfer.npz; 'ilt decompose' adds it to T): "
                   "facets light each other the more, the nearer the fold, and a spot a few pixels further "
                   "from the fold than its cell's pixels stands for them badly. 'all' (default): at every fold "
                   "(the box's scans up to 32% better, the M's and textured M's up to 22%, the uneven ones up to "
                   "40%; a box whose spots sit mid-cell 0.3-3% better where its surface is finely rendered, "
                   "docs/fullres.md '3D folds'); "
                   "'flatland': only at the folds whose light is the same along them (a flatland scene's); "
                   "'off'. It reads the frames of the beams beside the folds again (the box's 432 beams: 1.3x "
                   "the build's time, frames of 2.1 MP 1.7x; docs/fullres.md, 'Across a fold').")
@click.option("--keep-covered", type=click.Path(exists=True), metavar="EARLIER_ISF",
              help="An earlier build of the same scene and camera (its ISF directory, or its cells.exr): every "
                   "pixel its cells covered stays covered, so that a denser rescan covers at least what it "
                   "did. (A scan's lit test judges the faint rim of its light against its own noise; 'ilt run' "
                   "passes this between refine passes by itself.)")
@workers_option
@cluster_options
@workspace_option
@force_option
@json_option
def command(hdr_dir, spots_dir, output, sampling, min_separation, lit_fraction, max_cell_radius, fine_degree,
            no_fine, fold_cells, fold_transfer, keep_covered, workers, cluster, workspace, force, as_json):
    """Build the ISF directory (-o, default WORKSPACE/isf) from the beam frames in HDR_DIR
    and the spots in SPOTS_DIR (from 'ilt centroids').

    Writes T.npy (unit columns), scales.npy, samples.csv, cells.exr and fine/ (cell
    sampling), T.png and manifest.json, the directory 'ilt decompose --isf' reads. Flagged beams
    and near-duplicate spots are dropped with a warning and recorded in the manifest.
    On noisy frames (cell sampling) it also measures their noise against the pixel's level
    and writes noise.json and T_var.npy, the variance of every entry of T: 'ilt decompose'
    takes that as T's noise, and the fine fit tells a cell's slope from its noise by it.
    Noise that is a share of each pixel's light (a path tracer's) makes each spot's own
    cell as noisy as its pixels' squares say, or as T's diagonal scatters if that is less
    (noise.json's spot_cells; decompose corrects the inverse's bias by it). On noisy
    frames a pixel 6 sigma above all 8 of its neighbours (a path tracer's firefly, a hot
    pixel; the spot's own disc excepted) is replaced by their median before the sums,
    and the manifest counts them ('outliers'). The frames on disk are not changed.

    Run by hand after 'ilt centroids', this decodes every frame a second time; 'ilt
    run' runs the two stages on frames decoded once (centroids keeps them for this
    stage), with the same result bit for bit.
    """
    from ilt.isf.build import build_isf
    from ilt.parallel.cluster import executor_for

    hdr_dir, spots_dir = workspace.resolve(hdr_dir, "merge"), workspace.resolve(spots_dir, "centroids")
    output = workspace.resolve(output, "build-isf")
    require_dir(hdr_dir, "the HDR frames", "run 'ilt merge' first, or give HDR_DIR")
    require_dir(spots_dir, "the spots", "run 'ilt centroids' first, or give SPOTS_DIR")

    with executor_for(cluster, workers) as executor, progress_bar(_count(hdr_dir), "build-isf") as update:
        summary = build_isf(hdr_dir, spots_dir, output, sampling=sampling, min_separation=min_separation,
                            lit_fraction=lit_fraction, max_cell_radius=max_cell_radius, executor=executor,
                            workers=workers,
                            fine_degree=None if no_fine else fine_degree, keep_covered=keep_covered,
                            fold_cells=fold_cells, fold_transfer=fold_transfer, progress=update, force=force)
    emit(as_json, summary, [summary["output"]])
