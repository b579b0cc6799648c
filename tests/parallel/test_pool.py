"""The process pool (ilt.parallel.pool) stopped with chunks still queued."""

import threading
import time

from ilt.parallel.pool import process_pool


def test_stopping_a_pool_with_cancelled_chunks_queued_leaves_its_thread_quiet(monkeypatch):
    """One worker runs a chunk, one waits in the call queue, two are queued and then
    cancelled (as run_chunks does when a signal stops the stage); the workers are
    killed, and the pool's thread sees it before stop()'s shutdown (as under load). That
    thread fails what is left: the cancelled chunks stay cancelled and it ends without
    an exception (Python 3.11's raised InvalidStateError, printed a traceback and leaked
    the pool's semaphores: a CI failure of test_signals)."""
    raised = []
    monkeypatch.setattr(threading, "excepthook", raised.append)
    pool = process_pool(1)
    running = pool.submit(time.sleep, 30)
    futures = [pool.submit(time.sleep, 30) for _ in range(3)]
    deadline = time.monotonic() + 30
    while not running.running():  # the worker has it (and the next is in the call queue)
        assert time.monotonic() < deadline
        time.sleep(0.01)
    cancelled = [f for f in futures if f.cancel()]
    assert len(cancelled) >= 2, [f._state for f in futures]
    manager = pool._executor_manager_thread
    for worker in pool._workers.values():  # what stop() does first
        worker.kill()
    manager.join(timeout=30)
    assert not manager.is_alive()
    pool.stop()
    assert raised == [], [r.exc_value for r in raised]
    assert all(f.cancelled() for f in cancelled)
    assert running.exception() is not None  # its worker was killed under it


def test_a_dead_worker_is_named_by_its_beams_or_by_its_frames():
    """run_chunks' error when a worker process dies names the chunk it held: by its beams
    (numpy's integers too), or, for a task whose first item is its frames' paths (build-isf's
    fold pass), by those frames' names (it raised a TypeError instead of the WorkerError)."""
    from pathlib import Path

    import numpy as np

    from ilt.parallel.chunks import _beam_list

    assert _beam_list([2, 3, 4, 7]) == "beams 2-4, 7"
    assert _beam_list([np.int64(5)]) == "beam 5"
    frames = [Path("hdr") / f"beam-{b:05d}.exr" for b in range(16, 32)]
    assert _beam_list(frames) == "frames beam-00016.exr ... beam-00031.exr (16)"
    assert _beam_list(frames[:2]) == "frames beam-00016.exr, beam-00017.exr"

