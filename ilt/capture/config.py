"""The rig's TOML configuration (docs/capture.md is the reference).

``load_config(path)`` reads and checks the file and returns a :class:`RigConfig` of
plain frozen dataclasses; every fault is a :class:`ConfigError` naming the file and
the key.
"""

from __future__ import annotations

import tomllib
from dataclasses import asdict, dataclass, field
from fractions import Fraction
from pathlib import Path


class ConfigError(ValueError):
    """A rig configuration that cannot be used as written."""


@dataclass(frozen=True)
class PTUConfig:
    """Pan-tilt unit: ``port`` is a device path, a pyserial URL (``socket://host:port``)
    or ``"emulator"`` (an emulated unit on a pseudo-terminal, started by ``ilt capture``)."""

    port: str = "emulator"
    baud: int = 9600
    protocol: str = "dp-ascii"
    settle: float = 0.5
    timeout: float = 2.0
    speed: int | None = None
    emulator_speed: int = 2000
    emulator_faults: tuple[str, ...] = ()


@dataclass(frozen=True)
class LaserConfig:
    """``control``: ``ptu-aux`` (commands sent to the pan-tilt unit), ``serial`` (a second
    line speaking the same ``*``/``!`` reply convention) or ``none`` (switched by hand)."""

    control: str = "ptu-aux"
    on: str = "OA1"
    off: str = "OA0"
    port: str = ""
    baud: int = 9600
    timeout: float = 1.0


@dataclass(frozen=True)
class CameraConfig:
    backend: str = "sim"
    model: str = ""
    port: str = ""
    iso: str = ""
    timeout: float = 30.0
    scene: str = "m"
    radiance_scale: float = 1.0e8
    px_per_beam: float = 32.0
    rows: int = 32
    spot: float = 0.1
    seed: int = 0
    faults: tuple[str, ...] = ()


@dataclass(frozen=True)
class Exposure:
    """One frame of the bracket: shutter time (exact, seconds) and f-number."""

    shutter: Fraction
    aperture: float

    @property
    def seconds(self) -> float:
        return float(self.shutter)

    @property
    def relative(self) -> float:
        """Exposure relative to 1 s at f/1: ``t / N^2`` (the sensor's signal is proportional)."""
        return float(self.shutter) / self.aperture**2

    def label(self) -> str:
        s = self.shutter
        t = f"{s.numerator}_{s.denominator}s" if s.denominator != 1 else f"{s.numerator}s"
        return f"{t}-f{self.aperture:g}"

    def as_dict(self) -> dict:
        return {"shutter": str(self.shutter), "exposure_time": self.seconds, "f_number": self.aperture}


@dataclass(frozen=True)
class BracketConfig:
    exposures: tuple[Exposure, ...]
    adaptive: bool = False
    low: float = 1 / 64
    high: float = 0.9
    stride: int = 1


@dataclass(frozen=True)
class DarkConfig:
    """``frames``: ``longest`` (one laser-off frame at the longest exposure taken, as
    ``dark.dng`` of the beam; ``ilt merge`` subtracts it) or ``none``. ``every``: one
    dark frame shot every N beams, the beams between holding a hard link to it (a
    sensor's dark level drifts over minutes, not beams; docs/capture.md measures it)."""

    frames: str = "longest"
    every: int = 1


@dataclass(frozen=True)
class PlanConfig:
    kind: str = "line"
    units: str = "degrees"
    pan: tuple[float, ...] = (-10.0, 10.0)
    tilt: tuple[float, ...] = (0.0,)
    count: int = 16
    shape: tuple[int, int] = (1, 1)
    points: tuple[tuple[float, float], ...] = ()


@dataclass(frozen=True)
class RigConfig:
    path: str
    output: str
    ptu: PTUConfig
    laser: LaserConfig
    camera: CameraConfig
    bracket: BracketConfig
    dark: DarkConfig
    plan: PlanConfig = field(default_factory=PlanConfig)

    def as_dict(self) -> dict:
        """Everything but the file's own path, as plain JSON values (for the manifest)."""
        d = asdict(self)
        d.pop("path")
        d["bracket"]["exposures"] = [e.as_dict() for e in self.bracket.exposures]
        if d["dark"]["every"] == 1:  # as before [dark] every existed: a capture's fingerprint stays
            del d["dark"]["every"]
        return d


PAPER_SHUTTERS = ("1/15", "1/30", "1/60", "1/125", "1/250", "1/500", "1/1000", "1/2000", "1/4000", "1/8000")


def parse_shutter(value, where: str) -> Fraction:
    """``"1/125"``, ``"0.5"``, ``2`` or ``0.004`` as an exact positive number of seconds."""
    try:
        t = Fraction(str(value).strip().removesuffix("s"))
    except (ValueError, ZeroDivisionError):
        raise ConfigError(f"{where}: shutter {value!r} is not a time like '1/125' or 0.5") from None
    if t <= 0:
        raise ConfigError(f"{where}: shutter {value!r} must be > 0")
    return t


def load_config(path: str | Path) -> RigConfig:
    """Read a rig TOML file. Raises ConfigError (naming file and key) or OSError."""
    path = Path(path)
    with open(path, "rb") as f:
        try:
            raw = tomllib.load(f)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    return parse_config(raw, str(path))


def parse_config(raw: dict, where: str = "<config>") -> RigConfig:
    # the stage sections after capture are read by `ilt run` (ilt.workspace.pipeline)
    known = {"output", "ptu", "laser", "camera", "bracket", "dark", "plan",
             "merge", "centroids", "build-isf", "photos", "decompose", "cluster", "refine"}
    for key in raw:
        if key not in known:
            raise ConfigError(f"{where}: unknown section [{key}] (known: {', '.join(sorted(known))})")
    out = raw.get("output", {})
    ptu = _section(PTUConfig, raw.get("ptu", {}), f"{where}: [ptu]")
    laser = _section(LaserConfig, raw.get("laser", {}), f"{where}: [laser]")
    camera = _section(CameraConfig, raw.get("camera", {}), f"{where}: [camera]")
    dark = _section(DarkConfig, raw.get("dark", {}), f"{where}: [dark]")
    plan = _section(PlanConfig, raw.get("plan", {}), f"{where}: [plan]")
    bracket = _bracket(raw.get("bracket", {}), f"{where}: [bracket]")
    _check(ptu.protocol == "dp-ascii", f"{where}: [ptu] protocol {ptu.protocol!r} unknown (known: dp-ascii)")
    _check(ptu.baud > 0 and ptu.settle >= 0 and ptu.timeout > 0,
           f"{where}: [ptu] baud and timeout must be > 0, settle >= 0")
    _check(laser.control in ("ptu-aux", "serial", "none"),
           f"{where}: [laser] control {laser.control!r} unknown (ptu-aux, serial, none)")
    _check(laser.control != "serial" or laser.port,
           f"{where}: [laser] control = 'serial' needs a port")
    _check(camera.backend in ("sim", "gphoto2"), f"{where}: [camera] backend {camera.backend!r} unknown (sim, gphoto2)")
    _check(dark.frames in ("longest", "none"), f"{where}: [dark] frames {dark.frames!r} unknown (longest, none)")
    _check(isinstance(dark.every, int) and not isinstance(dark.every, bool) and dark.every >= 1,
           f"{where}: [dark] every {dark.every!r} must be a whole number of beams >= 1")
    _check(plan.kind in ("line", "grid", "list"), f"{where}: [plan] kind {plan.kind!r} unknown (line, grid, list)")
    _check(plan.units in ("degrees", "steps"), f"{where}: [plan] units {plan.units!r} unknown (degrees, steps)")
    if not isinstance(out, dict):
        out = {"directory": out}
    directory = str(out.get("directory", "capture"))
    # a config says where in the workspace a capture goes; elsewhere is for -o to say
    parts = Path(directory).parts
    _check(bool(parts) and not Path(directory).is_absolute() and ".." not in parts,
           f"{where}: [output] directory {directory!r} must be a relative path inside the workspace "
           "(no '..', not absolute); give 'ilt capture -o DIR' to write elsewhere")
    return RigConfig(where, directory, ptu, laser, camera, bracket, dark, plan)


def _check(ok: bool, message: str) -> None:
    if not ok:
        raise ConfigError(message)


def _section(cls, values: dict, where: str):
    if not isinstance(values, dict):
        raise ConfigError(f"{where}: must be a table")
    fields = cls.__dataclass_fields__
    kwargs = {}
    for key, value in values.items():
        name = key.replace("-", "_")
        if name not in fields:
            raise ConfigError(f"{where}: unknown key {key!r} (known: {', '.join(sorted(fields))})")
        default = fields[name].default
        if isinstance(default, tuple) or isinstance(value, list):
            value = _tuple(value)
        elif isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        elif default is not None and not isinstance(value, type(default)):
            raise ConfigError(f"{where}: {key} = {value!r} should be {type(default).__name__}")
        kwargs[name] = value
    return cls(**kwargs)


def _tuple(value):
    """TOML arrays (nested too) as tuples; a lone value as a 1-tuple."""
    if not isinstance(value, list):
        return (value,)
    return tuple(tuple(v) if isinstance(v, list) else v for v in value)


def _bracket(values: dict, where: str) -> BracketConfig:
    known = {"shutter", "aperture", "extra", "adaptive", "low", "high", "stride"}
    for key in values:
        if key not in known:
            raise ConfigError(f"{where}: unknown key {key!r} (known: {', '.join(sorted(known))})")
    aperture = float(values.get("aperture", 1.2))
    shutters = values.get("shutter", list(PAPER_SHUTTERS))
    if not isinstance(shutters, list) or not shutters:
        raise ConfigError(f"{where}: shutter must be a non-empty list like ['1/15', '1/30']")
    exposures = [Exposure(parse_shutter(s, where), aperture) for s in shutters]
    for i, extra in enumerate(values.get("extra", [])):
        if not isinstance(extra, dict) or set(extra) - {"shutter", "aperture"} or "shutter" not in extra:
            raise ConfigError(f"{where}: extra[{i}] must be {{shutter = '1/8000', aperture = 16}}")
        exposures.append(Exposure(parse_shutter(extra["shutter"], f"{where} extra[{i}]"),
                                  float(extra.get("aperture", aperture))))
    if any(e.aperture <= 0 for e in exposures):
        raise ConfigError(f"{where}: aperture must be > 0")
    if len({(e.shutter, e.aperture) for e in exposures}) != len(exposures):
        raise ConfigError(f"{where}: the same exposure appears twice")
    low, high = float(values.get("low", 1 / 64)), float(values.get("high", 0.9))
    _check(0 < low < high <= 1, f"{where}: need 0 < low < high <= 1, got low={low}, high={high}")
    stride = int(values.get("stride", 1))
    _check(stride >= 1, f"{where}: stride must be >= 1")
    # Longest exposure first: the adaptive rule walks towards shorter ones.
    ordered = sorted(exposures, key=lambda e: -e.relative)
    return BracketConfig(tuple(ordered), bool(values.get("adaptive", False)), low, high, stride)
