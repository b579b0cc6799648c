"""Writes that are whole or absent: a temporary name beside the target, renamed over it
on success (:func:`atomic_path`), and the temporaries a killed process left behind.

What it writes gets the modes an ordinary open() and mkdir() would give under the
umask, and temporaries carry their writer's pid and host, so the next run can remove
those of a process that is gone.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import secrets
import shutil
import socket
from collections.abc import Iterator
from pathlib import Path

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


def remove_lost_temporaries(directory: Path) -> None:
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


def make_temporary_directory(parent: Path, name: str, kind: str) -> Path:
    while True:
        path = parent / _temporary_name(name, kind)
        try:
            path.mkdir(0o777)  # the mode mkdir gives (0777 less the umask), not mkdtemp's 0700
            return path
        except FileExistsError:
            continue
