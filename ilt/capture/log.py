"""The capture log, ``capture.jsonl`` (docs/capture.md): its records, how they are
appended and how they are read back.

``ilt capture`` (:mod:`ilt.capture.loop`) writes it; ``ilt merge`` takes the frames'
fingerprints from it and ``ilt report`` its statistics, so the format lives here,
below all three. The file's name is :data:`ilt.io.manifest.LOG_NAME`.
"""

from __future__ import annotations

import json
import logging
import os
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


class CaptureLogError(ValueError):
    """A capture log damaged before its last line (a last line cut short is a crash, not damage)."""


class CaptureLog:
    """Append-only JSONL: each record is one ``write`` of one line, then fsync."""

    def __init__(self, path: Path):
        self.path = path
        self._fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)

    def append(self, event: str, **fields) -> dict:
        record = {"event": event, "time": datetime.now(timezone.utc).isoformat(timespec="milliseconds"), **fields}
        os.write(self._fd, (json.dumps(record, default=_plain) + "\n").encode())
        os.fsync(self._fd)
        return record

    def close(self) -> None:
        os.close(self._fd)


def read_log(path: str | os.PathLike) -> list[dict]:
    """The log's records; a last line cut short by a crash is dropped with a warning."""
    records = []
    lines = Path(path).read_text().splitlines()
    for k, line in enumerate(lines):
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            if k == len(lines) - 1:
                log.info("%s: last line cut short (crash while writing it); ignored", path)
            else:
                raise CaptureLogError(f"{path}:{k + 1}: not a JSON record; the log is damaged") from None
    return records


def _plain(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot log {type(obj).__name__}")
