"""``ilt capture``: drive the rig through a beam plan and write a capture directory."""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

import click

from ilt.cli.options import MissingInput, emit, informing, json_option, workspace_option

log = logging.getLogger(__name__)


@click.command("capture")
@click.argument("config", required=False, type=click.Path(dir_okay=False))
@click.option("-o", "--output", type=click.Path(file_okay=False), default=None,
              help="Capture directory (default: the config's [output] directory in the workspace).")
@click.option("--resume", is_flag=True,
              help="Continue an interrupted capture: complete beams are skipped, the interrupted one is shot again.")
@click.option("--estimate", is_flag=True,
              help="Print the scan's expected time (moves, settles, exposures, downloads, dark frames) and "
                   "exit; nothing is opened or moved. Timings measured in earlier capture logs are used "
                   "(the output directory's capture.jsonl, and any --log).")
@click.option("--log", "logs", multiple=True, type=click.Path(dir_okay=False, exists=True),
              help="With --estimate: an earlier scan's capture.jsonl to measure timings from (repeatable).")
@workspace_option
@json_option
def command(config, output, resume, estimate, logs, workspace, as_json):
    """Scan the beams of CONFIG (a rig TOML file, default WORKSPACE/rig.toml; docs/capture.md).

    Per beam: move the pan-tilt unit, settle, laser on, bracket of RAW exposures,
    laser off, dark frame. Every frame is logged in capture.jsonl; Ctrl-C stops with
    the laser off, and --resume goes on where the scan stopped. `configs/sim.toml`
    runs on the emulated rig. --estimate prints the expected hours first.
    """
    from ilt.capture.camera import check_sim_camera
    from ilt.capture.config import load_config
    from ilt.capture.loop import capture

    path = config or workspace.config
    if not Path(path).is_file():
        raise MissingInput(f"{path}: no such rig config; give a rig TOML (the simulated rig's is "
                           "configs/sim.toml, docs/capture.md)")
    cfg = load_config(path)
    if estimate:
        from ilt.capture.estimate import default_logs
        from ilt.capture.estimate import estimate as estimate_scan

        result = estimate_scan(cfg, [*logs, *default_logs(cfg, workspace.root, output)])
        if as_json:
            emit(True, result.as_dict(), [])
        else:
            click.echo(result.table())
        return
    if logs:
        raise click.UsageError("--log is for --estimate")
    check_sim_camera(cfg)
    output = output or str(workspace.root / cfg.output)
    start = time.monotonic()

    def on_beam(result, done, total):
        if not informing():
            return  # -q: only errors on stderr
        eta = (time.monotonic() - start) / done * (total - done)
        skipped = f", {result.skipped} exposures skipped" if result.skipped else ""
        if sys.stderr.isatty():
            width = 24
            bar = "#" * round(width * done / total)
            click.echo(f"\r[{bar:<{width}}] beam {result.beam} ({done}/{total}) {result.seconds:.1f} s"
                       f"{skipped}, ETA {eta:.0f} s", err=True, nl=done == total)
        elif done == total or done % max(1, total // 10) == 0:  # a log: a line every tenth of the scan
            log.info("capture: %d/%d beams, ETA %.0f s%s", done, total, eta, skipped)

    summary = capture(cfg, output, resume=resume, on_beam=on_beam)
    if summary["exposures_skipped"]:
        full, skipped = summary["exposures_full"], summary["exposures_skipped"]
        log.info("adaptive bracketing skipped %d of %d exposures (%.0f%%), about %.1f s saved",
                 skipped, full, 100 * skipped / full, summary["seconds_saved"])
    emit(as_json, summary, [summary["output"]])
