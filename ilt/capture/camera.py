"""Cameras behind one interface: ``sim`` (the simulated scene through the simulated
sensor, as real DNG files) and ``gphoto2`` (a real camera through libgphoto2).

A camera has ``model``, ``suffix`` (file extension of its RAW files), ``describe()``,
``shoot(path, exposure, key) -> dict`` (writes one frame to ``path`` and returns the
settings read back from the camera) and ``close()``. ``key`` names the frame
(beam, kind, exposure) so the simulated camera's noise is the same on every run.
"""

from __future__ import annotations

import errno
import logging
import re
import time
import zlib
from collections.abc import Callable
from fractions import Fraction
from pathlib import Path

import numpy as np

from .config import ConfigError, Exposure
from .errors import CameraError

log = logging.getLogger(__name__)

CAMERA_FAULTS = ("timeout", "error", "unplug", "enospc", "hang")


class SimCamera:
    """The simulated camera.

    ``render()`` returns the (H, W) radiance the camera sees now (electrons per second at
    f/1 per photosite: the beam where the pan-tilt unit really points, or darkness with
    the laser off); ``write_raw(path, radiance, exposure_time, f_number, rng)`` exposes
    and writes one DNG. Faults ``KIND@N`` fire on the N-th shot (counted from 1); ``hang``
    answers nothing for ``timeout`` seconds and then fails as ``timeout`` does (a camera
    stuck mid-download: a moment to interrupt the capture at).
    """

    suffix = ".dng"

    def __init__(self, render: Callable[[], np.ndarray], write_raw: Callable, model: str,
                 seed: int = 0, faults=(), timeout: float = 30.0):
        self.render, self.write_raw, self.model, self.seed = render, write_raw, model, seed
        self.timeout = timeout
        self.faults = {}
        for spec in faults:
            m = re.fullmatch(r"\s*(\w+)@(\d+)\s*", spec)
            if not m or m.group(1) not in CAMERA_FAULTS:
                raise ConfigError(f"[camera] fault {spec!r}: expected KIND@N, KIND in {', '.join(CAMERA_FAULTS)}")
            self.faults[int(m.group(2))] = m.group(1)
        self.shots = 0
        self.unplugged = False

    def describe(self) -> dict:
        return {"backend": "sim", "model": self.model, "seed": self.seed}

    def shoot(self, path: Path, exposure: Exposure, key: str) -> dict:
        self.shots += 1
        fault = self.faults.get(self.shots)
        if self.unplugged or fault == "unplug":
            self.unplugged = True
            raise CameraError(f"camera {self.model} disconnected (USB)")
        if fault == "hang":
            time.sleep(self.timeout)
        if fault in ("timeout", "hang"):
            raise CameraError(f"camera {self.model}: no image within the time limit ({key})")
        if fault == "error":
            raise CameraError(f"camera {self.model}: capture failed ({key})")
        if fault == "enospc":
            raise OSError(errno.ENOSPC, f"{path.parent}: no space left on device")
        rng = np.random.default_rng([self.seed, zlib.crc32(key.encode())])
        self.write_raw(path, self.render(), exposure.seconds, exposure.aperture, rng)
        return {"exposure_time": str(exposure.shutter), "f_number": f"{exposure.aperture:g}"}

    def close(self) -> None:
        pass


def make_sim_camera(cfg, plan_steps: np.ndarray, layout: tuple[int, int],
                    pointing: Callable[[], tuple[float, float, bool]]) -> SimCamera:
    """The simulated camera for a [camera] table (backend = "sim").

    ``plan_steps`` (m, 2) are the beam positions of the scene's plan (a refined scan's
    added beams are not among them); ``pointing()`` says where the unit really points
    (pan, tilt in steps) and whether the laser is on. At a plan beam's position (within
    half a step) that beam is rendered (:func:`ilt.sim.render.render_scene`); elsewhere,
    on a line or grid plan, the beam lands between the plan's beams as the angles say
    (:meth:`~ilt.sim.render.RenderedScene.beam_between`, through the plan's affine map
    from layout position to steps), on a list plan at the nearest beam. Scaled by
    ``radiance_scale``, written through :func:`ilt.sim.sensor.write_dng`.
    """
    from ilt.sim.render import render_scene
    from ilt.sim.sensor import write_dng

    m = len(plan_steps)
    scene = render_scene(cfg.scene, beams=m, px_per_beam=cfg.px_per_beam, rows=cfg.rows, spot=cfg.spot)
    if scene.m != m or tuple(scene.layout) != tuple(layout):
        raise ConfigError(f"[camera] scene {cfg.scene!r} renders {scene.m} beams in layout {list(scene.layout)}, "
                          f"but the plan has {m} in {list(layout)}")
    sensor = sim_sensor(scene)
    to_position = _layout_position(np.asarray(plan_steps, dtype=np.float64), layout)
    frames: dict = {}

    def render() -> np.ndarray:
        pan, tilt, laser = pointing()
        out = np.zeros((sensor.height, sensor.width))
        if laser:
            distance = np.hypot(plan_steps[:, 0] - pan, plan_steps[:, 1] - tilt)
            j = int(np.argmin(distance))
            key = j if distance[j] < 0.5 or to_position is None else (float(pan), float(tilt))
            if key not in frames:
                frames.clear()  # one beam at a time: memory does not grow with m
                beam = scene.beam_frame(j) if isinstance(key, int) else \
                    scene.beam_between(to_position(np.array([pan, tilt], dtype=np.float64))).beam_frame(0)
                frames[key] = beam.astype(np.float64) * cfg.radiance_scale
            h, w = scene.frame_shape
            out[:h, :w] = frames[key]
        return out

    def write_raw(path, radiance, exposure_time, f_number, rng):
        write_dng(path, radiance, exposure_time, f_number, sensor, rng)

    return SimCamera(render, write_raw, f"{sensor.make} {sensor.model}", cfg.seed, cfg.faults, cfg.timeout)


def _layout_position(steps: np.ndarray, layout) -> Callable[[np.ndarray], np.ndarray] | None:
    """steps (2,) -> fractional layout position (col, row), from the affine map the plan's
    beams follow (a line or grid of evenly spaced angles); None when they follow none
    (a list plan, or a single beam)."""
    rows, cols = (int(n) for n in layout)
    if len(steps) < 2 or rows * cols != len(steps):
        return None
    index = np.arange(len(steps))
    design = np.column_stack([np.ones(len(steps)), index % cols, index // cols])
    coef, *_ = np.linalg.lstsq(design, steps, rcond=None)
    if np.abs(design @ coef - steps).max() > 1.0:   # not evenly spaced: no map to invert
        return None
    offset, linear = coef[0], coef[1:].T            # steps = offset + linear @ (col, row)
    inverse = np.linalg.pinv(linear, rcond=1e-9)

    def position(at: np.ndarray) -> np.ndarray:
        return inverse @ (at - offset)

    return position


def sim_sensor(scene):
    """The simulated sensor that sees a rendered scene's whole frame (even sides for the Bayer mosaic)."""
    from ilt.sim.sensor import SensorModel

    height, width = (s + s % 2 for s in scene.frame_shape)
    return SensorModel(width=max(width, 22), height=max(height, 22), model="SimSensor")


# ---------------------------------------------------------------------- gphoto2


def parse_setting(text: str) -> Fraction | None:
    """A camera's shutter or aperture choice as a number: '1/8000', '0.0012s', 'f/2.8',
    '30', '2.5"'; None for words like 'bulb' or 'auto'."""
    t = str(text).strip().lower().removeprefix("f/").rstrip('s"').strip()
    try:
        return Fraction(t)
    except (ValueError, ZeroDivisionError):
        return None


def match_choice(choices: list[str], value: float, what: str, tolerance: float = 0.05) -> str:
    """The camera's choice nearest to ``value`` within ``tolerance`` (relative), since
    cameras list nominal values (1/125 for a true 1/128 s)."""
    best, err = None, None
    for c in choices:
        v = parse_setting(c)
        if v is None or v <= 0:
            continue
        e = abs(float(v) / value - 1.0)
        if err is None or e < err:
            best, err = c, e
    if best is None or err > tolerance:
        raise CameraError(f"camera offers no {what} near {value:g} (choices: {', '.join(map(str, choices))})")
    return best


class GPhoto2Camera:
    """A camera through python-gphoto2 (optional extra ``gphoto2``).

    Every setting is read back after it is written (some Canon drivers report success
    when a setting failed); a camera whose model is not ``model`` is refused; pending
    events are drained before and after each capture.
    """

    def __init__(self, model: str = "", port: str = "", iso: str = "", timeout: float = 30.0):
        try:
            import gphoto2 as gp
        except ImportError:
            raise CameraError("camera backend 'gphoto2' needs python-gphoto2: pip install gphoto2") from None
        self.gp, self.timeout, self.suffix = gp, timeout, ""
        self.camera = gp.Camera()
        try:
            if port:
                ports = gp.PortInfoList()
                ports.load()
                self.camera.set_port_info(ports[ports.lookup_path(port)])
            self.camera.init()
            self.model = self._read("cameramodel") or self.camera.get_abilities().model
        except gp.GPhoto2Error as exc:
            raise CameraError(f"camera: cannot connect{' on ' + port if port else ''}: {exc}") from None
        if model and self.model != model:
            self.close()
            raise CameraError(f"camera: connected model is {self.model!r}, the config wants {model!r}; refusing to shoot")
        if iso:
            self.set("iso", iso)
        self.drain_events()

    def describe(self) -> dict:
        return {"backend": "gphoto2", "model": self.model}

    def _widget(self, config, names: tuple[str, ...]):
        for name in names:
            try:
                return config.get_child_by_name(name)
            except self.gp.GPhoto2Error:
                continue
        raise CameraError(f"camera {self.model}: has no setting {' or '.join(names)}")

    def _read(self, name: str) -> str | None:
        try:
            return str(self.camera.get_config().get_child_by_name(name).get_value())
        except self.gp.GPhoto2Error:
            return None

    def choices(self, *names: str) -> list[str]:
        w = self._widget(self.camera.get_config(), names)
        return [w.get_choice(i) for i in range(w.count_choices())]

    def set(self, name: str | tuple[str, ...], value: str) -> str:
        """Write a setting, read it back, and raise CameraError when it did not stick."""
        names = (name,) if isinstance(name, str) else name
        config = self.camera.get_config()
        w = self._widget(config, names)
        try:
            w.set_value(value)
            self.camera.set_config(config)
        except self.gp.GPhoto2Error as exc:
            raise CameraError(f"camera {self.model}: cannot set {w.get_name()} to {value}: {exc}") from None
        got = str(self._widget(self.camera.get_config(), names).get_value())
        return verify_setting(w.get_name(), value, got, self.model)

    def drain_events(self, wait_ms: int = 50) -> list:
        events = []
        deadline = time.monotonic() + self.timeout
        while time.monotonic() < deadline:
            kind, data = self.camera.wait_for_event(wait_ms)
            if kind == self.gp.GP_EVENT_TIMEOUT:
                break
            events.append((kind, data))
        return events

    def shoot(self, path: Path, exposure: Exposure, key: str) -> dict:
        gp = self.gp
        shutter = self.set("shutterspeed", match_choice(self.choices("shutterspeed"), exposure.seconds, "shutter speed"))
        names = ("aperture", "f-number")
        aperture = self.set(names, match_choice(self.choices(*names), exposure.aperture, "aperture"))
        self.drain_events()
        try:
            where = self.camera.capture(gp.GP_CAPTURE_IMAGE)
            file = self.camera.file_get(where.folder, where.name, gp.GP_FILE_TYPE_NORMAL)
            file.save(str(path))
        except gp.GPhoto2Error as exc:
            raise CameraError(f"camera {self.model}: capture failed ({key}): {exc}") from None
        self.suffix = self.suffix or Path(where.name).suffix.lower()
        self.drain_events()
        return {"exposure_time": shutter, "f_number": aperture}

    def close(self) -> None:
        try:
            self.camera.exit()
        except self.gp.GPhoto2Error:
            pass


def verify_setting(name: str, wanted: str, got: str, model: str) -> str:
    """The read-back value when it is what was written, else CameraError."""
    if got != wanted:
        a, b = parse_setting(wanted), parse_setting(got)
        if a is None or b is None or a != b:
            raise CameraError(f"camera {model}: {name} reads back {got!r} after setting {wanted!r} "
                              "(the driver reported success); check the mode dial and lens")
    return got


def check_sim_camera(cfg) -> None:
    """Refuse a simulated camera that cannot render the plan, before the capture directory
    is made: an unknown [camera] scene, or a scene too large for the memory available."""
    if cfg.camera.backend != "sim":
        return
    from ilt.capture.config import ConfigError
    from ilt.capture.plan import planned_beams
    from ilt.sim.memory import render_bytes, require
    from ilt.sim.render import DEFAULT_FINE, FRAME_SCENES, SUPERSAMPLE

    if cfg.camera.scene not in FRAME_SCENES:
        raise ConfigError(f"{cfg.path}: [camera] scene {cfg.camera.scene!r} unknown "
                          f"(known: {', '.join(FRAME_SCENES)})")
    beams = planned_beams(cfg.plan)
    require(render_bytes(cfg.camera.scene, beams, DEFAULT_FINE, cfg.camera.px_per_beam, SUPERSAMPLE),
            f"{cfg.path}: the simulated camera's scene {cfg.camera.scene!r} for {beams} beams")
