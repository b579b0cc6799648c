"""A workspace: one directory holding every stage directory of a scan (docs/workspace.md).

```
WORKSPACE/
  rig.toml      the config of the last `ilt run` (what `ilt status` compares against)
  capture/      ilt capture      raw brackets, capture.jsonl, manifest.json
  hdr/          ilt merge        one linear EXR per beam
  spots/        ilt centroids    spots.csv, overlay.png
  isf/          ilt build-isf    T.npy, samples.csv
  refine/       ilt refine       refine.csv: where the next beams should land
  passes/       ilt run          [refine] passes: pass-P/ (refine's output), landing.csv
  photos/       ilt run          photos merged from their brackets (simulated rig)
  decompose/    ilt decompose    one directory of bounce images per photo
  report/       ilt report       index.html and its PNGs
```

Stage commands read and write these sub-directories when no path is given.
"""

from __future__ import annotations

import os
from pathlib import Path

from ilt.io.manifest import MANIFEST

#: stage name -> its sub-directory, in pipeline order
STAGE_DIRS = {
    "capture": "capture",
    "merge": "hdr",
    "centroids": "spots",
    "build-isf": "isf",
    "refine": "refine",
    "photos": "photos",
    "decompose": "decompose",
}
CONFIG = "rig.toml"
REPORT = "report"
#: the refine passes of `ilt run` (ilt.workspace.passes) and each new beam's landing
PASSES = "passes"
LANDING_CSV = "landing.csv"


class Workspace:
    """Paths of a workspace rooted at ``root`` (nothing is created until a stage writes)."""

    def __init__(self, root: str | os.PathLike = "."):
        self.root = Path(root)

    def __repr__(self) -> str:
        return f"Workspace({str(self.root)!r})"

    def stage_dir(self, stage: str) -> Path:
        return self.root / STAGE_DIRS[stage]

    @property
    def config(self) -> Path:
        return self.root / CONFIG

    @property
    def report(self) -> Path:
        return self.root / REPORT

    @property
    def passes(self) -> Path:
        return self.root / PASSES

    def resolve(self, given: str | os.PathLike | None, stage: str) -> str:
        """``given`` when a path was given, else the stage's directory in this workspace."""
        return str(given) if given is not None else str(self.stage_dir(stage))


def workspace_marks(path: str | os.PathLike) -> list[str]:
    """What makes ``path`` a workspace (its rig.toml, its stage directories), or [] when
    it is not one: a stage directory (with its own manifest.json) is never a workspace."""
    path = Path(path)
    if (path / MANIFEST).exists():
        return []
    marks = [CONFIG] if (path / CONFIG).is_file() else []
    return marks + [f"{sub}/" for sub in STAGE_DIRS.values() if (path / sub / MANIFEST).exists()]
