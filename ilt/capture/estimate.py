"""The rig's time, known before the scan (``ilt capture --estimate CONFIG``).

A scan's time is the sum, over its beams, of a move of the pan-tilt unit (travel at its
speed plus the command round trips), the settle time, the laser switched on and off,
the bracket's exposures with each frame's download, and the dark frame. Nothing is
opened or moved: the unit's speed and resolution are the config's ``[ptu] speed`` when
given, else a PTU-D46's (the emulator's for ``port = "emulator"``), and the camera's
per-frame overhead is a default for its backend, unless earlier capture logs
(``capture.jsonl``) measured them: then the median over their frames of the time from one
frame's record to the next in the same beam, less the later frame's exposure, is the
per-frame overhead; the median time from a beam's ``move`` record (written on arrival)
to its first frame, less that frame's exposure and overhead, is the settle with the laser
switched on; and the median time from a beam's end to the next arrival is what a move
costs besides its travel (laser off, the beam's manifest, the commands).

Adaptive bracketing (``[bracket] adaptive``) skips exposures a beam does not need: the
estimate counts the full bracket, an upper bound, and says so.
"""

from __future__ import annotations

import math
import os
import statistics
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np

from .config import RigConfig
from .log import CaptureLogError, read_log
from .plan import make_plan, to_steps

#: a PTU-D46's arc-seconds per position (pan, tilt), as the emulator reports them
PTU_RESOLUTION = (92.5714, 46.2857)
#: positions per second of a PTU-D46 at its default speed setting
PTU_SPEED = 1000.0
#: per frame after its exposure: trigger, write and download (seconds), by camera backend.
#: A tethered DSLR over USB (gphoto2) takes about a second a RAW frame
FRAME_OVERHEAD = {"gphoto2": 1.0, "sim": 0.01}
#: per move: the command round trips (halt, two targets, await, position read back)
MOVE_OVERHEAD = 0.1
#: per laser switch (a command and its acknowledgement)
LASER_SWITCH = 0.05


@dataclass
class Estimate:
    """Seconds per part of a scan and where each figure came from."""

    beams: int
    frames_per_beam: int
    parts: dict[str, float]
    sources: dict[str, str]
    notes: list[str] = field(default_factory=list)

    @property
    def seconds(self) -> float:
        return float(sum(self.parts.values()))

    def as_dict(self) -> dict:
        return {"beams": self.beams, "frames_per_beam": self.frames_per_beam, "seconds": self.seconds,
                "hours": self.seconds / 3600, "parts": self.parts, "sources": self.sources, "notes": self.notes}

    def table(self) -> str:
        rows = [f"{'part':<10} {'seconds':>10}  source"]
        for name, value in self.parts.items():
            rows.append(f"{name:<10} {value:>10.1f}  {self.sources.get(name, '')}")
        rows.append(f"{'total':<10} {self.seconds:>10.1f}  = {self.seconds / 3600:.2f} h for {self.beams} beams, "
                    f"{self.frames_per_beam} frames a beam")
        return "\n".join(rows + [f"note: {n}" for n in self.notes])


@dataclass
class Measured:
    """Timings measured in capture logs: per-frame overhead, arrival to first exposure
    (settle, laser on), a beam's end to the next arrival (laser off, manifest, move)."""

    frame_overhead: float | None = None
    settle: float | None = None
    between: float | None = None
    frames: int = 0
    beams: int = 0
    logs: list[str] = field(default_factory=list)


def measure_logs(paths: list[str | os.PathLike], speed: float = PTU_SPEED, real_exposures: bool = True) -> Measured:
    """Medians of the timings in ``capture.jsonl`` files (see the module docstring).
    A log that cannot be read is skipped; one with no frames adds nothing. ``speed``
    (positions/s) takes each logged move's travel out of the time between beams;
    ``real_exposures``: the camera waits for its exposures (the simulated one does not)."""
    overheads, settles, betweens, used = [], [], [], []
    for path in paths:
        try:
            records = read_log(path)
        except (OSError, CaptureLogError):
            continue
        used.append(str(path))
        last: dict[int, tuple[datetime, str]] = {}
        first_frame: dict[int, bool] = {}
        frame_over: list[float] = []
        move_times: dict[int, datetime] = {}
        firsts: list[tuple[float, float]] = []
        previous_end, previous_at = None, (0, 0)
        for r in records:
            when = _time(r)
            if when is None:
                continue
            beam = r.get("beam")
            if r.get("event") == "move":
                at = r.get("requested") or {}
                at = (int(at.get("pan", 0)), int(at.get("tilt", 0)))
                if previous_end is not None:
                    travel = max(abs(at[0] - previous_at[0]), abs(at[1] - previous_at[1])) / speed
                    betweens.append((when - previous_end).total_seconds() - travel)
                previous_at = at
                move_times[beam] = when
                last.pop(beam, None)
                first_frame[beam] = True
            elif r.get("event") == "beam_done":
                previous_end = when
            elif r.get("event") in ("start", "resume", "set_aside"):
                previous_end = None
            elif r.get("event") == "frame" and "shared_from" not in r:  # a linked dark took no time
                shutter = float((r.get("requested") or {}).get("exposure_time") or 0.0) if real_exposures else 0.0
                if beam in last:
                    frame_over.append((when - last[beam][0]).total_seconds() - shutter)
                elif first_frame.get(beam) and beam in move_times:
                    firsts.append(((when - move_times[beam]).total_seconds(), shutter))
                first_frame[beam] = False
                last[beam] = (when, r.get("kind", ""))
        overheads += frame_over
        if frame_over:
            per_frame = statistics.median(frame_over)
            settles += [gap - shutter - per_frame for gap, shutter in firsts]
    out = Measured(logs=used, frames=len(overheads), beams=len(settles))
    if overheads:
        out.frame_overhead = max(0.0, statistics.median(overheads))
    if settles:
        out.settle = max(0.0, statistics.median(settles))
    if betweens:
        out.between = max(0.0, statistics.median(betweens))
    return out


def estimate(cfg: RigConfig, logs: list[str | os.PathLike] = ()) -> Estimate:
    """The scan's time by part (seconds), from the config and any earlier capture logs."""
    plan = make_plan(cfg.plan)
    emulated = cfg.ptu.port == "emulator"
    speed = float(cfg.ptu.speed or (cfg.ptu.emulator_speed if emulated else PTU_SPEED))
    speed_source = ("[ptu] speed" if cfg.ptu.speed else
                    "[ptu] emulator_speed" if emulated else f"a PTU-D46's default speed ({PTU_SPEED:g} positions/s)")
    steps = to_steps(plan, PTU_RESOLUTION).astype(np.float64)
    path = np.vstack([[0.0, 0.0], steps])  # from the unit's home position
    travel = float(np.sum(np.max(np.abs(np.diff(path, axis=0)), axis=1)) / speed)
    exposures = list(cfg.bracket.exposures)
    dark = cfg.dark.frames == "longest"
    frames = len(exposures) + dark
    m = plan.m
    real = cfg.camera.backend != "sim"
    measured = measure_logs(list(logs), speed, real)
    backend = cfg.camera.backend
    per_frame = FRAME_OVERHEAD.get(backend, 1.0)
    frame_source = f"default for the {backend!r} camera backend"
    if measured.frame_overhead is not None:
        per_frame = measured.frame_overhead
        frame_source = f"median of {measured.frames} frames in {len(measured.logs)} capture log(s)"
    # the simulated camera writes its frames at once: its exposures take no time
    shutter = sum(e.seconds for e in exposures) if real else 0.0
    dark_shutter = max(e.seconds for e in exposures) if (dark and real) else 0.0
    parts = {
        "moves": travel + MOVE_OVERHEAD * m,
        "settle": cfg.ptu.settle * m,
        "laser": 2 * LASER_SWITCH * m if cfg.laser.control != "none" else 0.0,
        "exposures": shutter * m,
        "downloads": per_frame * len(exposures) * m,
        "dark": (dark_shutter + per_frame) * math.ceil(m / cfg.dark.every) if dark else 0.0,
    }
    sources = {
        "moves": f"travel at {speed:g} positions/s ({speed_source}) + {MOVE_OVERHEAD:g} s of commands a move",
        "settle": f"[ptu] settle = {cfg.ptu.settle:g} s a beam",
        "laser": f"{LASER_SWITCH:g} s a switch, two a beam",
        "exposures": (f"the bracket's {len(exposures)} exposures, {shutter:.4g} s a beam" if real else
                      "the simulated camera does not wait for its exposures"),
        "downloads": f"{per_frame:.3g} s a frame: {frame_source}",
        "dark": ("[dark] frames = none" if not dark else "one frame at the longest exposure a beam"
                 if cfg.dark.every == 1 else f"one frame at the longest exposure every {cfg.dark.every} beams"),
    }
    notes = []
    if measured.settle is not None:
        # from a move's record (written when the unit has arrived) to the first frame's:
        # the settle and the laser switched on
        parts["settle"] = measured.settle * m
        sources["settle"] = (f"median {measured.settle:.3g} s from arrival to the first frame's exposure "
                             f"in {measured.beams} logged beams (laser on included)")
        parts["laser"] = LASER_SWITCH * m if cfg.laser.control != "none" else 0.0
        sources["laser"] = f"{LASER_SWITCH:g} s a beam to switch it off"
    if measured.between is not None:
        # from a beam's end to the next move's arrival, less that move's travel: laser
        # off, the beam's manifest, the commands
        parts["moves"] = travel + measured.between * m
        parts["laser"] = 0.0 if measured.settle is None else parts["laser"] - LASER_SWITCH * m
        sources["moves"] = (f"travel at {speed:g} positions/s ({speed_source}) + median {measured.between:.3g} s "
                            "between a beam's end and the next arrival in the logs, less its travel (laser "
                            "off, manifest, commands)")
    if cfg.bracket.adaptive:
        notes.append("adaptive bracketing skips exposures a beam does not need: this is the full bracket, "
                     "an upper bound")
    if not emulated and not cfg.ptu.speed:
        notes.append("the unit's own speed and resolution are read when it connects; give [ptu] speed "
                     "for a closer figure")
    return Estimate(m, frames, parts, sources, notes)


def default_logs(cfg: RigConfig, workspace_root: Path, output: str | None) -> list[Path]:
    """The capture log of the config's output directory, when an earlier scan left one."""
    directory = Path(output) if output else workspace_root / cfg.output
    log = directory / "capture.jsonl"
    return [log] if log.is_file() else []


def _time(record: dict) -> datetime | None:
    try:
        return datetime.fromisoformat(record["time"])
    except (KeyError, TypeError, ValueError):
        return None
