"""``ilt status``: each stage of a workspace, done, stale (why) or missing."""

from __future__ import annotations

import click

from ilt.cli.options import emit, json_option, workspace_option


@click.command("status")
@click.argument("config", required=False, type=click.Path(dir_okay=False))
@workspace_option
@click.option("--verify", is_flag=True,
              help="Re-hash every file of every done stage against its manifest; a file that differs makes "
                   "its stage 'changed' (named with the file).")
@json_option
def command(config, workspace, verify, as_json):
    """Say for each stage of the workspace whether `ilt run` would skip it (done), re-run
    it (stale: which input or parameter changed), run it for the first time (missing)
    or refuse to build on it (changed: its files differ from its manifest), against
    CONFIG (default WORKSPACE/rig.toml). Reads manifests and looks at each file's size
    and modification time, hashing only files where these moved; --verify hashes them all.

    Exit code 0 whatever the states; --json for scripts.
    """
    from ilt.workspace.pipeline import workspace_config, workspace_status

    states = workspace_status(workspace, workspace_config(workspace, config), verify="full" if verify else "quick")
    if as_json:
        emit(True, [s.as_dict() for s in states], [])
    else:
        width = max(len(s.stage) for s in states)
        for s in states:
            click.echo(f"{s.stage:<{width}}  {s}")
