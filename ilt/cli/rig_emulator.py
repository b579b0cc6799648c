"""``ilt rig-emulator``: an emulated pan-tilt unit for testing scripts without hardware."""

from __future__ import annotations

import sys

import click


@click.command("rig-emulator")
@click.option("--socket", "tcp_port", type=click.IntRange(0, 65535), default=None,
              help="Serve on socket://127.0.0.1:PORT (0: any free port) instead of a pseudo-terminal.")
@click.option("--fault", "faults", multiple=True, metavar="KIND:COMMAND@N",
              help="Inject a fault (drop, timeout, error, limit, unplug) on the N-th COMMAND; repeatable.")
@click.option("--speed", type=click.IntRange(min=1), default=2000, show_default=True, help="Steps per second.")
@click.option("--laser-on", default="OA1", show_default=True, help="Command that switches the aux output on.")
@click.option("--laser-off", default="OA0", show_default=True, help="Command that switches it off.")
def command(tcp_port, faults, speed, laser_on, laser_off):
    """Run an emulated PTU-D46 (FLIR/Directed Perception ASCII protocol) until Ctrl-C.

    Prints the port to open on stdout (a /dev/pts path, or socket://127.0.0.1:PORT),
    e.g. for `[ptu] port` of a rig config or `python -m serial.tools.miniterm`.
    """
    from ilt.capture.emulator import PTUEmulator

    emu = PTUEmulator("pty" if tcp_port is None else "socket", faults=faults, speed=speed,
                      laser_on=laser_on, laser_off=laser_off, tcp_port=tcp_port or 0)
    emu.start()
    click.echo(emu.port)
    sys.stdout.flush()
    try:
        while not emu.unplugged:
            emu._stop.wait(0.2)
    finally:
        emu.stop()
