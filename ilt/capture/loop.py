"""The capture loop (paper Sec. 4): per beam move, settle, laser on, bracket, laser off,
dark frame; never lose a frame.

Layout (the one ``ilt merge`` reads, docs/hdr.md):

```
capture/
  capture.jsonl        append-only log: one JSON record per event and per frame
  manifest.json        written when every beam is complete ("beams": [...], rig facts)
  beam-00000/
    frame-00.dng ...   the bracket, longest exposure first
    dark.dng           laser off, at the longest exposure taken
    manifest.json      written last: a beam is complete exactly when it exists
  .incomplete/         frames of interrupted beams, set aside on --resume (never deleted)
```

Every frame is written to a temporary name, fsynced and linked to its final name (an
existing frame is never overwritten), then the directory is fsynced and the frame is
logged with its hash. The laser is switched off on every exit path.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ilt.capture.log import CaptureLog, read_log
from ilt.io.beams import BEAM_GLOB, FrameRecord, beam_name, write_beam_manifest
from ilt.io.manifest import LOG_NAME, fingerprint_file, write_manifest

from .adaptive import AdaptiveBracket
from .camera import GPhoto2Camera, make_sim_camera
from .config import ConfigError, Exposure, RigConfig
from .emulator import LaserEmulator, PTUEmulator
from .errors import CameraError, RigError
from .laser import Laser, laser_off, open_laser
from .plan import Plan, check_limits, extend_plan, make_plan, to_steps
from .ptu import PanTilt

log = logging.getLogger(__name__)

ATTIC = ".incomplete"
EMULATOR = "emulator"


# ---------------------------------------------------------------------- the log


def verify_log(directory: str | os.PathLike) -> list[str]:
    """Problems of a capture directory against its log (empty when consistent): every
    logged frame is where the log says (or set aside) with the logged hash, and every
    complete beam's frames are logged."""
    directory = Path(directory)
    records = read_log(directory / LOG_NAME)
    moved = {}
    for r in records:
        if r["event"] == "set_aside":
            moved[r["beam"]] = moved.get(r["beam"], []) + [r["to"]]
    problems = []
    latest: dict[str, dict] = {}
    for r in records:
        if r["event"] != "frame":
            continue
        here = directory / r["file"]
        candidates = [here] + [directory / to / Path(r["file"]).name for to in moved.get(r["beam"], [])]
        if not any(p.exists() and fingerprint_file(p) == r["sha256"] for p in candidates):
            problems.append(f"{r['file']}: logged frame missing or changed")
        latest[r["file"]] = r
    for beam_dir in sorted(directory.glob(BEAM_GLOB)):
        if (beam_dir / "manifest.json").exists():
            for f in beam_dir.iterdir():
                rel = f"{beam_dir.name}/{f.name}"
                if f.name != "manifest.json" and rel not in latest:
                    problems.append(f"{rel}: on disk but not logged")
                elif f.name != "manifest.json" and fingerprint_file(f) != latest[rel]["sha256"]:
                    problems.append(f"{rel}: hash differs from the log")
    return problems


# ---------------------------------------------------------------------- the rig


@dataclass
class Rig:
    ptu: PanTilt
    laser: Laser
    camera: object
    plan: Plan
    steps: np.ndarray
    emulators: list = field(default_factory=list)
    #: the dark frame shot last in this run: (path, beams that used it, its exposure)
    last_dark: tuple | None = None


@contextlib.contextmanager
def open_rig(cfg: RigConfig, pointing: Callable | None = None, added=()):
    """Start (emulators,) the pan-tilt unit, the laser (switched off first) and the camera.

    ``pointing()`` -> (pan, tilt steps, laser on) is the truth the simulated camera
    renders; with ``port = "emulator"`` it is the emulator's state, else (an external
    unit) the position read back and the laser state acknowledged. ``added``: the beams
    of refine passes appended to the config's plan (:func:`~ilt.capture.plan.extend_plan`).
    """
    plan = extend_plan(make_plan(cfg.plan), added)
    emulators: list = []
    ptu = laser = camera = None
    try:
        port = cfg.ptu.port
        if port == EMULATOR:
            emu = PTUEmulator("pty", faults=cfg.ptu.emulator_faults, speed=cfg.ptu.emulator_speed,
                              laser_on=cfg.laser.on, laser_off=cfg.laser.off).start()
            emulators.append(emu)
            port = emu.port
        laser_cfg = cfg.laser
        if laser_cfg.control == "serial" and laser_cfg.port == EMULATOR:
            lemu = LaserEmulator("pty", on=laser_cfg.on, off=laser_cfg.off).start()
            emulators.append(lemu)
            laser_cfg = replace(laser_cfg, port=lemu.port)
        ptu = PanTilt(port, cfg.ptu.baud, cfg.ptu.timeout, cfg.ptu.speed)
        ptu.initialize()
        laser = open_laser(laser_cfg, ptu.line)
        laser.off()
        steps = to_steps(plan, ptu.resolution)
        check_limits(steps, ptu.info["limits"])
        if pointing is None and emulators:
            pointing = _emulated_pointing(emulators)
        if pointing is None:
            def pointing():
                pan, tilt = ptu.position or (np.nan, np.nan)
                return pan, tilt, bool(laser.state)
        camera = open_camera(cfg, steps[:plan.base_m], plan.base_layout or plan.layout, pointing)
        yield Rig(ptu, laser, camera, plan, steps, emulators)
    finally:
        laser_off(laser)
        for thing in (camera, laser, ptu):
            if thing is not None:
                with contextlib.suppress(Exception):
                    thing.close()
        for emu in emulators:
            emu.stop()


def _emulated_pointing(emulators):
    ptu_emu = emulators[0]
    laser_emu = emulators[1] if len(emulators) > 1 else ptu_emu

    def pointing():
        return ptu_emu.position("P"), ptu_emu.position("T"), laser_emu.aux

    return pointing


def open_camera(cfg: RigConfig, steps: np.ndarray, layout, pointing):
    c = cfg.camera
    if c.backend == "sim":
        camera = make_sim_camera(c, steps, layout, pointing)
    else:
        camera = GPhoto2Camera(c.model, c.port, c.iso, c.timeout)
    if c.model and camera.model != c.model:
        camera.close()
        raise CameraError(f"camera: connected model is {camera.model!r}, the config wants {c.model!r}; refusing to shoot")
    return camera


# ---------------------------------------------------------------------- the scan


def prepare_output(directory: Path, resume: bool) -> None:
    """Check (and create) the capture directory before any hardware moves."""
    logfile = directory / LOG_NAME
    if resume:
        if not logfile.exists():
            raise ConfigError(f"{directory}: no {LOG_NAME} to resume (start without --resume)")
    elif logfile.exists():
        raise ConfigError(f"{directory}: holds a capture ({LOG_NAME}); use --resume to continue it")
    elif directory.exists() and any(p for p in directory.iterdir() if not p.name.startswith(".write-test-")):
        # a probe left by a process killed between its write and unlink is not a capture
        raise ConfigError(f"{directory}: exists and is not empty; choose a new output directory")
    try:
        directory.mkdir(parents=True, exist_ok=True)
        probe = directory / f".write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise RigError(f"{directory}: cannot write the capture directory ({exc.strerror or exc})") from None


def scan_fingerprint(cfg: RigConfig, steps: np.ndarray) -> str:
    """What must not change between a capture and its --resume: beams, bracket, dark, camera."""
    d = cfg.as_dict()
    facts = {"steps": steps.tolist(), "bracket": d["bracket"], "dark": d["dark"],
             "camera": {k: v for k, v in d["camera"].items() if k != "faults"}}
    return "sha256:" + hashlib.sha256(json.dumps(facts, sort_keys=True).encode()).hexdigest()


@dataclass
class BeamResult:
    beam: int
    frames: int
    skipped: int
    seconds: float


def capture(cfg: RigConfig, output: str | os.PathLike | None = None, *, resume: bool = False,
            pointing: Callable | None = None, on_beam: Callable[[BeamResult, int, int], None] | None = None,
            added=()) -> dict:
    """Run (or resume) a scan into ``output`` (default: the config's). Returns a summary.

    ``added``: the beams of refine passes appended to the config's plan (list of (k, 2)
    angles in its units, :func:`~ilt.capture.plan.extend_plan`). With ``resume``, a plan
    that extends the capture's (the same beams first, then more; the same bracket, dark
    frame and camera) is shot as the next pass: logged as an ``extend`` event, the
    beams already taken kept. Raises RigError / ConfigError / OSError with a one-line
    reason; the laser is off and every frame already written stays, logged, whatever
    happens.
    """
    directory = Path(output or cfg.output)
    prepare_output(directory, resume)
    started = time.monotonic()
    with open_rig(cfg, pointing, added) as rig:
        fingerprint = scan_fingerprint(cfg, rig.steps)
        event = "resume" if resume else "start"
        if resume:
            event = _resume_event(directory, cfg, rig.steps, fingerprint)
        journal = CaptureLog(directory / LOG_NAME)
        try:
            journal.append(event, fingerprint=fingerprint, config=cfg.as_dict(),
                           ptu=rig.ptu.info, camera=rig.camera.describe(), plan=rig.plan.as_dict())
            results = _scan(cfg, rig, directory, journal, on_beam)
        except BaseException as exc:
            laser_off(rig.laser)
            journal.append("abort", reason=f"{type(exc).__name__}: {exc}", laser_off=rig.laser.state is False)
            raise
        finally:
            journal.close()
        names = [beam_name(j) for j in range(rig.plan.m)]
        taken = sum(r.frames for r in results)
        skipped = sum(r.skipped for r in results)
        per_beam = len(cfg.bracket.exposures)
        # time saved: each skipped exposure would have cost a beam's mean time per frame
        saved = sum(r.skipped * r.seconds / max(r.frames, 1) for r in results)
        summary = {
            "output": str(directory),
            "beams": rig.plan.m,
            "shot": len(results),
            "frames": taken,
            "exposures_skipped": skipped,
            "exposures_full": per_beam * len(results),
            "seconds_saved": round(saved, 3),
            "seconds": round(time.monotonic() - started, 3),
        }
        write_manifest(directory, "capture", cfg.as_dict(), extra={
            "beams": names, "layout": list(rig.plan.layout), "plan": rig.plan.as_dict(),
            "steps": rig.steps.tolist(), "ptu": rig.ptu.info, "camera": rig.camera.describe(),
            "fingerprint": fingerprint,
        })
    return summary


def _resume_event(directory: Path, cfg: RigConfig, steps: np.ndarray, fingerprint: str) -> str:
    """"resume" when the plan is the capture's latest, "extend" when it appends beams to
    it; ConfigError naming the directory otherwise."""
    latest = None
    for r in read_log(directory / LOG_NAME):
        if r["event"] in ("start", "resume", "extend") and "fingerprint" in r:
            latest = r
    if latest is None or latest["fingerprint"] == fingerprint:
        return "resume"
    taken = len((latest.get("plan") or {}).get("targets", ()))
    if 0 < taken < len(steps) and scan_fingerprint(cfg, steps[:taken]) == latest["fingerprint"]:
        log.info("%s: %d beams taken; extending the scan by %d", directory, taken, len(steps) - taken)
        return "extend"
    raise ConfigError(f"{directory}: the config's plan, bracket or camera differ from the capture's; "
                      "resume with the config it was started with")


def _scan(cfg: RigConfig, rig: Rig, directory: Path, journal: CaptureLog, on_beam) -> list[BeamResult]:
    results = []
    todo = [j for j in range(rig.plan.m) if not (directory / beam_name(j) / "manifest.json").exists()]
    if len(todo) < rig.plan.m:
        log.info("%d of %d beams already complete; %d to shoot", rig.plan.m - len(todo), rig.plan.m, len(todo))
    for n, j in enumerate(todo):
        t0 = time.monotonic()
        result = _beam(cfg, rig, directory, journal, j)
        result.seconds = time.monotonic() - t0
        results.append(result)
        journal.append("beam_done", beam=j, frames=result.frames, skipped=result.skipped,
                       seconds=round(result.seconds, 3))
        if on_beam:
            on_beam(result, n + 1, len(todo))
    return results


def _beam(cfg: RigConfig, rig: Rig, directory: Path, journal: CaptureLog, j: int) -> BeamResult:
    beam_dir = directory / beam_name(j)
    if beam_dir.exists():
        attic = directory / ATTIC
        attic.mkdir(exist_ok=True)
        k = 1 + sum(1 for _ in attic.glob(f"{beam_dir.name}-*"))
        to = attic / f"{beam_dir.name}-{k}"
        os.replace(beam_dir, to)
        _fsync_dir(directory)
        journal.append("set_aside", beam=j, to=str(to.relative_to(directory)))
        log.info("beam %d was interrupted: its frames are kept in %s; shooting it again", j, to)
    beam_dir.mkdir()
    pan, tilt = (int(v) for v in rig.steps[j])
    got = rig.ptu.move(pan, tilt)
    journal.append("move", beam=j, requested={"pan": pan, "tilt": tilt}, readback={"pan": got[0], "tilt": got[1]})
    time.sleep(cfg.ptu.settle)
    position = {"pan": pan, "tilt": tilt, "readback_pan": got[0], "readback_tilt": got[1]}
    frames: list[FrameRecord] = []
    rig.laser.on()
    try:
        exposures = _bracket(cfg, rig, beam_dir, journal, j, position, frames)
    finally:
        laser_off(rig.laser)
    if rig.laser.state is not False:
        raise RigError(f"beam {j}: the laser did not acknowledge 'off'; stopping (switch it off by hand)")
    dark = None
    if cfg.dark.frames == "longest":
        longest = max(exposures, key=lambda e: e.relative)
        shared = rig.last_dark
        if shared is not None and shared[1] < cfg.dark.every and shared[2] == longest and shared[0].exists():
            dark = _link_dark(beam_dir, journal, j, shared[0], longest, position, rig.camera.suffix)
            rig.last_dark = (shared[0], shared[1] + 1, longest)
        else:
            dark = _frame(rig, beam_dir, journal, j, "dark", longest, position)
            rig.last_dark = (beam_dir / dark.file, 1, longest)
    full = cfg.bracket.exposures
    write_beam_manifest(beam_dir, frames, dark, extra={
        **position, "skipped": [e.as_dict() for e in full if e not in exposures]})
    _fsync_dir(beam_dir)
    return BeamResult(j, len(frames) + (dark is not None), len(full) - len(exposures), 0.0)


def _bracket(cfg, rig, beam_dir, journal, j, position, frames) -> list[Exposure]:
    b = cfg.bracket
    if not b.adaptive:
        for k, e in enumerate(b.exposures):
            frames.append(_frame(rig, beam_dir, journal, j, f"frame-{k:02d}", e, position))
        return list(b.exposures)
    from ilt.io.raw import read_green

    chooser = AdaptiveBracket(b.exposures, b.low, b.high, b.stride)
    e = chooser.first()
    while e is not None:
        record = _frame(rig, beam_dir, journal, j, f"frame-{len(frames):02d}", e, position)
        frames.append(record)
        green, info = read_green(beam_dir / record.file, record.exposure_time, record.f_number)
        chooser.add(e, green, info.saturation, info.saturated)
        e = chooser.next()
    skipped = chooser.skipped()
    if skipped:
        journal.append("adaptive", beam=j, taken=[x.as_dict() for x in chooser.taken],
                       skipped=[x.as_dict() for x in skipped])
    return chooser.taken


def _frame(rig: Rig, beam_dir: Path, journal: CaptureLog, j: int, stem: str, exposure: Exposure, position: dict):
    """Shoot one frame into ``beam_dir/stem.<suffix>``: temporary name, fsync, link, log."""
    from ilt.io.exposure import exif_facts, read_exif

    camera = rig.camera
    tmp = beam_dir / f".{stem}.tmp-{os.getpid()}{camera.suffix or '.raw'}"
    key = f"{beam_dir.name}/{stem}/{exposure.label()}/{'laser' if rig.laser.state else 'dark'}"
    try:
        readback = camera.shoot(tmp, exposure, key)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        final = beam_dir / f"{stem}{camera.suffix}"
        _publish(tmp, final)
    except OSError as exc:
        if isinstance(exc, RigError):
            raise
        raise RigError(f"{beam_dir / stem}: cannot write the frame ({exc.strerror or exc})") from None
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
    _fsync_dir(beam_dir)
    t, n = exif_facts(read_exif(final))
    journal.append(
        "frame", beam=j, file=f"{beam_dir.name}/{final.name}", kind="dark" if stem == "dark" else "bracket",
        requested={"pan": position["pan"], "tilt": position["tilt"], **exposure.as_dict()},
        readback={"pan": position["readback_pan"], "tilt": position["readback_tilt"], **readback},
        exif={"exposure_time": None if t is None else str(t), "f_number": None if n is None else str(n)},
        sha256=fingerprint_file(final), laser=rig.laser.state)
    return FrameRecord(final.name, str(exposure.shutter), f"{exposure.aperture:g}")


def _link_dark(beam_dir: Path, journal: CaptureLog, j: int, source: Path, exposure: Exposure, position: dict,
               suffix: str) -> FrameRecord:
    """The beam's dark frame as a hard link to the one shot ``[dark] every`` beams ago (a
    copy where the file system has no links), logged as a frame with ``shared_from``."""
    final = beam_dir / f"dark{suffix}"
    try:
        os.link(source, final)
    except OSError:
        shutil.copy2(source, final)
    _fsync_dir(beam_dir)
    journal.append(
        "frame", beam=j, file=f"{beam_dir.name}/{final.name}", kind="dark",
        requested={"pan": position["pan"], "tilt": position["tilt"], **exposure.as_dict()},
        shared_from=f"{source.parent.name}/{source.name}", sha256=fingerprint_file(final), laser=False)
    return FrameRecord(final.name, str(exposure.shutter), f"{exposure.aperture:g}")


def _publish(tmp: Path, final: Path) -> None:
    """Give ``tmp`` its final name, refusing to replace an existing file."""
    try:
        os.link(tmp, final)
    except FileExistsError:
        raise RigError(f"{final}: exists; a frame is never overwritten") from None
    except OSError:  # file systems without hard links
        if final.exists():
            raise RigError(f"{final}: exists; a frame is never overwritten") from None
        os.rename(tmp, final)


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
