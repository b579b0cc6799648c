"""Stage manifests, content fingerprints and atomic directory writes (DESIGN.md sec. 3).

A stage never writes into its final directory: it fills a hidden sibling temporary
directory and renames it into place, so an interrupted run leaves either the old
directory or the complete new one, never a half stage that looks whole.

It replaces only what it may lose: an empty directory or an earlier output of the same
stage holding nothing but its own files (issue 14, "nothing a user made is ever lost").
What it writes gets the modes an ordinary open() and mkdir() would give under the
umask, and temporaries carry their writer's pid, so the next run can remove those of
a process that is gone.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import secrets
import shutil
import socket
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ilt import __version__

MANIFEST = "manifest.json"
#: the run record ``ilt run`` keeps beside a stage's manifest (:mod:`ilt.stage`)
RECORD = ".stage.json"
#: a capture's journal (:mod:`ilt.capture_log`): the raw data it names is never replaced
LOG_NAME = "capture.jsonl"


class StageError(ValueError):
    """A stage directory that cannot be written or read as asked."""


def fingerprint_file(path: str | os.PathLike, chunk: int = 1 << 22) -> str:
    """``sha256:<hex>`` of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return "sha256:" + h.hexdigest()


def fingerprint_array(a: np.ndarray) -> str:
    """``sha256:<hex>`` of an array's dtype, shape and bytes (C order)."""
    h = hashlib.sha256()
    h.update(f"{a.dtype.str}{a.shape}".encode())
    h.update(np.ascontiguousarray(a).data)
    return "sha256:" + h.hexdigest()


#: a temporary name of :func:`atomic_path` or :func:`staged_directory`:
#: ``.<name>.tmp-<pid>@<host>-<random>`` (``.old-`` for a replaced directory on its way
#: out); the pid of the process filling it tells a stale one (its process is gone) from
#: one a concurrent run is filling, on the host that made it (a digest of its name: a
#: workspace on shared storage is filled from other machines too, whose pids mean
#: nothing here)
TEMPORARY = re.compile(r"^\.(?P<name>.+)\.(?P<kind>tmp|old)-(?P<pid>\d+)(?:@(?P<host>[0-9a-f]+))?-")
_HOST = hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]


def _temporary_name(name: str, kind: str, suffix: str = "") -> str:
    return f".{name}.{kind}-{os.getpid()}@{_HOST}-{secrets.token_hex(4)}{suffix}"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):  # gone, or no pid at all
        return False
    except PermissionError:
        return True  # another user's process
    return True


def remove_stale_temporaries(directory: str | os.PathLike) -> list[Path]:
    """Remove the temporary files and directories in ``directory`` (not below) left by
    ilt processes of this host that are gone (killed mid-write); returns what was removed."""
    removed = []
    with os.scandir(directory) as entries:
        for entry in entries:
            m = TEMPORARY.match(entry.name)
            if m is None or m["host"] not in (None, _HOST) or _alive(int(m["pid"])):
                continue
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path, ignore_errors=True)
            else:
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(entry.path)
            removed.append(Path(entry.path))
    return removed


def _remove_lost_temporaries(directory: Path) -> None:
    """Temporary files inside a finished staged directory: a writer lost mid-write left
    them (a cluster's worker killed while its beam was run again elsewhere); nothing
    writes there any more, and no manifest lists a hidden file."""
    for root, _, files in os.walk(directory):
        for name in files:
            if (m := TEMPORARY.match(name)) and m["kind"] == "tmp":
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(os.path.join(root, name))


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix) that replaces it on success.

    The writer fills the temporary file; it is fsynced and renamed over ``path``. On an
    exception the temporary file is removed and ``path`` is untouched. The file gets
    the mode ``open()`` would give it (0666 less the umask), not mkstemp's 0600, so
    others can read what ilt writes when the umask lets them.
    """
    path = Path(path)
    while True:
        tmp = path.with_name(_temporary_name(path.stem, "tmp", path.suffix))
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            break
        except FileExistsError:
            continue
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_json(path: str | os.PathLike, data: dict) -> Path:
    """Write JSON atomically (temporary file in the same directory, fsync, rename)."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, default=_json_default) + "\n")
    return Path(path)


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot write {type(obj).__name__} to JSON")


def save_npy(path: str | os.PathLike, array: np.ndarray) -> Path:
    """``np.save`` atomically (no pickles)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, array, allow_pickle=False)
    return Path(path)


def write_manifest(
    directory: str | os.PathLike,
    stage: str,
    parameters: dict,
    inputs: dict[str, str] | None = None,
    extra: dict | None = None,
) -> Path:
    """Write ``directory/manifest.json``: stage, ilt version, parameters, inputs with
    fingerprints, and the fingerprint of every file written in the directory."""
    directory = Path(directory)
    outputs = {
        str(p.relative_to(directory)): fingerprint_file(p)
        for p in sorted(directory.rglob("*"))
        if p.is_file() and p.name != MANIFEST and not p.name.startswith(".")
    }
    data = {
        "stage": stage,
        "ilt_version": __version__,
        "parameters": parameters,
        "inputs": inputs or {},
        "outputs": outputs,
    }
    if extra:
        data.update(extra)
    return write_json(directory / MANIFEST, data)


def read_manifest(directory: str | os.PathLike) -> dict:
    path = Path(directory) / MANIFEST
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise StageError(f"{path}: no manifest (not a stage directory written by ilt?)") from None
    except json.JSONDecodeError as exc:
        raise StageError(f"{path}: not valid JSON ({exc})") from None


def _make_temporary_directory(parent: Path, name: str, kind: str) -> Path:
    while True:
        path = parent / _temporary_name(name, kind)
        try:
            path.mkdir(0o777)  # the mode mkdir gives (0777 less the umask), not mkdtemp's 0700
            return path
        except FileExistsError:
            continue


#: how many of the files a refusal names
_NAMED = 5


def _listing(names: list[str]) -> str:
    shown = ", ".join(names[:_NAMED])
    return shown + (f" and {len(names) - _NAMED} more" if len(names) > _NAMED else "")


def _files(directory: Path) -> list[str]:
    """Every file and link below ``directory``, relative (empty directories lose nothing)."""
    out = []
    for root, dirs, files in os.walk(directory):
        links = [d for d in dirs if os.path.islink(os.path.join(root, d))]
        rel = Path(root).relative_to(directory)
        out += [(rel / name).as_posix() for name in files + links]
    return sorted(out)


def _manifest_or_none(directory: Path) -> dict | None:
    """``directory``'s manifest, or None when it has none ilt could have written."""
    try:
        manifest = read_manifest(directory)
    except (StageError, OSError):
        return None
    return manifest if isinstance(manifest, dict) else None


def _foreign(directory: Path, files: list[str]) -> list[str]:
    """The files of ``directory`` that are not its stage's own.

    Own are: the files its manifest lists as outputs; those listed by the manifest of a
    sub-directory of the same stage (``decompose/<photo>/`` that ``ilt decompose`` adds
    to the ``decompose/`` of ``ilt run``); a sub-directory's manifest.json beside an own
    file (``isf/fine/``, ``photos/raw/<kind>/``); the run record; ilt's temporary files
    and what lies in its temporary directories (a killed ``ilt decompose``'s).
    A directory without a readable manifest owns nothing.
    """
    top = _manifest_or_none(directory)
    if top is None:
        return files
    own = set(top.get("outputs", {}))
    for name in files:
        path = Path(name)
        if path.name == MANIFEST and len(path.parts) > 1:
            sub = _manifest_or_none(directory / path.parent)
            if sub is not None and sub.get("stage") == top.get("stage"):
                own |= {(path.parent / o).as_posix() for o in sub.get("outputs", {})}
    own_dirs = {Path(name).parent for name in own}
    return [name for name in files
            if name not in own and name not in (MANIFEST, RECORD)
            and not (Path(name).name == MANIFEST and Path(name).parent in own_dirs)
            and not any(TEMPORARY.match(part) for part in Path(name).parts)]


def _refusal(final: Path) -> str | None:
    """Why ``final`` may not be replaced by a stage's output, or None when it may."""
    from ilt.workspace import workspace_marks

    resolved = final.resolve()
    cwd = Path.cwd().resolve()
    if resolved == cwd or resolved in cwd.parents:
        return f"{final} is the current directory or one above it; choose another output directory"
    if resolved == Path(os.path.expanduser("~")).resolve():
        return f"{final} is your home directory; choose another output directory"
    if not final.exists() and not final.is_symlink():
        return None
    if not final.is_dir() or final.is_symlink():
        return f"{final} is not a directory ilt wrote; choose another output directory"
    if marks := workspace_marks(final):
        return f"{final} is a workspace (holds {_listing(marks)}); choose another output directory"
    files = _files(final)
    if logs := [f for f in files if Path(f).name == LOG_NAME]:
        return f"{final} holds a raw capture ({logs[0]}); choose another output directory"
    if foreign := _foreign(final, files):
        return (f"{final} holds files ilt did not write: {_listing(foreign)}; "
                "choose another output directory or move them")
    return None


def _stage(directory: Path) -> str | None:
    """The stage ``directory``'s manifest names (None: no manifest)."""
    return (_manifest_or_none(directory) or {}).get("stage")


def _quoted(stage: str | None) -> str:
    return f"'{stage}'" if stage else "an unnamed stage"


@contextlib.contextmanager
def staged_directory(final: str | os.PathLike, force: bool = False) -> Iterator[Path]:
    """Yield an empty temporary directory that replaces ``final`` on success.

    On an exception the temporary directory is removed and ``final`` is untouched.
    An existing ``final`` is an error unless ``force``; then it is replaced only
    after the new one is complete, and only when it is empty or an earlier output of
    the same stage whose every file is its own (see :func:`_foreign`): never the
    current directory or one above it, the home directory, a workspace or a raw
    capture, even with ``force``. Refusals are :class:`StageError` naming ``final``.

    The writer writes ``manifest.json`` (naming its stage and listing its outputs) last:
    that is how a later run recognises the directory as the stage's own. Temporaries
    beside ``final`` left by a killed ilt process are removed first.
    """
    final = Path(os.path.normpath(final))
    if reason := _refusal(final):
        raise StageError(reason)
    if final.exists() and not force:
        raise StageError(f"{final} exists; use --force to replace it")
    final.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(final.parent)
    tmp = _make_temporary_directory(final.parent, final.name, "tmp")
    try:
        yield tmp
        _remove_lost_temporaries(tmp)
        if final.exists():
            # checked again: the directory may have changed (or appeared) while the stage ran
            if reason := _refusal(final):
                raise StageError(reason)
            old, new = _stage(final), _stage(tmp)
            if old != new and _files(final):
                raise StageError(f"{final} is the output of {_quoted(old)}, not {_quoted(new)}; "
                                 "choose another output directory")
            old_dir = _make_temporary_directory(final.parent, final.name, "old")
            os.replace(final, old_dir / final.name)
            os.replace(tmp, final)
            shutil.rmtree(old_dir, ignore_errors=True)
        else:
            os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
