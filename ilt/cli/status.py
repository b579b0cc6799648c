"""``ilt status``: each stage of a workspace, done, stale (why) or missing."""

from __future__ import annotations

import click

from ilt.cli.options import emit, json_option, workspace_option


@click.command("status")
@click.argument("config", required=False, type=click.Path(dir_okay=False))
@workspace_option
@json_option
def command(config, workspace, as_json):
    """Say for each stage of the workspace whether `ilt run` would skip it (done), re-run
    it (stale: which input or parameter changed) or run it for the first time (missing),
    against CONFIG (default WORKSPACE/rig.toml). Reads manifests only.

    Exit code 0 whatever the states; --json for scripts.
    """
    from ilt.pipeline import workspace_config, workspace_status

    states = workspace_status(workspace, workspace_config(workspace, config))
    if as_json:
        emit(True, [s.as_dict() for s in states], [])
    else:
        width = max(len(s.stage) for s in states)
        for s in states:
            click.echo(f"{s.stage:<{width}}  {s}")
