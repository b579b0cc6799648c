"""Process pools for the per-beam stages (merge, centroids, build-isf).

Workers are forked from a fork server (multiprocessing's ``forkserver``), never from
the calling process: that process may hold OpenImageIO, OpenCV or LibRaw (OpenMP)
threads, and a child forked from a threaded process can inherit a lock held by a
thread that does not exist in the child and wait on it forever. The fork server is a
fresh single-threaded process that imports the stage modules once (preloaded), so
every worker starts in milliseconds with them imported. Each worker runs one
OpenImageIO and one OpenCV thread: N workers use N cores.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp

from ilt.imageio import one_thread_per_process

#: modules the fork server imports once for every worker
PRELOAD = ["ilt.hdr.stages", "ilt.spots", "ilt.build_isf", "rawpy", "exifread", "cv2"]


def process_pool(workers: int) -> cf.ProcessPoolExecutor:
    """A pool of ``workers`` single-threaded processes forked from the fork server."""
    context = mp.get_context("forkserver")
    context.set_forkserver_preload(PRELOAD)
    return cf.ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=one_thread_per_process)
