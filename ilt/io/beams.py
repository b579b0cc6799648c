"""A beam directory of a capture: its name and its ``manifest.json`` (docs/hdr.md).

```
beam-00000/
  manifest.json          {"beam": 0, "frames": [...], "dark": {...} | null}
  frame-00.dng ...
```

``ilt capture``, the simulated sensor and ``ilt run``'s photos write beam directories;
``ilt merge`` (:mod:`ilt.hdr.bracket`) reads them. The format lives here, below them all.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path

from ilt.io.manifest import MANIFEST, write_json

#: the names :func:`beam_name` gives
BEAM_GLOB = "beam-[0-9]*"


def beam_name(j: int) -> str:
    """The directory name of beam ``j`` (0-based)."""
    return f"beam-{j:05d}"


@dataclass(frozen=True)
class FrameRecord:
    """One frame of a beam: file name in the beam directory and its nominal exposure facts
    (text as written, e.g. "1/125" s and "1.2"; None when the manifest leaves it to EXIF)."""

    file: str
    exposure_time: str | None = None
    f_number: str | None = None


def write_beam_manifest(beam_dir: str | os.PathLike, frames: list[FrameRecord],
                        dark: FrameRecord | None = None, extra: dict | None = None) -> Path:
    """Write ``beam_dir/manifest.json`` for the frames (atomically)."""
    beam_dir = Path(beam_dir)
    data = {
        "beam": _beam_index(beam_dir),
        "frames": [asdict(f) for f in frames],
        "dark": asdict(dark) if dark else None,
    }
    data.update(extra or {})
    return write_json(beam_dir / MANIFEST, data)


def _beam_index(beam_dir: Path) -> int | None:
    tail = beam_dir.name.rpartition("-")[2]
    return int(tail) if tail.isdigit() else None
