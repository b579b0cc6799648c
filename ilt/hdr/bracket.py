"""Reading the capture directory layout: one directory per beam, each a bracket of RAW frames.

```
capture/
  manifest.json            optional; "beams": ["beam-00000", ...] (else beam-* in order)
  beam-00000/
    manifest.json          {"beam": 0, "frames": [...], "dark": {...} | null}
    frame-00.dng ...
```

Each frame record is ``{"file": "frame-00.dng", "exposure_time": "1/8000", "f_number": "16"}``:
times in seconds and f-numbers as JSON numbers or exact rational text ("1/125", "1.2").
Either fact may be missing (null); it is then read from the frame's EXIF. See docs/hdr.md.
The beam directories' names and manifests are written by :mod:`ilt.io.beams`.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

from ilt.capture.log import CaptureLogError, read_log
from ilt.io.beams import BEAM_GLOB, FrameRecord, beam_name
from ilt.io.manifest import LOG_NAME, MANIFEST

log = logging.getLogger(__name__)


class CaptureError(ValueError):
    """A capture directory or beam manifest that does not follow the layout."""


@dataclass(frozen=True)
class Bracket:
    """A beam's frames as absolute paths with their manifest facts, and its dark frame."""

    beam_dir: Path
    frames: list[FrameRecord]
    dark: FrameRecord | None

    def path(self, record: FrameRecord) -> Path:
        return self.beam_dir / record.file


def read_beam(beam_dir: str | os.PathLike) -> Bracket:
    """Read a beam directory's manifest. Raises CaptureError naming the file at fault."""
    beam_dir = Path(beam_dir)
    path = beam_dir / MANIFEST
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise CaptureError(f"{path}: missing (a beam directory needs its manifest.json)") from None
    except json.JSONDecodeError as exc:
        raise CaptureError(f"{path}: not valid JSON ({exc})") from None
    try:
        frames = [_record(f) for f in data["frames"]]
        dark = _record(data["dark"]) if data.get("dark") else None
    except (KeyError, TypeError) as exc:
        raise CaptureError(f"{path}: frame records need at least a 'file' ({exc!r})") from None
    if not frames:
        raise CaptureError(f"{path}: lists no frames")
    names = [f.file for f in frames] + ([dark.file] if dark else [])
    for name in names:
        if Path(name).name != name:
            raise CaptureError(f"{path}: frame file {name!r} must be a plain name inside the beam directory")
    if len(set(names)) != len(names):
        raise CaptureError(f"{path}: a frame file is listed twice")
    return Bracket(beam_dir, frames, dark)


def list_beams(capture_dir: str | os.PathLike) -> list[Path]:
    """Beam directories of a capture, in the order of its manifest (else by name)."""
    capture_dir = Path(capture_dir)
    if not capture_dir.is_dir():
        raise CaptureError(f"{capture_dir}: not a directory")
    top = capture_dir / MANIFEST
    beams = None
    if top.exists():
        try:
            beams = json.loads(top.read_text()).get("beams")
        except (json.JSONDecodeError, AttributeError) as exc:
            raise CaptureError(f"{top}: not a valid manifest ({exc})") from None
    if beams is None:
        dirs = sorted(p for p in capture_dir.glob(BEAM_GLOB) if p.is_dir())
    else:
        for b in beams:
            # a listed beam is read from inside the capture, never from elsewhere
            if not isinstance(b, str) or Path(b).name != b or b in ("", ".", ".."):
                raise CaptureError(f"{top}: beams entry {b!r} must be the name of a beam directory inside "
                                   f"{capture_dir} (like 'beam-00000'); fix the manifest")
        dirs = [capture_dir / b for b in beams]
    if not dirs:
        raise CaptureError(f"{capture_dir}: no beam-NNNNN directories (see docs/hdr.md)")
    return dirs


def logged_fingerprints(capture_dir: str | os.PathLike) -> dict[str, dict[str, str]]:
    """The fingerprints ``ilt capture`` logged: beam directory name -> {frame file name:
    "sha256:<hex>"}, from ``capture.jsonl`` (docs/capture.md); empty without a log.

    A file logged twice keeps its latest record; a beam that ``--resume`` set aside
    forgets the records before it (those files moved to ``.incomplete/``). A damaged log
    gives nothing (with a warning): the frames are then hashed as they are read.
    """
    path = Path(capture_dir) / LOG_NAME
    if not path.is_file():
        return {}
    try:
        records = read_log(path)
    except CaptureLogError as exc:
        log.info("%s; every frame will be hashed", exc)
        return {}
    beams: dict[str, dict[str, str]] = {}
    for r in records:
        if r.get("event") == "set_aside":
            beams.pop(beam_name(r["beam"]), None)
        elif r.get("event") == "frame" and isinstance(r.get("sha256"), str):
            beam, _, name = str(r.get("file", "")).partition("/")
            if name and "/" not in name:
                beams.setdefault(beam, {})[name] = r["sha256"]
    return beams


def _record(item: dict) -> FrameRecord:
    def text(v):
        return None if v is None else str(v)

    return FrameRecord(str(item["file"]), text(item.get("exposure_time")), text(item.get("f_number")))
