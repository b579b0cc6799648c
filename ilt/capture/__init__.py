"""Drive the paper's rig (Sec. 4): pan-tilt unit, laser and camera, beam by beam.

``config`` reads the rig's TOML file, ``plan`` turns it into beam directions,
``ptu`` speaks the FLIR/Directed Perception ASCII protocol over pyserial,
``emulator`` is a pan-tilt unit on a pseudo-terminal or a loopback socket,
``laser`` switches the beam, ``camera`` shoots brackets (simulated or gphoto2),
``adaptive`` decides which exposures a beam needs, ``loop`` runs the scan:
append-only log, atomic frames, resume, and ``estimate`` says how long it will take.
"""

from ilt import lazy_face

__getattr__, __dir__, __all__ = lazy_face(
    __name__,
    {
        "config": ["ConfigError", "Exposure", "RigConfig", "load_config", "parse_config"],
        "errors": ["CameraError", "DeviceError", "Disconnected", "LaserError", "LimitHit", "PTUError", "RigError", "RigTimeout"],
        "log": ["CaptureLog", "CaptureLogError", "read_log"],
        "loop": ["capture", "verify_log"],
        "plan": ["make_plan"],
        "ptu": ["PanTilt"],
        "emulator": ["LaserEmulator", "PTUEmulator"],
        "estimate": ["Estimate", "estimate", "measure_logs"],
    },
)
