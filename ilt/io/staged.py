"""Stage directories written whole or not at all (DESIGN.md sec. 3, issue 14).

A stage never writes into its final directory: it fills a hidden sibling temporary
directory and renames it into place, so an interrupted run leaves either the old
directory or the complete new one, never a half stage that looks whole. It replaces
only what it may lose: an empty directory or an earlier output of the same stage
holding nothing but its own files; never the current directory or one above it, the
home directory, a workspace or a raw capture.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

from ilt.io.atomic import TEMPORARY, make_temporary_directory, remove_lost_temporaries, remove_stale_temporaries
from ilt.io.manifest import LOG_NAME, MANIFEST, RECORD, StageError, read_manifest
from ilt.io.workspace_dirs import workspace_marks

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


def _owner(directory: Path, files: list[str]) -> tuple[str | None, set[str]]:
    """The stage that wrote ``directory`` (None: none) and the files that are its own.

    Own are the files its manifest lists as outputs, and those listed by the manifest
    of a sub-directory of the same stage (``decompose/<photo>/`` that ``ilt decompose``
    adds to the ``decompose/`` of ``ilt run``). A directory without a readable manifest
    of its own is a stage's when the manifests of its sub-directories all name that one
    stage (the ``decompose/`` that ``ilt decompose`` run by hand fills); else it owns
    nothing.
    """
    subs = []
    for name in files:
        path = Path(name)
        if path.name == MANIFEST and len(path.parts) > 1:
            if (sub := _manifest_or_none(directory / path.parent)) is not None:
                subs.append((path.parent, sub))
    top = _manifest_or_none(directory)
    if top is not None:
        stage, own = top.get("stage"), set(top.get("outputs", {}))
    else:
        stages = {sub.get("stage") for _, sub in subs}
        if len(stages) != 1:
            return None, set()
        stage, own = stages.pop(), set()
    for parent, sub in subs:
        if sub.get("stage") == stage:
            own |= {(parent / o).as_posix() for o in sub.get("outputs", {})}
    return stage, own


def _foreign(directory: Path, files: list[str]) -> list[str]:
    """The files of ``directory`` that are not its stage's own (:func:`_owner`), nor a
    sub-directory's manifest.json beside an own file (``isf/fine/``,
    ``photos/raw/<kind>/``), the run record, ilt's temporary files or what lies in its
    temporary directories (a killed ``ilt decompose``'s).
    """
    stage, own = _owner(directory, files)
    if stage is None:
        return files
    own_dirs = {Path(name).parent for name in own}
    return [name for name in files
            if name not in own and name not in (MANIFEST, RECORD)
            and not (Path(name).name == MANIFEST and Path(name).parent in own_dirs)
            and not any(TEMPORARY.match(part) for part in Path(name).parts)]


def _refusal(final: Path) -> str | None:
    """Why ``final`` may not be replaced by a stage's output, or None when it may."""
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
    """The stage that wrote ``directory`` (:func:`_owner`; None: none)."""
    return _owner(directory, _files(directory))[0]


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
    tmp = make_temporary_directory(final.parent, final.name, "tmp")
    try:
        yield tmp
        remove_lost_temporaries(tmp)
        if final.exists():
            # checked again: the directory may have changed (or appeared) while the stage ran
            if reason := _refusal(final):
                raise StageError(reason)
            old, new = _stage(final), _stage(tmp)
            if old != new and _files(final):
                raise StageError(f"{final} is the output of {_quoted(old)}, not {_quoted(new)}; "
                                 "choose another output directory")
            old_dir = make_temporary_directory(final.parent, final.name, "old")
            os.replace(final, old_dir / final.name)
            os.replace(tmp, final)
            shutil.rmtree(old_dir, ignore_errors=True)
        else:
            os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
