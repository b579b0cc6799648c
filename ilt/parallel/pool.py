"""Process pools for the per-beam stages (merge, centroids, build-isf).

Workers are forked from a fork server (multiprocessing's ``forkserver``), never from
the calling process: that process may hold OpenImageIO, OpenCV or LibRaw (OpenMP)
threads, and a child forked from a threaded process can inherit a lock held by a
thread that does not exist in the child and wait on it forever. The fork server is a
fresh single-threaded process that imports the stage modules once (preloaded), so
every worker starts in milliseconds with them imported. Each worker runs one
OpenImageIO and one OpenCV thread: N workers use N cores.

Whatever happens to the calling process, nothing of the pool outlives it: on an
exception (Ctrl-C, SIGTERM through the CLI) the pool cancels what is queued and kills
its workers; if the calling process is killed outright, the fork server and the
workers get SIGKILL from the kernel (Linux) or a watchdog thread (elsewhere).
"""

from __future__ import annotations

import concurrent.futures as cf
import ctypes
import ctypes.util
import multiprocessing as mp
import multiprocessing.connection
import multiprocessing.forkserver
import multiprocessing.resource_tracker
import os
import signal
import sys
import threading
import weakref
from collections.abc import Iterator
from contextlib import contextmanager

from ilt.io.exr import one_thread_per_process

#: modules the fork server imports once for every worker (this one first: its import
#: in the fork server runs :func:`_fork_server_hook`)
PRELOAD = ["ilt.parallel.pool", "ilt.hdr.stages", "ilt.spots.stage", "ilt.isf.build", "rawpy", "exifread", "cv2"]

#: in the fork server's environment only: the pid of the process that started it, or
#: "" when it was started from a thread other than the main one
_SERVER_ENV = "ILT_FORK_SERVER_OF"

_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def _die_with_parent() -> bool:
    """Ask the kernel to SIGKILL this process when its parent thread ends (Linux
    ``prctl(PR_SET_PDEATHSIG)``). False where there is no such call."""
    if not sys.platform.startswith("linux"):
        return False
    libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    return libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0


#: the fork server's import path (set in the fork server): the interpreter's own,
#: without the entry for the current directory (see :func:`_start_fork_server`)
_SERVER_PATH: list[str] | None = None


def _fork_server_hook() -> None:
    """Run on import: in the fork server (and only there, where ``_SERVER_ENV`` is set),
    die with the process that started it, and keep its clean import path for workers."""
    global _SERVER_PATH
    parent = os.environ.pop(_SERVER_ENV, None)
    if parent is None:
        return
    _SERVER_PATH = list(sys.path)
    # the death signal follows the thread that started the server: set only when that
    # is the main thread (else it would fire when that thread ends); a parent dead
    # before the call is seen by the pid check
    if parent and _die_with_parent() and os.getppid() != int(parent):
        os._exit(1)


_fork_server_hook()


#: signals whose handlers (Ctrl-C's KeyboardInterrupt, the CLI's SIGTERM and SIGHUP)
#: raise an exception in the main thread
_HELD = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


@contextmanager
def _signals_held() -> Iterator[None]:
    """Run the handlers of ``_HELD`` signals after the block, not inside it: an
    exception raised while a process starts would leave it running, unknown to its
    pool (or the fork server unknown to multiprocessing), and unstoppable."""
    if threading.current_thread() is not threading.main_thread():
        yield  # handlers run in the main thread only
        return
    caught: list[int] = []
    held = {s: signal.getsignal(s) for s in _HELD}
    held = {s: h for s, h in held.items() if h is not None}  # (None: a handler not set from Python)
    for s in held:
        signal.signal(s, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        for s, handler in held.items():
            signal.signal(s, handler)
        for s in dict.fromkeys(caught):
            signal.raise_signal(s)


def _start_fork_server() -> None:
    """Start the fork server now if it is not running, with the stage modules preloaded.

    Python starts it as ``python -c ...``, so its ``sys.path[0]`` is the current
    directory, and a folder named ``ilt`` there would be imported instead of this
    package: the parent's ``sys_path``, passed along, is ignored by Python 3.11's fork
    server (https://github.com/python/cpython/issues/117378, fixed in 3.12.8 and
    3.13.1, which apply it instead: the ``ilt`` script's is its bin directory).
    ``PYTHONSAFEPATH`` (Python 3.11+,
    https://docs.python.org/3/using/cmdline.html#envvar-PYTHONSAFEPATH) stops the
    interpreter from prepending that entry. It is set here only while the server
    starts (the server and its workers keep it; another thread starting a process at
    that moment would inherit it too).
    """
    saved = {k: os.environ.get(k) for k in ("PYTHONSAFEPATH", _SERVER_ENV)}
    os.environ["PYTHONSAFEPATH"] = "1"
    os.environ[_SERVER_ENV] = str(os.getpid()) if threading.current_thread() is threading.main_thread() else ""
    try:
        multiprocessing.forkserver.set_forkserver_preload(PRELOAD)
        with _signals_held():
            multiprocessing.forkserver.ensure_running()
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


class RunningTasks:
    """Which worker process runs which task, in memory shared with the workers
    (inherited at their start), so that when one dies the task it ran is known. No
    lock (a named semaphore would have to be unlinked): each entry has one writer, the
    worker running its task."""

    #: entries; two tasks this far apart that run at once would share one
    SIZE = 1 << 16

    def __init__(self, context):
        self.pids = context.RawArray("q", self.SIZE)

    def start(self, task: int) -> None:
        self.pids[task % self.SIZE] = os.getpid()

    def end(self, task: int) -> None:
        self.pids[task % self.SIZE] = 0

    def of(self, pid: int, tasks) -> list[int]:
        """Of ``tasks``, those the worker ``pid`` was running."""
        return [t for t in tasks if self.pids[t % self.SIZE] == pid]


_running: RunningTasks | None = None


def _init_worker(running: RunningTasks) -> None:
    """Worker initializer: one thread for OpenImageIO and OpenCV, the fork server's
    import path, ended with the calling process, deaf to what is meant for it."""
    global _running
    if _SERVER_PATH is not None:
        # the parent's sys.path (with its sys.path[0], the script's directory or the
        # current one) was applied by multiprocessing on the way in (spawn.prepare)
        sys.path[:] = _SERVER_PATH
    # Ctrl-C or a hang-up of the terminal reaches the whole process group: the calling
    # process handles it and stops the pool (SIGTERM, which stays fatal here)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    # the parent is the fork server, which dies with the calling process (Linux)
    _die_with_parent()
    # everywhere, and when the fork server could not be tied to the calling process:
    # the calling process's sentinel becomes ready when it has died
    parent = mp.parent_process()
    if parent is not None:
        threading.Thread(target=_exit_when_ready, args=(parent.sentinel,), daemon=True,
                         name="ilt-parent-watchdog").start()
    _running = running
    one_thread_per_process()


def _exit_when_ready(sentinel) -> None:
    multiprocessing.connection.wait([sentinel])
    os._exit(1)


def _tracked(task: int, function, *args):
    """In a worker: ``function(*args)``, marked as run by this process meanwhile."""
    _running.start(task)
    try:
        return function(*args)
    finally:
        _running.end(task)


class _Future(cf.Future):
    """A pool's future that, once cancelled, ignores the failure the pool's thread sets
    on it when the pool breaks. Python 3.11's thread does not expect a future it holds
    to be cancelled: a chunk queued when ilt stops (cancelled by ``run_chunks``, then
    its workers killed) made that thread die with ``InvalidStateError``, print a
    traceback and leak its semaphores (seen under load; gh-107219, fixed in 3.12)."""

    def set_exception(self, exception) -> None:
        try:
            super().set_exception(exception)
        except cf.InvalidStateError:
            if not self.cancelled():
                raise


class BeamPool(cf.ProcessPoolExecutor):
    """A process pool that knows which task each worker runs and leaves no worker
    behind when the block using it ends on an exception."""

    def __init__(self, workers: int):
        context = mp.get_context("forkserver")
        self._running = RunningTasks(context)
        # weak: a future (and its result) lives as long as its caller keeps it
        self._futures: weakref.WeakValueDictionary[int, cf.Future] = weakref.WeakValueDictionary()
        self._submitted = 0
        super().__init__(max_workers=workers, mp_context=context, initializer=_init_worker,
                         initargs=(self._running,))
        # the pool's processes by pid: the executor's own dict (private; there is no
        # public one before Python 3.14's terminate_workers), kept past shutdown, which
        # forgets it, for lost() and stop()
        self._workers = self._processes

    def submit(self, function, /, *args, **kwargs) -> cf.Future:
        task, self._submitted = self._submitted, self._submitted + 1
        with _signals_held():  # (it may start a worker)
            future = super().submit(_tracked, task, function, *args, **kwargs)
        future.__class__ = _Future  # before anyone can cancel it
        self._futures[task] = future
        return future

    def lost(self) -> list[tuple[cf.Future | None, str]]:
        """After the pool broke: each future a worker was running when it died, with how
        it ended ("was killed by SIGKILL", "exited with status 1"); the workers the pool
        stopped because another died (SIGTERM) are not counted."""
        # the executor's thread reads the dead workers' exit codes as it tears the pool
        # down; a fork server child's code is read once from its sentinel, and two
        # threads reading it at once leave one of them with 255 ("exited with status
        # 255" for a worker that exited with 3, seen once under load): let it finish
        manager = getattr(self, "_executor_manager_thread", None)
        if manager is not None and manager is not threading.current_thread():
            manager.join(timeout=10)
        out = []
        for pid, process in list(self._workers.items()):
            code = process.exitcode
            if code is None or code == -signal.SIGTERM:
                continue
            how = f"was killed by {signal.Signals(-code).name}" if code < 0 else f"exited with status {code}"
            # none: it died before it ran any (in its initializer)
            tasks = self._running.of(pid, list(self._futures.keys())) or [None]
            out.extend((self._futures.get(t), how) for t in tasks)
        return out

    def stop(self) -> None:
        """Cancel what is queued, kill the workers (their chunks are lost anyway), and
        wait for them and the pool's thread: nothing of the pool is left running."""
        for process in list(self._workers.values()):
            process.kill()
        # the pool's thread sees the workers gone, fails what is left and joins them
        self.shutdown(wait=True, cancel_futures=True)

    def __exit__(self, exc_type, exc_value, traceback):
        if exc_type is None:
            self.shutdown(wait=True)
        else:  # rather than let the chunks in flight finish
            self.stop()
        return False


def process_pool(workers: int) -> BeamPool:
    """A pool of ``workers`` single-threaded processes forked from the fork server
    (:class:`BeamPool`; as a context manager it stops at once on an exception)."""
    _start_fork_server()
    return BeamPool(workers)


def stop_servers() -> None:
    """End the fork server and the resource tracker (for a program about to exit, so
    that none outlives it; a later pool starts them again). Python has no public call
    for this; these are the ones its own tests use (``multiprocessing.util._cleanup_tests``)."""
    multiprocessing.forkserver._forkserver._stop()
    multiprocessing.resource_tracker._resource_tracker._stop()
