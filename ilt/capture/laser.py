"""The laser: switched through the pan-tilt unit's auxiliary output or a second serial line.

:func:`laser_off` is the one way every error path turns the beam off: it never raises,
and says so in the log when the laser's state is unknown.
"""

from __future__ import annotations

import logging

from .errors import LaserError, RigError
from .ptu import SerialLine

log = logging.getLogger(__name__)


class Laser:
    """``on()`` / ``off()`` send the configured commands; ``state`` is the last one
    acknowledged (None when unknown, after a failure)."""

    def __init__(self, line: SerialLine | None, on: str, off: str, owns_line: bool):
        self.line, self.commands, self.owns_line = line, (on, off), owns_line
        self.state: bool | None = None

    def _set(self, on: bool) -> None:
        self.state = None
        if self.line is not None:
            try:
                self.line.command(self.commands[0 if on else 1])
            except RigError as exc:
                raise LaserError(f"laser could not be switched {'on' if on else 'off'}: {exc}") from None
        self.state = on

    def on(self) -> None:
        self._set(True)

    def off(self) -> None:
        self._set(False)

    def close(self) -> None:
        if self.owns_line and self.line is not None:
            self.line.close()


def open_laser(cfg, ptu_line: SerialLine | None) -> Laser:
    """The laser of a [laser] table; ``ptu_line`` carries ``ptu-aux`` commands."""
    if cfg.control == "ptu-aux":
        return Laser(ptu_line, cfg.on, cfg.off, owns_line=False)
    if cfg.control == "serial":
        return Laser(SerialLine(cfg.port, cfg.baud, cfg.timeout, "laser"), cfg.on, cfg.off, owns_line=True)
    log.warning("laser control 'none': switch the laser by hand; frames are labelled as if it obeyed")
    return Laser(None, cfg.on, cfg.off, owns_line=False)


def laser_off(laser: Laser | None) -> bool:
    """Turn the laser off, whatever happened before; True when the unit acknowledged."""
    if laser is None:
        return True
    try:
        laser.off()
        return True
    except LaserError as exc:
        log.error("%s; SWITCH THE LASER OFF BY HAND", exc)
        return False
