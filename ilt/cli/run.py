"""``ilt run``: every stage of a workspace, skipping what is up to date."""

from __future__ import annotations

import time

import click

from ilt.cli.options import cluster_options, emit, json_option, note, progress_bar, workspace_option


@click.command("run")
@click.argument("config", required=False, type=click.Path(dir_okay=False))
@workspace_option
@click.option("--force", is_flag=True, help="Re-run every stage (a previous scan is moved aside, never deleted).")
@cluster_options
@json_option
def command(config, workspace, force, cluster, as_json):
    """Capture, merge, centroids, build-isf, photos and decompose for CONFIG (a rig
    TOML, default WORKSPACE/rig.toml) in the workspace, like make: a stage whose
    parameters and inputs have not changed since it ran is skipped; a changed one
    re-runs with every stage after it; an interrupted capture is resumed. The photos
    stage shoots and merges the [photos] sim illuminations on the simulated rig;
    decompose splits them and the [photos] files, at full resolution when build-isf
    made isf/fine/.

    CONFIG is copied to WORKSPACE/rig.toml; a rig.toml edited since the last run copied
    it is moved aside to rig.toml.previous-N first (a warning names what differs),
    never overwritten. A run refuses to start when a done stage's files differ from
    its manifest (`ilt status --verify` lists them all). Stages made by hand (ilt
    merge, centroids, build-isf) with the config's parameters count as done.

    --scheduler or --scheduler-file (else the config's [cluster] scheduler or
    scheduler-file, else $DASK_SCHEDULER_ADDRESS) runs merge, centroids and build-isf on a
    Dask cluster, through TLS with the [cluster] ca, cert and key (docs/cluster.md); the
    stages' files are the same, and a stage done on one is up to date on the other.

    Prints the workspace's stage directories; `ilt status` says what is up to date.
    """
    from ilt.parallel.cluster import executor_for
    from ilt.workspace.pipeline import run_pipeline, workspace_config

    start = time.monotonic()
    cfg = workspace_config(workspace, config)
    # connected before anything is written: an unreachable scheduler leaves no workspace
    with executor_for(cluster.over(cfg.cluster)) as executor:
        summaries = run_pipeline(workspace, cfg, force=force, progress=progress_bar, executor=executor)
    ran = [s["stage"] for s in summaries if s["ran"]]
    note(f"ilt: run: {'ran ' + ', '.join(ran) if ran else 'every stage was up to date'} "
         f"({time.monotonic() - start:.1f} s)")
    emit(as_json, summaries, [s["directory"] for s in summaries])
