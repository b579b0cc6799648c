"""Where per-beam work runs: this machine's process pool or a Dask cluster.

``pool`` (a fork-server process pool, one BLAS thread per worker), ``cluster`` (a
dask.distributed executor behind the same seam; Dask is imported only when a scheduler
is given), ``chunks`` (beams in chunks over either, with one-line errors naming the
beams a lost worker held), ``memory`` (the memory this machine has free).
"""

from ilt import lazy_face

__getattr__, __dir__, __all__ = lazy_face(
    __name__,
    {
        "chunks": ["WorkerError", "beam_executor", "chunks", "run_chunks"],
        "cluster": ["ClusterConfig", "ClusterExecutor", "WorkerOSError", "executor_for"],
        "memory": ["available_memory"],
        "pool": ["process_pool"],
    },
)
