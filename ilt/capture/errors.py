"""Typed rig errors.

Every one derives from ``OSError`` (a device or I/O fault, not a bug), so the CLI
reports it as one line and exit code 1.
"""

from __future__ import annotations


class RigError(OSError):
    """A fault of the rig: pan-tilt unit, laser or camera."""

    def __init__(self, message: str):
        super().__init__(message)
        self.message = message

    def __str__(self) -> str:
        return self.message


class PTUError(RigError):
    """The pan-tilt unit failed."""


class RigTimeout(PTUError):
    """A device did not answer within its time limit."""


class DeviceError(PTUError):
    """The pan-tilt unit answered ``! message``."""


class LimitHit(PTUError):
    """The pan-tilt unit reported ``!P`` or ``!T`` (an axis hit its limit) during a move."""


class Disconnected(PTUError):
    """The serial line (or socket) to a device went away."""


class LaserError(RigError):
    """The laser could not be switched."""


class CameraError(RigError):
    """The camera failed, or is not the one configured."""
