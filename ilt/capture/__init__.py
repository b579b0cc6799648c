"""Drive the paper's rig (Sec. 4): pan-tilt unit, laser and camera, beam by beam.

``config`` reads the rig's TOML file, ``plan`` turns it into beam directions,
``ptu`` speaks the FLIR/Directed Perception ASCII protocol over pyserial,
``emulator`` is a pan-tilt unit on a pseudo-terminal or a loopback socket,
``laser`` switches the beam, ``camera`` shoots brackets (simulated or gphoto2),
``adaptive`` decides which exposures a beam needs, and ``loop`` runs the scan:
append-only log, atomic frames, resume.
"""

from .errors import (
    CameraError,
    DeviceError,
    Disconnected,
    LaserError,
    LimitHit,
    PTUError,
    RigError,
    RigTimeout,
)

__all__ = [
    "CameraError",
    "DeviceError",
    "Disconnected",
    "LaserError",
    "LimitHit",
    "PTUError",
    "RigError",
    "RigTimeout",
]
