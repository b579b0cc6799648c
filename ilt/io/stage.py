"""Stage skipping (DESIGN.md sec. 3): is a stage directory up to date, like ``make``?

A stage directory is *complete* when its ``manifest.json`` exists: every stage writes
it last (inside a staged temporary directory that is renamed into place, or, for a
capture, after the last beam). When a stage is run by :func:`run_stage` (``ilt run``),
a run record ``.stage.json`` is written beside the manifest: the parameters it ran
with, the fingerprints of its inputs and the fingerprint of the manifest it produced.

:func:`stage_state` compares that record with what a run would use now and says
``done``, ``stale: <what changed>`` or ``missing``. Fingerprints are cheap: an input
stage directory is fingerprinted by its manifest's stage, parameters and output
fingerprints (already recorded when it was written), never by re-reading its frames;
only plain files (a photo, a response) are hashed.

The record also keeps each output file's size and modification time, so that
:func:`changed_outputs` can tell cheaply whether a stage's files still are the ones
its manifest fingerprints: only a file whose size or time moved is re-hashed (all of
them with ``full``, as ``ilt status --verify`` does).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ilt.io.manifest import MANIFEST, RECORD, StageError, fingerprint_file, read_manifest, write_json

log = logging.getLogger(__name__)


DONE, STALE, MISSING = "done", "stale", "missing"


@dataclass(frozen=True)
class StageState:
    """What :func:`stage_state` found: ``state`` is done, stale or missing; ``reason`` says why."""

    stage: str
    directory: str
    state: str
    reason: str = ""

    @property
    def done(self) -> bool:
        return self.state == DONE

    def __str__(self) -> str:
        return f"{self.state}: {self.reason}" if self.reason else self.state

    def as_dict(self) -> dict:
        return {"stage": self.stage, "directory": self.directory, "state": self.state, "reason": self.reason}


def _digest(data) -> str:
    return "sha256:" + hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()


def fingerprint_stage(directory: str | os.PathLike) -> str:
    """Fingerprint of a complete stage directory from its manifest alone (no frame is read)."""
    m = read_manifest(directory)
    return _digest({"stage": m.get("stage"), "parameters": m.get("parameters"), "outputs": m.get("outputs")})


def fingerprint_input(path: str | os.PathLike) -> str:
    """A stage directory by its manifest (:func:`fingerprint_stage`), a file by its bytes."""
    path = Path(path)
    if path.is_dir():
        return fingerprint_stage(path)
    if not path.exists():
        raise StageError(f"{path}: missing input")
    return fingerprint_file(path)


def plain(data):
    """Parameters as JSON would give them back (tuples as lists), for comparison."""
    return json.loads(json.dumps(data, sort_keys=True, default=str))


def read_record(directory: str | os.PathLike) -> dict | None:
    path = Path(directory) / RECORD
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except json.JSONDecodeError:
        return None  # a record cut short: treated as absent, so the stage is re-run


def _stats(directory: Path, names) -> dict[str, list[int]]:
    out = {}
    for name in names:
        try:
            st = (directory / name).stat()
        except FileNotFoundError:
            continue
        out[name] = [st.st_size, st.st_mtime_ns]
    return out


def write_record(directory: str | os.PathLike, stage: str, parameters: dict, inputs: dict[str, str]) -> Path:
    """Record that ``directory`` (complete) was made from ``parameters`` and ``inputs``,
    with the size and modification time of each output file its manifest lists."""
    directory = Path(directory)
    return write_json(directory / RECORD, {
        "stage": stage,
        "parameters": plain(parameters),
        "inputs": inputs,
        "manifest": fingerprint_stage(directory),
        "files": _stats(directory, read_manifest(directory).get("outputs", {})),
    })


def changed_outputs(directory: str | os.PathLike, full: bool = False) -> list[str]:
    """The output files of a complete stage directory that are missing or whose bytes
    differ from its manifest's fingerprints (relative names, sorted).

    Without ``full``, a file whose size and modification time are the ones the run
    record kept is taken as unchanged (a stat, no read); the others are hashed.
    """
    directory = Path(directory)
    outputs = read_manifest(directory).get("outputs", {})
    known = {} if full else (read_record(directory) or {}).get("files", {})
    now = _stats(directory, outputs)
    changed = []
    for name, fingerprint in sorted(outputs.items()):
        if name not in now:
            changed.append(name)
        elif known.get(name) != now[name] and fingerprint_file(directory / name) != fingerprint:
            changed.append(name)
    return changed


def input_evidence(path: str | os.PathLike) -> str:
    """How a stage's own manifest names an input it read: a stage directory by the hash
    of its manifest.json file (ilt merge, centroids and build-isf record it), a file by
    its bytes."""
    path = Path(path)
    return fingerprint_file(path / MANIFEST if path.is_dir() else path)


def _changes(kind: str, old: dict, new: dict) -> list[str]:
    out = []
    for key in sorted(set(old) | set(new)):
        if key not in old:
            out.append(f"{kind} {key} new")
        elif key not in new:
            out.append(f"{kind} {key} removed")
        elif old[key] != new[key]:
            if kind == "parameter" and not isinstance(new[key], (dict, list)):
                out.append(f"parameter {key} changed ({old[key]!r} -> {new[key]!r})")
            else:
                out.append(f"{kind} {key} changed")
    return out


def stage_state(directory: str | os.PathLike, stage: str, parameters: dict,
                inputs: dict[str, str] | None = None, evidence: dict[str, str] | None = None) -> StageState:
    """Is ``directory`` an up-to-date result of ``stage`` run with ``parameters`` on ``inputs``?

    ``inputs`` maps a name to a fingerprint (:func:`fingerprint_input`). A directory
    without a run record (written by a stage command on its own, e.g. ``ilt merge``
    by hand) is done when its manifest's parameters match and its manifest's inputs
    name every input: ``evidence`` maps each input name to :func:`input_evidence`.
    Parameters the manifest does not record, or records resolved where ``parameters``
    leaves them to the stage (None, e.g. build-isf's default cell radius), are not
    compared there.
    """
    directory = Path(directory)
    inputs = inputs or {}

    def state(s, reason=""):
        return StageState(stage, str(directory), s, reason)

    if not (directory / MANIFEST).exists():
        return state(MISSING, "incomplete (no manifest.json)" if directory.exists() else "")
    try:
        manifest = read_manifest(directory)
    except StageError as exc:
        return state(STALE, str(exc))
    if manifest.get("stage") != stage:
        return state(STALE, f"{MANIFEST} is from stage {manifest.get('stage')!r}")
    wanted = plain(parameters)
    record = read_record(directory)
    if record is None:
        recorded = plain(manifest.get("parameters", {}))
        common = [k for k in wanted if k in recorded and wanted[k] is not None]
        changes = _changes("parameter", {k: recorded[k] for k in common}, {k: wanted[k] for k in common})
        if changes:
            return state(STALE, "; ".join(changes))
        named = set(manifest.get("inputs", {}).values())
        unknown = [n for n in inputs if (evidence or {}).get(n) not in named]
        if unknown:
            return state(STALE, f"no run record (made outside 'ilt run'): input {', '.join(unknown)} "
                                "not the one it was made from")
        return state(DONE)
    if record.get("manifest") != fingerprint_stage(directory):
        return state(STALE, "outputs changed since it was run")
    changes = _changes("input", record.get("inputs", {}), inputs) + \
        _changes("parameter", record.get("parameters", {}), wanted)
    if changes:
        return state(STALE, "; ".join(changes))
    return state(DONE)


def run_stage(directory: str | os.PathLike, stage: str, parameters: dict, inputs: dict[str, str],
              make: Callable[[], object], *, force: bool = False,
              evidence: dict[str, str] | None = None, state: StageState | None = None) -> tuple[bool, StageState]:
    """Run ``make()`` (which writes ``directory`` completely, replacing it) unless the
    stage is up to date; then record the run. Returns (ran, the state before).

    Logs ``<stage>: up to date`` when skipped, else what made it run. A stage a
    command made by hand that is up to date (see :func:`stage_state`) gets its run
    record here, as if ``ilt run`` had made it. ``state``: the stage's
    :func:`stage_state` for these ``inputs`` when the caller found it already.
    """
    before = state or stage_state(directory, stage, parameters, inputs, evidence)
    if before.done and not force:
        log.info("%s: up to date (%s)", stage, directory)
        if read_record(directory) is None:
            write_record(directory, stage, parameters, inputs)
        return False, before
    why = "--force" if before.done else str(before)
    log.info("%s: running (%s)", stage, why)
    make()
    write_record(directory, stage, parameters, inputs)
    return True, before
