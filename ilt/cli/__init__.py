"""The ``ilt`` command line: thin wrappers that parse, call a library function, report.

Exit codes: 0 success; 1 bad input or data (a one-line reason naming the file on
stderr); 2 usage error; 130 interrupted; 143 terminated (SIGTERM); 129 hung up (SIGHUP).
"""

from __future__ import annotations

import logging
import signal
import sys

import click

from ilt import __version__

EXIT_CODES = """\b
Exit codes:
  0    success
  1    bad input or data: one line on stderr names the file and the fault
  2    usage error (unknown option, missing argument)
  129  hung up (SIGHUP), 130 interrupted (Ctrl-C), 143 terminated (SIGTERM):
       nothing partial is left behind"""


#: bad input or data, as opposed to a bug: every ilt error class derives from ValueError,
#: and OSError covers missing, unreadable and unwritable files (and a worker process
#: that died, ilt.parallel.chunks.WorkerError)
USER_ERRORS = (ValueError, OSError)

#: signals that end ilt the way Ctrl-C does
TERMINATING = (signal.SIGTERM, signal.SIGHUP)


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised where Ctrl-C raises KeyboardInterrupt, so that every
    cleanup path that handles Ctrl-C (a staged directory removed, the pool's workers
    stopped, the laser switched off) handles these too."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _terminate(signum, frame) -> None:
    # once: a second signal (a supervisor repeating itself) must not cut short the
    # cleanup the first one started; SIGKILL still ends ilt
    for s in TERMINATING:
        signal.signal(s, signal.SIG_IGN)
    raise Terminated(signum)


class IltError(click.ClickException):
    """A bad input or data: one line on stderr, exit code 1."""

    def show(self, file=None) -> None:
        click.echo(f"ilt: error: {self.message}", err=True)


class IltGroup(click.Group):
    """Turns known failures into exit code 1 and Ctrl-C into 130, for every command."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except USER_ERRORS as exc:
            raise IltError(str(exc)) from None
        except Terminated as exc:
            click.echo(f"ilt: terminated ({exc}); nothing partial is left behind", err=True)
            raise click.exceptions.Exit(128 + exc.signum) from None
        except KeyboardInterrupt:
            click.echo("ilt: interrupted", err=True)
            raise click.exceptions.Exit(130) from None


@click.group(cls=IltGroup, epilog=EXIT_CODES, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="ilt")
@click.option("-v", "--verbose", count=True, help="Debug detail in the log on stderr.")
@click.option("-q", "--quiet", is_flag=True, help="Only errors on stderr.")
def cli(verbose: int, quiet: bool) -> None:
    """Inverse light transport: split photos of a scene into 1-, 2-, 3-...-bounce images.

    Implements Seitz, Matsushita & Kutulakos, "A Theory of Inverse Light Transport"
    (ICCV 2005). Data goes to files, the paths written go to stdout, logs go to stderr.
    """
    level = logging.ERROR if quiet else logging.DEBUG if verbose else logging.INFO
    logging.basicConfig(level=level, format="ilt: %(levelname)s: %(message)s", stream=sys.stderr, force=True)


def _register() -> None:
    """Every module of this package with a ``command`` is a subcommand (one module each)."""
    import importlib
    import pkgutil

    for info in pkgutil.iter_modules(__path__):
        module = importlib.import_module(f"{__name__}.{info.name}")
        if isinstance(getattr(module, "command", None), click.Command):
            cli.add_command(module.command)


_register()


def main() -> None:
    """Console entry point: SIGTERM and SIGHUP end ilt like Ctrl-C (here only, so that a
    program using the library keeps its own handlers), and no process of ilt's (the
    pools' fork server, the resource tracker) outlives it."""
    for s in TERMINATING:
        signal.signal(s, _terminate)
    try:
        cli(prog_name="ilt")
    finally:
        for s in TERMINATING:  # ilt is exiting: let it finish doing so
            signal.signal(s, signal.SIG_IGN)
        if "ilt.parallel.pool" in sys.modules:  # a pool ran (not imported otherwise: it loads OpenImageIO)
            sys.modules["ilt.parallel.pool"].stop_servers()
