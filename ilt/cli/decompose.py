"""``ilt decompose``: photos to n-bounce images."""

from __future__ import annotations

from pathlib import Path

import click

from ilt.cli.options import (
    bounces_option,
    cluster_options_for,
    emit,
    force_option,
    json_option,
    stage_option,
    stage_output_option,
    workspace_option,
)
from ilt.workspace.options import DECOMPOSE


@click.command("decompose")
@click.argument("inputs", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("--isf", "isf_path", default=None, type=click.Path(),
              help="ISF directory (T.npy, samples.csv, manifest.json) or a T .npy file (default WORKSPACE/isf).")
@stage_output_option
@bounces_option
@stage_option(DECOMPOSE["tol"], show_default=True,
              help="Stop once ||Ln|| / ||L|| < TOL for every input column (0: compute all N).")
@click.option("--cache-dir", type=click.Path(file_okay=False), default=None,
              help="Where factorised operators are kept between runs "
                   "(default $ILT_CACHE_DIR, else $XDG_CACHE_HOME/ilt).")
@click.option("--no-cache", is_flag=True, help="Do not read or write the operator cache.")
@click.option("--solver", type=click.Choice(["auto", "dense", "mixed", "blocks", "series", "compressed"]),
              default="auto", show_default=True,
              help="How C1 is built: dense LU (reference), mixed float32/float64, blocks for independent "
                   "groups of points, series (products with T sparse at the noise floor, for locally coupled "
                   "scenes), compressed (T low-rank off its diagonal to the noise floor, for large m); auto "
                   "picks by structure, size and noise and says why.")
@click.option("--noise", type=click.FloatRange(min=0), default=None,
              help="Noise sigma of T relative to its unit columns (default: the ISF's noise.json, measured "
                   "from the beam frames by build-isf, else from T's negative entries when it has some); "
                   "blocks and series treat entries below it as zero, compressed compresses T to it.")
@click.option("--regularise/--no-regularise", default=None,
              help="Denoise T before inverting it: smooth its indirect part along pixels and beams (neighbouring "
                   "cells, or the plan's grid without cells), edge-aware (neighbours whose light differs by more "
                   "than the noise are not averaged), as wide as its estimated error against the true T is least "
                   "(SURE with each entry's noise from T_var.npy) and within the noise (discrepancy principle). "
                   "Default: on when T's noise is known (build-isf's noise.json, or --noise) and "
                   "m <= 4096; summary.json says what was done and why.")
@stage_option(DECOMPOSE["samples_only"],
              help="Split the photo at the m samples only: skip the full-resolution bounce images "
                   "(the ISF's fine/ operator).")
@stage_option(DECOMPOSE["accept_non_lambertian"],
              help="Write the bounces even when T fails the Lambertian check (isf/lambertian.json says "
                   "'not lambertian') or the bounce series diverges (spectral radius of A = I - C1 >= 1); every "
                   "output then records the verdict. Without it such a T is refused, nothing written.")
@click.option("--no-spill", "no_spill", is_flag=True,
              help="Take T1 diagonal, as the paper does, even when the ISF measured its spots' direct light "
                   "in neighbouring cells (isf/spill.npz): by default that light is taken out of T first, "
                   "so it is not read as interreflection (docs/spots-and-isf.md).")
@click.option("--no-fold-transfer", "no_fold_transfer", is_flag=True,
              help="Use T as measured, each cell's light sent from its spot, even where the ISF measured the "
                   "light its cells send across the scene's folds spread over the cell (isf/fold_transfer.npz, "
                   "docs/fullres.md 'Across a fold').")
@cluster_options_for("the compression of T's blocks, with the compressed solver (T.npy on storage every "
                     "worker sees; the other solvers, the photos and the outputs stay on this machine)")
@workspace_option
@force_option
@json_option
def command(inputs, isf_path, output, n_bounces, tol, cache_dir, no_cache, solver, noise, regularise, samples_only,
            accept_non_lambertian, no_spill, no_fold_transfer, cluster, workspace, force, as_json):
    """Split each INPUT into its 1..N-bounce images, the indirect sum and the residual.

    INPUT is an EXR photo on the grid of the beam frames (integrated over the ISF's
    cells, or read at its sample pixels) or a .npy of sample vectors, shape (m,) or
    (m, k). Results go to <input stem>/ in -o (default WORKSPACE/decompose): for an EXR
    photo and an ISF with a fine operator (ilt build-isf writes isf/fine/), bounce-<n>.exr
    (n = 1..N), indirect.exr, residual.exr and coverage.exr at the photo's own resolution (photo = sum of the
    bounces + residual at every pixel; coverage 1 where the scan models a pixel's
    indirect light, 0.5 on the rim within 10 px of a cell, where a pixel takes its
    nearest cell's indirect light up to the photo's; no pixel holds more indirect light than
    the photo does, plus 3 sigma of the noise read off the photo's own pixels (at each
    pixel's level, the median of the 5 x 5 pixels about it), and its cell's
    other pixels take the rest: summary.json's bounded_pixels);
    always bounces.npy (N, m[, k]), residual.npy, samples/ (the
    sample-level images: a strip or grid in the ISF's layout, and *.frame.exr cell
    mosaics), preview.png and summary.json with the diagnostics. Pixels that 'ilt
    merge' marked saturated (<stem>.saturated.png beside the photo) are left out of
    the full-resolution images and counted.
    """
    from ilt.decompose.stage import decompose, default_cache_dir
    from ilt.isf.directory import load_isf
    from ilt.parallel.cluster import executor_for

    isf_path, output = workspace.resolve(isf_path, "build-isf"), workspace.resolve(output, "decompose")
    isf = load_isf(isf_path, mmap=True)  # T is never held twice: solvers copy or read it as they need
    cache = None if no_cache else (Path(cache_dir) if cache_dir else default_cache_dir())
    with executor_for(cluster) as executor:
        summaries = decompose(isf, list(inputs), output, n_bounces=n_bounces, tol=tol, cache_dir=cache,
                              force=force, solver=solver, noise=noise, regularise=regularise,
                              samples_only=samples_only, executor=executor, spill=not no_spill,
                              accept_non_lambertian=accept_non_lambertian, fold_transfer=not no_fold_transfer)
    emit(as_json, summaries, [s["output"] for s in summaries])
