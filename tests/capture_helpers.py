"""Small rigs for the capture tests: tiny frames, few beams, short brackets."""

from __future__ import annotations

from pathlib import Path

from ilt.capture.config import parse_config
from ilt.io.manifest import fingerprint_file

SMALL = {
    "ptu": {"port": "emulator", "settle": 0.0, "timeout": 0.5, "emulator_speed": 20000},
    "laser": {"control": "ptu-aux"},
    "camera": {"backend": "sim", "scene": "m", "px_per_beam": 8.0, "rows": 22, "model": "ilt SimSensor"},
    "bracket": {"shutter": ["1/15", "1/250", "1/4000"], "aperture": 1.2},
    "dark": {"frames": "longest"},
    "plan": {"kind": "line", "pan": [-5.0, 5.0], "tilt": 0.0, "count": 8},
}


def small_config(**sections):
    raw = {k: dict(v) for k, v in SMALL.items()}
    for name, values in sections.items():
        raw.setdefault(name, {}).update(values)
    return parse_config(raw, "test.toml")


def toml_text(**sections) -> str:
    raw = {k: dict(v) for k, v in SMALL.items()}
    for name, values in sections.items():
        raw.setdefault(name, {}).update(values)
    out = []
    for name, values in raw.items():
        out.append(f"[{name}]")
        for k, v in values.items():
            out.append(f"{k} = {_toml(v)}")
    return "\n".join(out) + "\n"


def _toml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml(x)}" for k, x in v.items()) + "}"
    return repr(v)


def frame_hashes(directory: Path) -> dict[str, str]:
    """relative path -> sha256 of every file of the beam directories (what merge reads)."""
    return {str(p.relative_to(directory)): fingerprint_file(p)
            for p in sorted(directory.glob("beam-*/*")) if p.is_file()}


def pointing_of(emu, laser_emu=None):
    return lambda: (emu.position("P"), emu.position("T"), (laser_emu or emu).aux)


def run_rig_toml(count: int, px_per_beam: float, camera: str, tail: str) -> str:
    """A rig config for `ilt run` tests: the emulated unit, the sim camera on the M scene
    (``camera``: its extra lines), a short paper-like bracket with an f/16 frame, a line
    of ``count`` beams, then ``tail`` (the later stages' sections)."""
    return f"""\
[ptu]
port = "emulator"
settle = 0.0
emulator_speed = 20000

[camera]
backend = "sim"
model = "ilt SimSensor"
scene = "m"
px_per_beam = {px_per_beam:.1f}
rows = {int(px_per_beam)}
{camera}

[bracket]
shutter = ["1/15", "1/125", "1/1000", "1/8000"]
aperture = 1.2
extra = [{{ shutter = "1/8000", aperture = 16 }}]

[plan]
kind = "line"
pan = [-20.0, 20.0]
tilt = 0.0
count = {count}

{tail}"""


#: the small simulated rig of the workspace tests (8 x 8 beams, one photo, 4 bounces)
SMALL_RIG = run_rig_toml(8, 8, "radiance_scale = 1.0e8", """\
[centroids]
workers = 1

[build-isf]
workers = 1

[photos]
sim = ["flashlight"]

[decompose]
bounces = 4
""")
