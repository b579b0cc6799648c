"""Options shared by several commands, defined once so they mean the same everywhere."""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import sys
import time
from pathlib import Path

import click

from ilt.parallel.cluster import ClusterConfig
from ilt.workspace.options import BOUNCES, MAX_BOUNCES, WORKERS, StageOption


def stage_option(option: StageOption, *short: str, **kwargs):
    """The click option of a stage option (:mod:`ilt.workspace.options`): its long flag,
    parameter name, default and type from there; ``short`` flags, help and the rest here."""
    kind = {"is_flag": True} if isinstance(option.default, bool) else {"type": option.type}
    # a flag on by default is turned off by --no-FLAG
    flag = f"--{option.flag}/--no-{option.flag}" if option.default is True else f"--{option.flag}"
    return click.option(*short, flag, option.name, default=option.default, **kind, **kwargs)


force_option = click.option("--force", is_flag=True, help="Replace outputs that already exist.")
json_option = click.option(
    "--json", "as_json", is_flag=True, help="Print a machine-readable JSON summary on stdout."
)
output_option = click.option(
    "-o", "--output", "output", required=True, type=click.Path(file_okay=False),
    help="Directory to write (created; must not exist unless --force).",
)
bounces_option = stage_option(
    BOUNCES, show_default=True,
    help=f"Number of bounce images N to compute (at most {MAX_BOUNCES}: after that many bounces at most "
         "albedo^1000 of the light is left, 4e-5 even at albedo 0.99).",
)
workers_option = stage_option(
    WORKERS, "-j", show_default="all cores",
    help="Worker processes, one core each (1: in this process). No output depends on it.",
)


def cluster_options_for(work: str):
    """``--scheduler``, ``--scheduler-file`` and ``--insecure`` (ilt.parallel.cluster), runtime
    options like --workers, handed to the command as one ``cluster``, a
    :class:`ilt.parallel.cluster.ClusterConfig`; ``work``: what runs on the cluster (the help names it)."""
    scheduler = click.option(
        "--scheduler", "scheduler", default=None, metavar="ADDRESS",
        help=f"Run {work} on a Dask cluster (pip install 'ilt[cluster]'; docs/cluster.md): "
             "'local' is a LocalCluster of single-threaded processes on this machine's loopback (--workers of them "
             "where the command has it, else one a core); tls://HOST:8786 a running 'dask scheduler' through TLS "
             "(certificates: Dask's configuration; ilt run: [cluster] ca, cert, key); tcp://HOST:8786 plain TCP, "
             "on this machine only unless --insecure. Every worker must see the files at the same path. Default: "
             "$DASK_SCHEDULER_ADDRESS when set, else this machine. No output depends on it; an unreachable "
             "scheduler is an error (10 s).",
    )
    scheduler_file = click.option(
        "--scheduler-file", "scheduler_file", default=None, metavar="PATH",
        type=click.Path(dir_okay=False, path_type=Path),
        help="The scheduler's address from this JSON file, as 'dask scheduler --scheduler-file PATH' (and "
             "dask-jobqueue's) writes it; waited for up to 10 s. Instead of --scheduler.",
    )
    insecure = click.option(
        "--insecure", is_flag=True,
        help="Allow a plain tcp:// scheduler on another machine: the network is trusted (whoever can reach a "
             "scheduler's port runs code as its user; docs/cluster.md).",
    )

    def decorate(command):
        @functools.wraps(command)
        def with_cluster(*args, scheduler, scheduler_file, insecure, **kwargs):
            if scheduler and scheduler_file:
                raise click.UsageError("give --scheduler or --scheduler-file, not both")
            return command(*args, cluster=ClusterConfig(scheduler, scheduler_file, insecure=insecure), **kwargs)

        for option in (insecure, scheduler_file, scheduler):   # (click lists them bottom-up)
            with_cluster = option(with_cluster)
        return with_cluster

    return decorate


#: the cluster options of the per-beam stages
cluster_options = cluster_options_for("the per-beam work")


class MissingInput(ValueError):
    """An input a command needs is not there."""


def require_dir(path, what: str, hint: str) -> None:
    """Raise :class:`MissingInput` naming ``path`` and how to make it, unless it is a directory."""
    path = Path(path)
    if not path.is_dir():
        state = "not a directory" if path.exists() else "no such directory"
        raise MissingInput(f"{path}: {state} ({what}); {hint}")


def informing() -> bool:
    """Whether the log on stderr shows INFO (not ``-q``)."""
    return logging.getLogger().isEnabledFor(logging.INFO)


def note(text: str) -> None:
    """A result for people (a table, where the figures are) on stderr; nothing with ``-q``."""
    if informing():
        click.echo(text, err=True)


@contextlib.contextmanager
def progress_bar(length: int, label: str):
    """Yield ``update(n)`` of the progress of ``length`` beams on stderr: a bar with ETA
    on a terminal; in a log (stderr not a terminal) a line every tenth of the way,
    ``ilt: INFO: merge: 16/32 beams, ETA 3 s``; nothing with ``-q``."""
    if not informing() or length <= 0:
        yield lambda n=1: None
        return
    if sys.stderr.isatty():
        with click.progressbar(length=length, label=label, file=sys.stderr, show_eta=True) as bar:
            yield bar.update
        return
    start, done, step = time.monotonic(), 0, max(1, length // 10)

    def update(n=1):
        nonlocal done
        before, done = done, done + n
        if done // step > before // step or done >= length > before:
            eta = (time.monotonic() - start) / done * max(0, length - done)
            logging.getLogger("ilt").info("%s: %d/%d beams, ETA %.0f s", label, min(done, length), length, eta)

    yield update


def emit(as_json: bool, summary, paths: list[str]) -> None:
    """What a pipe needs goes to stdout: the JSON summary, or the paths written."""
    if as_json:
        json.dump(summary, sys.stdout, indent=2, default=str)
        sys.stdout.write("\n")
    else:
        for p in paths:
            click.echo(p)


def _workspace(ctx, param, value):
    from ilt.io.workspace_dirs import Workspace

    return Workspace(value)


#: every stage command: ``workspace.resolve(path_given, stage)`` is the path given, else
#: the stage's standard directory in the workspace (ilt/io/workspace_dirs.py)
workspace_option = click.option(
    "-w", "--workspace", "workspace", type=click.Path(file_okay=False), default=".", show_default=True,
    callback=_workspace,
    help="Workspace directory; stage directories not given are its capture/ hdr/ spots/ isf/ decompose/.",
)
#: ``-o`` of a stage command: default, the stage's directory in the workspace
stage_output_option = click.option(
    "-o", "--output", "output", default=None, type=click.Path(file_okay=False),
    help="Directory to write (default: the stage's directory in the workspace; must not exist unless --force).",
)
