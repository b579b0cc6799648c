"""Beams in chunks, on this machine's process pool or a cluster's executor.

:func:`run_chunks` sends every chunk through one path (:func:`run_batch`), keeps the
results in beam order, reports progress, and turns a worker lost mid-chunk into one
:class:`WorkerError` naming the beams it held. The stages (merge, centroids,
build-isf) hand it their per-chunk functions; :func:`beam_executor` gives the pool.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import BrokenExecutor, Executor
from contextlib import contextmanager
from itertools import islice

from ilt.io.exr import one_thread


class WorkerError(ChildProcessError):
    """A worker process died (killed, out of memory, crashed, failed to start); the
    message names the beams it was running. An OSError ("an operation on a child
    process failed"), so that the CLI reports it in one line like a system error."""


def chunks(items: Sequence, size: int) -> list[Sequence]:
    """Consecutive slices of ``items``: of ``size``, then the last ``2 size`` items in
    slices of a quarter of it, so that workers finish together (a worker left alone
    with a whole last chunk idles the others for up to a chunk's time)."""
    small = max(1, size // 4)
    head = max(0, len(items) - 2 * size)
    head -= head % size
    return ([items[i:i + size] for i in range(0, head, size)]
            + [items[i:i + small] for i in range(head, len(items), small)])


@contextmanager
def beam_executor(executor: Executor | None, workers: int | None) -> Iterator[Executor | None]:
    """The executor to use: the caller's, else a process pool of ``workers`` (None: all cores).

    ``workers == 1`` runs in this process (yields None) on one core: OpenImageIO and
    OpenCV are held to one thread meanwhile, as in each of N worker processes, so that
    ``-j N`` means N cores. A pool of its own is stopped at once (queued chunks
    cancelled, workers killed) when the block ends on an exception.
    """
    if executor is not None:
        yield executor
        return
    workers = workers or os.cpu_count() or 1
    if workers == 1:
        with one_thread():
            yield None
        return
    from ilt.parallel.pool import process_pool

    with process_pool(workers) as pool:
        yield pool


def run_chunks(function: Callable, tasks: Iterable[tuple], executor: Executor | None,
               in_flight: int = 8, progress: Callable[[int], None] | None = None) -> Iterator:
    """``function(*task)`` for every task, in order, at most ``in_flight`` submitted at once.

    Each task's first item is a sequence of beams; ``progress(len(beams))`` is called
    as each finishes. With ``executor`` None everything runs here. A worker process
    that dies raises :class:`WorkerError` naming the beams it was running. Each
    submission is :func:`run_batch` of ``chunks_per_task`` consecutive tasks (an
    executor's attribute, a cluster's 4, :class:`ilt.parallel.cluster.ClusterExecutor`; else 1):
    each runs as it would alone, so the results are the same, with fewer round trips.
    """
    if executor is None:
        for task in tasks:
            result = function(*task)
            if progress:
                progress(len(task[0]))
            yield result
        return
    per_task = max(1, int(getattr(executor, "chunks_per_task", 1)))
    pending: deque = deque()
    tasks = iter(tasks)
    try:
        while True:
            while len(pending) < in_flight:
                batch = list(islice(tasks, per_task))
                if not batch:
                    break
                beams = [b for task in batch for b in task[0]]
                try:
                    future = executor.submit(run_batch, function, batch)
                except BrokenExecutor:  # a worker died since the last result: the pool takes no more
                    raise WorkerError(_lost_beams(executor, pending)) from None
                pending.append((beams, [len(task[0]) for task in batch], future))
            if not pending:
                return
            _, sizes, future = pending[0]
            try:
                results = future.result()
            except BrokenExecutor:
                raise WorkerError(_lost_beams(executor, pending)) from None
            pending.popleft()
            for size, result in zip(sizes, results):
                yield result
                if progress:
                    progress(size)
    finally:
        # the caller failed or stopped reading (a bad beam, a signal): no chunk of this
        # stage may go on writing, on a pool the caller keeps (a cluster) least of all
        for *_, future in pending:
            future.cancel()


def run_batch(function: Callable, tasks: list[tuple]) -> list:
    """On a worker: ``[function(*task) for task in tasks]``."""
    return [function(*task) for task in tasks]


def _lost_beams(executor: Executor, pending: deque) -> str:
    """One line on a broken pool: the beams of the chunk each dead worker was running
    (:meth:`ilt.parallel.pool.BeamPool.lost`), else of every chunk in flight."""
    lost = getattr(executor, "lost", lambda: [])()
    named = [(beams, how) for beams, _, future in pending for f, how in lost if f is future]
    hows = {how for _, how in lost}
    # the kernel's OOM killer sends SIGKILL; a worker that failed printed its error
    hint = "out of memory? try fewer --workers" if any("SIGKILL" in h for h in hows) else \
        "its error, if it printed one, is above"
    if named:
        return "; ".join(f"{_beam_list(beams)}: the worker process running them {how}"
                         for beams, how in named) + f" ({hint})"
    return (f"{_beam_list([b for beams, _, _ in pending for b in beams])}: a worker process "
            f"{', '.join(sorted(hows)) or 'died'} before finishing them ({hint})")


def _beam_list(beams: Sequence) -> str:
    """Beams as text: "beam 3", "beams 16-31", "beams 2, 5-7"; a task that carries its
    frames' paths instead of beam numbers (build-isf's fold pass) by their names: "frames
    beam-00016.exr ... beam-00031.exr (16)"."""
    if not all(isinstance(b, int) or (hasattr(b, "__index__") and not isinstance(b, bool)) for b in beams):
        names = [os.path.basename(str(b)) for b in beams]
        shown = ", ".join(names) if len(names) <= 3 else f"{names[0]} ... {names[-1]} ({len(names)})"
        return f"frame{'s' if len(names) > 1 else ''} {shown}"
    beams = [int(b) for b in beams]
    runs: list[list[int]] = []
    for b in beams:
        if runs and b == runs[-1][1] + 1:
            runs[-1][1] = b
        else:
            runs.append([b, b])
    text = ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)
    return f"beam{'s' if len(beams) > 1 else ''} {text}"
