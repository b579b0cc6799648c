"""``ilt calibrate``: Mitsunaga-Nayar radiometric self-calibration of a bracket."""

from __future__ import annotations

import click

from ilt.cli.options import emit, force_option, json_option, note


@click.command("calibrate")
@click.argument("inputs", nargs=-1, required=True, metavar="IMAGES_OR_DIR...", type=click.Path())
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False),
              help="response.json to write (a .png plot is written beside it).")
@click.option("--times", default=None,
              help="Exposure times of the files, e.g. 1/15,1/30, in their order; they override EXIF (with a "
                   "warning where EXIF differs by more than 1/6 stop); a capture manifest's times come first.")
@click.option("--order", type=click.IntRange(1, 10), default=None,
              help="Polynomial order (default: chosen on held-out pixels).")
@click.option("--max-order", type=click.IntRange(1, 10), default=None,
              help="Highest order tried (default 3 for RAW, 12 otherwise).")
@click.option("--pin-span/--free-span", default=None,
              help="Keep the product of exposure ratios at the nominal one (default: on for "
                   "non-RAW images, off for RAW).")
@click.option("--estimate-ratios/--trust-ratios", default=None,
              help="Estimate the exposure ratios with f (default: on for RAW, whose f is close to "
                   "linear; off for other images, where f and the ratios are ambiguous).")
@click.option("--tolerance", type=click.FloatRange(min=0, min_open=True), default=1e-6, show_default=True,
              help="Stop when f changes by less than this at every M.")
@click.option("--no-plot", is_flag=True, help="Do not write the PNG plot.")
@force_option
@json_option
def command(inputs, output, times, order, max_order, pin_span, estimate_ratios, tolerance, no_plot, force,
            as_json):
    """Estimate the inverse response f and true exposure ratios from IMAGES_OR_DIR.

    IMAGES_OR_DIR: the frames of one bracket (RAW, or 8/16-bit TIFF/PNG/JPEG), a beam
    directory, or a capture directory (up to 8 beams pooled). f is monotone with
    f(0) = 0 and f(1) = 1. Writes its polynomial coefficients (power and Bernstein
    form), f sampled at 256 points, the exposure ratios, residual and max |f(M) - M|;
    -o's directory is made if missing.
    """
    from ilt.hdr.stages import calibrate
    from ilt.io.exposure import parse_times

    path, result = calibrate(list(inputs), output, times=parse_times(times) if times else None,
                             order=order, max_order=max_order, pin_span=pin_span,
                             estimate_ratios=estimate_ratios, tolerance=tolerance, plot=not no_plot, force=force)
    note(f"ilt: order {result['order']}, residual {result['residual']:.3g}, "
         f"max |f(M) - M| = {result['linearity_error']:.3g}")
    emit(as_json, result, [str(path)])
