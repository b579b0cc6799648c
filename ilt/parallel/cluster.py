"""The per-beam stages and the compressed solver on a Dask cluster (``--scheduler``;
docs/cluster.md).

One seam: :func:`executor_for` turns a scheduler address into the
``concurrent.futures.Executor`` that merge, centroids and build-isf take as their
``executor=`` argument, and ``compressed`` for its blocks
(:func:`ilt.transport.compressed.compressed_operator`, reading T from its memory-mapped file),
or None, the default, under which they run on a process pool (the solver: threads)
of this machine (:mod:`ilt.parallel.pool`) and nothing of Dask is imported.

Workers receive paths and beam ranges, never frames; what a task returns (a beam's
summary, a chunk's spots or columns of T) comes back to this process, which writes
every stage file but the merged EXRs, written by the merge workers into the staged
output directory: the workspace (capture/, hdr/, the frame scratch of ``ilt run``)
must be on storage every worker sees at the same path. The scheduler is a runtime
option like ``--workers``: no stage fingerprint or parameter depends on it.

A scheduler runs the pickled functions of any client that reaches its port, so
:func:`executor_for` reaches one only where that is safe (:class:`ClusterConfig`): a
``tls://`` scheduler with this client's certificates (:func:`_security`), a plain
``tcp://`` one on this machine's loopback, or another machine's when ``insecure`` says
the network is trusted; ``local`` listens on loopback only.
"""

from __future__ import annotations

import concurrent.futures as cf
import ipaddress
import json
import logging
import os
import re
import ssl
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from urllib.parse import urlsplit

log = logging.getLogger(__name__)

#: the environment variable Dask itself reads for the scheduler's address
ENV = "DASK_SCHEDULER_ADDRESS"
#: ``--scheduler local``: a LocalCluster on this machine
LOCAL = "local"
#: seconds to wait for the scheduler (and its --scheduler-file) before giving up
CONNECT_TIMEOUT = 10.0
#: the schemes whose connections are encrypted and authenticated by certificates
TLS_SCHEMES = ("tls", "wss")
#: a client's TLS files: the ClusterConfig field, the Security attribute, Dask's configuration key
TLS_FILES = (("ca", "tls_ca_file", "distributed.comm.tls.ca-file"),
             ("cert", "tls_client_cert", "distributed.comm.tls.client.cert"),
             ("key", "tls_client_key", "distributed.comm.tls.client.key"))


@dataclass(frozen=True)
class ClusterConfig:
    """Where the stages run and how this client reaches the scheduler safely: the command
    line's ``--scheduler``, ``--scheduler-file`` and ``--insecure``, over the ``[cluster]``
    table of ``ilt run``'s rig TOML (read by :mod:`ilt.workspace.pipeline`; paths resolved).

    ``ca``, ``cert``, ``key``: PEM files of the cluster's certificate authority and of
    this client's certificate and private key, for a ``tls://`` scheduler; one not given
    is Dask's configuration's (``distributed.comm.tls.*``). ``insecure``: a plain
    ``tcp://`` scheduler on another machine is allowed (the network is trusted).
    ``origin``: where ``ca``, ``cert`` and ``key`` were given, named in errors
    (``rig.toml: [cluster]``)."""

    scheduler: str | None = None
    #: a JSON file with the scheduler's "address" ('dask scheduler --scheduler-file PATH')
    scheduler_file: Path | None = None
    ca: Path | None = None
    cert: Path | None = None
    key: Path | None = None
    insecure: bool = False
    origin: str = "[cluster]"

    def over(self, config: ClusterConfig) -> ClusterConfig:
        """These settings (the command line's) over ``config`` (a rig TOML's): this
        scheduler or scheduler file when one is given, else ``config``'s; insecure when
        either says so; ``config``'s TLS files."""
        chosen = self if self.scheduler or self.scheduler_file else config
        return replace(config, scheduler=chosen.scheduler, scheduler_file=chosen.scheduler_file,
                       insecure=self.insecure or config.insecure)


class ClusterError(ConnectionError):
    """The scheduler cannot be reached, or Dask is not installed: one line naming the
    address (an OSError, so that the CLI reports it in one line, exit 1)."""


class WorkerOSError(OSError):
    """An OSError a task raised on a Dask worker (most often a path that worker does not
    see: a machine without the shared storage), re-raised there with the worker's
    address and name added, one line: ``PATH: ... (on the Dask worker tcp://...)``."""


class SchedulerLost(ClusterError):
    """The connection to the scheduler was lost mid-stage (the scheduler stopped, or its
    machine or the network went away): Dask cancels every task of the client, and the
    stage fails with this one line naming the scheduler's address (an OSError: exit 1;
    the staged output directory is removed, as on any error)."""


class ClusterLost(cf.BrokenExecutor):
    """A task the cluster gave up on (its workers kept dying: Dask's KilledWorker after
    ``distributed.scheduler.allowed-failures`` retries): :func:`ilt.parallel.chunks.run_chunks`
    turns it into a WorkerError naming the beams. (A lost scheduler is
    :class:`SchedulerLost`.)"""


def scheduler_address(scheduler: str | None) -> str | None:
    """``scheduler`` when given, else ``$DASK_SCHEDULER_ADDRESS`` when set, else None."""
    scheduler = (scheduler or "").strip() or os.environ.get(ENV, "").strip()
    return scheduler or None


def read_scheduler_file(path: Path) -> str:
    """The "address" of a scheduler file, as ``dask scheduler --scheduler-file PATH``
    (dask-jobqueue's and dask-mpi's schedulers too) writes it once it listens: waited for
    up to :data:`CONNECT_TIMEOUT` seconds, so that a batch job can start the scheduler
    and ilt together. :class:`ClusterError` naming the file."""
    deadline = time.monotonic() + CONNECT_TIMEOUT
    while True:
        try:
            address = json.loads(path.read_text())["address"]
            if isinstance(address, str) and address.strip():
                return address.strip()
            problem = "not a Dask scheduler file (JSON with the scheduler's \"address\")"
        except FileNotFoundError:
            problem = (f"no scheduler file within {CONNECT_TIMEOUT:g} s ('dask scheduler --scheduler-file {path}' "
                       "writes it once the scheduler listens)")
        except (ValueError, KeyError, TypeError):  # (or not yet written out)
            problem = "not a Dask scheduler file (JSON with the scheduler's \"address\")"
        except OSError as exc:
            raise ClusterError(f"{path}: {exc.strerror or exc} (the --scheduler-file)") from None
        if time.monotonic() >= deadline:
            raise ClusterError(f"{path}: {problem}")
        time.sleep(0.1)


def refuse_plain_tcp_off_this_machine(address: str, insecure: bool) -> None:
    """:class:`ClusterError` for a scheduler address whose connections are neither
    encrypted (``tls://``) nor on this machine's loopback, unless ``insecure``: anyone who
    can reach such a scheduler's port can run code as the user it runs as. Looks at the
    address alone (no name is resolved, nothing connected)."""
    parts = urlsplit(address)
    if parts.scheme in TLS_SCHEMES or insecure or _loopback(parts.hostname or ""):
        return
    raise ClusterError(
        f"{address}: refused: a plain {parts.scheme}:// scheduler off this machine runs the code of anyone who can "
        "reach its port; use a tls:// scheduler (certificates: [cluster] ca, cert, key, or Dask's "
        "distributed.comm.tls.*; docs/cluster.md), or --insecure / [cluster] insecure = true if only trusted "
        "users can reach that network")


def _loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:   # a host name: another machine, as far as the address says
        return False


def _security(address: str, cluster: ClusterConfig):
    """The ``distributed.security.Security`` of this client for a ``tls://`` (``wss://``)
    scheduler, None for a plain one: ``cluster``'s ca, cert and key where given, else
    Dask's configuration's. Checked before any connection: :class:`ClusterError` in one
    line naming the address, or the file and where it was given, when the CA or the
    certificate is missing, a file is not there or not a certificate (and its key), or
    the private key is open to other users."""
    if urlsplit(address).scheme not in TLS_SCHEMES:
        return None
    from distributed.security import Security

    given = {attr: str(getattr(cluster, name)) for name, attr, _ in TLS_FILES if getattr(cluster, name) is not None}
    security = Security(require_encryption=True, **given)
    files = {name: (getattr(security, attr), f"{cluster.origin} {name}" if attr in given else f"Dask's {key}")
             for name, attr, key in TLS_FILES}
    missing = [what for name, what in (("ca", "no CA certificate (ca)"), ("cert", "no client certificate (cert)"))
               if not files[name][0]]
    if missing:
        raise ClusterError(f"{address}: {' and '.join(missing)} for this TLS scheduler: set [cluster] ca, cert and key "
                           "in ilt run's rig TOML, or Dask's distributed.comm.tls.ca-file, .client.cert and "
                           ".client.key (docs/cluster.md)")
    on_disk = {name: (value, source) for name, (value, source) in files.items() if value and "\n" not in value}
    for value, source in on_disk.values():   # (Dask's configuration may hold the PEM text itself)
        if not os.path.isfile(value):
            raise ClusterError(f"{source} = {value}: no such file (TLS for {address})")
    try:
        security.get_connection_args("client")
    except (ssl.SSLError, OSError) as exc:
        named = ", ".join(f"{name} = {value}" for name, (value, _) in files.items() if value)
        raise ClusterError(f"{address}: {named}: not the CA's certificate, this client's certificate and its "
                           f"private key in PEM ({_ssl_words(exc)})") from None
    # the private key: the key file, else the certificate's (the key appended to it)
    value, source = on_disk.get("key") or on_disk.get("cert") or (None, "")
    if value is not None and (mode := os.stat(value).st_mode & 0o777) & 0o077:
        raise ClusterError(f"{source} = {value}: the private key is open to other users (mode {mode:04o}), who could "
                           f"join the cluster with it: chmod 600 {value}")
    return security


def _ssl_words(exc: BaseException) -> str:
    """OpenSSL's words for ``exc`` (``certificate verify failed: self-signed certificate``),
    without its codes and source lines."""
    text = re.sub(r"^in <[^>]*>: ", "", str(exc))   # (distributed's CommClosedError: the connection)
    text = re.sub(r"^\w+Error: |\[SSL(: \w+)?\] |\s*\(_ssl\.c:\d+\)", "", text)
    return text.strip() or type(exc).__name__


def _tls_refusal(address: str, exc: BaseException) -> str | None:
    """The one line for a connection to a TLS scheduler refused by either side's
    certificates, None when ``exc`` is no such refusal (no scheduler answered)."""
    from distributed.comm.core import CommClosedError

    chain = []
    while exc is not None and exc not in chain:
        chain.append(exc)
        exc = exc.__cause__ or exc.__context__
    unverified = next((e for e in chain if isinstance(e, ssl.SSLCertVerificationError)), None)
    if unverified is not None:
        return (f"{address}: the scheduler's certificate is not signed by this client's CA ({_ssl_words(unverified)}): "
                "ca must be the certificate authority of the cluster's certificates (docs/cluster.md)")
    refused = next((e for e in chain if isinstance(e, ssl.SSLError)), None)
    if refused is None and isinstance(chain[0], CommClosedError):   # closed during the handshake
        refused = chain[0]
    if refused is None:   # (a timeout: nothing answered)
        return None
    return (f"{address}: the scheduler refused this client's certificate ({_ssl_words(refused)}): cert must be "
            "signed by the certificate authority the scheduler was started with (its --tls-ca-file; "
            "docs/cluster.md)")


class ClusterExecutor(cf.Executor):
    """A dask.distributed ``ClientExecutor`` (``pure=False``: every submission a task of
    its own) whose futures fail with :class:`ClusterLost`, a ``BrokenExecutor``, when
    the cluster loses a task for good, with :meth:`lost` saying which and how, as
    :class:`ilt.parallel.pool.BeamPool` does for a dead process. A worker that dies is
    otherwise Dask's business: its tasks run again on the others.

    A lost scheduler fails every future it handed out with :class:`SchedulerLost`, at
    once: Dask cancels the tasks it knows of when the connection drops, but a task
    submitted while it tries to reconnect is never cancelled, and waiting for it hung
    ``ilt merge`` in one of four runs of tests/parallel/test_cluster.py's stopped-scheduler test."""

    #: consecutive chunks of a stage in one task (:func:`ilt.parallel.chunks.run_chunks`): a task
    #: costs a round trip through the scheduler, a few ms, against 80 ms for a chunk of
    #: 16 small frames
    chunks_per_task = 4

    def __init__(self, client, directory: str | None = None, address: str | None = None):
        self.client = client
        #: the scheduler's address, named when it goes away
        self.address = address or getattr(getattr(client, "scheduler", None), "address", None) or "?"
        self.directory = directory or os.getcwd()
        self._inner = client.get_executor(pure=False)
        self._lost: list[tuple[cf.Future, str]] = []
        #: whether the connection to the scheduler was lost (every task cancelled)
        self.scheduler_lost = False
        self._outstanding: set[cf.Future] = set()
        self._lock = threading.Lock()

    def _connected(self) -> bool:
        return not self.scheduler_lost and getattr(self.client, "status", "running") == "running"

    def _fail_outstanding(self) -> None:
        """The scheduler is gone: every future not done fails with SchedulerLost."""
        self.scheduler_lost = True
        with self._lock:
            waiting = list(self._outstanding)
        for outer in waiting:
            try:
                outer.set_exception(SchedulerLost(
                    f"{self.address}: the connection to the Dask scheduler was lost mid-stage (it stopped, or "
                    "its machine or the network went away); the stage's unfinished beams were cancelled and "
                    "nothing was written: start the scheduler again and re-run"))
            except cf.InvalidStateError:  # done meanwhile
                pass

    def submit(self, fn, /, *args, **kwargs) -> cf.Future:
        outer: cf.Future = cf.Future()
        with self._lock:
            self._outstanding.add(outer)
        outer.add_done_callback(self._forget)
        if not self._connected():
            self._fail_outstanding()
            return outer
        inner = self._inner.submit(in_directory, self.directory, fn, *args, **kwargs)

        def done(f: cf.Future) -> None:
            if outer.done():
                return
            try:
                if f.cancelled():   # not by us (then outer is done): the scheduler went away
                    self._fail_outstanding()
                elif (exc := f.exception()) is None:
                    outer.set_result(f.result())
                elif _is_lost(exc):
                    how = f"was lost by the cluster ({type(exc).__name__}: {exc})"
                    self._lost.append((outer, how))
                    outer.set_exception(ClusterLost(how))
                else:
                    outer.set_exception(exc)
            except cf.InvalidStateError:  # cancelled meanwhile
                pass

        outer.add_done_callback(lambda o: o.cancelled() and inner.cancel())
        inner.add_done_callback(done)
        if not self._connected():   # lost while this task was being sent: Dask will not cancel it
            self._fail_outstanding()
        return outer

    def _forget(self, outer: cf.Future) -> None:
        with self._lock:
            self._outstanding.discard(outer)

    def lost(self) -> list[tuple[cf.Future, str]]:
        return list(self._lost)

    def worker_threads(self) -> int:
        """Tasks the cluster's workers run at once now (their threads, all told)."""
        return sum(self.client.nthreads().values())

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self._inner.shutdown(wait=wait and not cancel_futures)


def in_directory(directory: str, fn, /, *args, **kwargs):
    """On a worker: ``fn(*args, **kwargs)`` in the submitting process's current
    directory, so that the relative paths a stage passes mean what they mean there
    (the storage shared at the same path on every machine). A :class:`WorkerOSError`
    naming the directory and this worker when the worker does not see it; any OSError
    of the task (an input this worker cannot open) comes back as a WorkerOSError, its
    message and this worker's address."""
    if os.getcwd() != directory:
        try:
            os.chdir(directory)
        except OSError:
            raise WorkerOSError(f"{directory}: not found on the Dask worker {_this_worker()}: every worker must "
                                "see the workspace at the same path (docs/cluster.md)") from None
    try:
        return fn(*args, **kwargs)
    except WorkerOSError:
        raise
    except OSError as exc:
        raise WorkerOSError(f"{_one_line(exc)} ({_on_this_worker()})") from None
    except Exception as exc:
        # ilt's own one-line error for a file it could not open (CaptureError, raised
        # from the FileNotFoundError): the same class, the worker added to its message
        if _from_os_error(exc) and len(exc.args) == 1 and isinstance(exc.args[0], str):
            exc.args = (f"{exc.args[0]} ({_on_this_worker()})",)
        raise


def _on_this_worker() -> str:
    return (f"on the Dask worker {_this_worker()}: every worker must see the workspace at the same path, "
            "docs/cluster.md")


def _from_os_error(exc: BaseException) -> bool:
    """Whether ``exc`` was raised while handling an OSError (``raise ... from None`` too)."""
    seen = set()
    cause = exc.__cause__ or exc.__context__
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, OSError):
            return True
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return False


def _this_worker() -> str:
    """On a worker: its address, with its name when that says more and the host
    (``tcp://10.0.0.5:40123 (node1-3, node1)``)."""
    import socket

    host = socket.gethostname()
    try:
        from distributed import get_worker

        worker = get_worker()
        address, name = str(worker.address), str(worker.name)
    except Exception:  # (not in a worker task: the host is all there is to say)
        return f"on {host}"
    extra = [x for x in (name if name != address and not name.isdigit() else "", host) if x]
    return f"{address} ({', '.join(extra)})"


def _one_line(exc: OSError) -> str:
    """``exc``'s message on one line, naming its file when the message does not."""
    text = " ".join(str(exc).split())
    filename = getattr(exc, "filename", None)
    if filename is not None and str(filename) not in text:
        text = f"{filename}: {text}"
    return text


def _is_lost(exc: BaseException) -> bool:
    from distributed.comm.core import CommClosedError
    from distributed.scheduler import KilledWorker

    return isinstance(exc, (KilledWorker, CommClosedError))


def _one_thread_plugin():
    """A worker plugin: one OpenImageIO and OpenCV thread per Dask worker (as in each
    process of ilt's own pools), so that N single-threaded workers use N cores."""
    from distributed import WorkerPlugin

    class OneThread(WorkerPlugin):
        name = "ilt-one-thread"

        def setup(self, worker):
            from ilt.io.exr import one_thread_per_process

            one_thread_per_process()

    return OneThread()


@contextmanager
def executor_for(cluster: ClusterConfig | str | None = None,
                 workers: int | None = None) -> Iterator[cf.Executor | None]:
    """The executor of the per-beam stages for ``cluster`` (a bare address or None: its
    ``scheduler`` alone).

    No scheduler or scheduler file (and ``$DASK_SCHEDULER_ADDRESS`` unset): yields None,
    the stages' own process pool, without importing Dask. ``"local"``: a
    ``distributed.LocalCluster`` on this machine's loopback, ``workers`` (default: every
    core) single-threaded worker processes, closed at the end. An address
    (``tls://host:8786``; ``host:8786`` is ``tcp://``) or the one in ``scheduler_file``: a
    Client of that scheduler's workers, closed at the end (the cluster keeps running),
    through TLS (:func:`_security`) or plain TCP where that is allowed
    (:func:`refuse_plain_tcp_off_this_machine`). :class:`ClusterError` when it is not
    allowed, the certificates are missing or refused, or the scheduler does not answer
    within :data:`CONNECT_TIMEOUT` seconds; nothing has been written then. The
    dashboard's address is logged at INFO.
    """
    if not isinstance(cluster, ClusterConfig):
        cluster = ClusterConfig(scheduler=cluster)
    address = scheduler_address(cluster.scheduler) if cluster.scheduler_file is None else str(cluster.scheduler_file)
    if address is None:
        yield None
        return
    try:
        import distributed
    except ImportError:
        raise ClusterError(f"{address}: the scheduler needs dask.distributed: pip install 'ilt[cluster]'") from None
    _quiet_dask()
    local = executor = None
    if cluster.scheduler_file is not None:
        address = read_scheduler_file(cluster.scheduler_file)
    if address == LOCAL:
        n = workers or os.cpu_count() or 1
        # every server of it (scheduler, nannies, workers, dashboard) on loopback: a
        # worker too runs the functions it is sent
        local = distributed.LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                                         dashboard_address="127.0.0.1:0", silence_logs=logging.CRITICAL)
        client = distributed.Client(local)
        where = f"a LocalCluster of {n} worker processes"
    else:
        if "://" not in address:
            address = f"tcp://{address}"
        refuse_plain_tcp_off_this_machine(address, cluster.insecure)
        security = _security(address, cluster)
        try:
            client = distributed.Client(address, timeout=CONNECT_TIMEOUT, security=security)
        except (OSError, TimeoutError) as exc:
            refusal = _tls_refusal(address, exc) if security is not None else None
            raise ClusterError(refusal or f"{address}: no Dask scheduler answered within {CONNECT_TIMEOUT:g} s "
                                          f"({type(exc).__name__}); start one with 'dask scheduler', or check "
                                          f"--scheduler / [cluster] scheduler / ${ENV}") from None
        where = f"the Dask scheduler at {address}"
    try:
        client.register_plugin(_one_thread_plugin())
        dashboard = _dashboard(client)
        n = len(client.scheduler_info().get("workers", {}))
        log.info("tasks run on %s (%d workers)%s", where, n, f"; dashboard {dashboard}" if dashboard else "")
        if n == 0:
            log.warning("%s has no workers yet: the stages wait for some ('dask worker %s')", address, address)
        executor = ClusterExecutor(client, address=client.scheduler.address if local is not None else address)
        yield executor
    finally:
        quiet = executor is not None and executor.scheduler_lost and not logging.getLogger().isEnabledFor(logging.DEBUG)
        if quiet:
            # closing a client that is trying to reconnect logs Dask's traceback of the
            # cancelled attempt (at ERROR): SchedulerLost has said it in one line
            logging.disable(logging.CRITICAL)
        try:
            client.close()
        finally:
            if quiet:
                logging.disable(logging.NOTSET)
        if local is not None:
            try:
                local.close()
            except AssertionError as exc:
                # distributed's nanny cannot kill a worker it is restarting (after a worker
                # died: "can only join a started process"); that worker ends with this
                # process, and the stage's own outcome is what the user must see
                log.debug("closing %s: %s", where, exc)


def _quiet_dask() -> None:
    """Dask's own INFO lines (workers joining, connections closing) only with ``ilt -v``:
    ilt logs what matters (where the stages run, the dashboard). Worker failures come
    back as the task's exception, which ilt reports in one line."""
    if not logging.getLogger().isEnabledFor(logging.DEBUG):
        logging.getLogger("distributed").setLevel(logging.WARNING)
    tornado = logging.getLogger("tornado.application")
    if not any(isinstance(f, _CancelledCascade) for f in tornado.filters):
        tornado.addFilter(_CancelledCascade())


class _CancelledCascade(logging.Filter):
    """Drops tornado's ERROR record of distributed's ``_cascade_future`` setting the
    failure of a task on its concurrent future after ilt cancelled that future (the
    stage had already failed on an earlier chunk and cancels the rest: ``run_chunks``).
    distributed sets it without checking, the future raises InvalidStateError and
    tornado logs it with a traceback: a second message after ilt's one line, in about one
    of five runs of tests/parallel/test_cluster.py's worker-without-storage test. The
    failure itself is the one ilt reported."""

    def filter(self, record: logging.LogRecord) -> bool:
        exc = record.exc_info[1] if record.exc_info else None
        if not isinstance(exc, cf.InvalidStateError):
            return True
        tb = exc.__traceback__
        while tb is not None:
            if tb.tb_frame.f_code.co_filename.endswith(os.path.join("distributed", "cfexecutor.py")):
                return False
            tb = tb.tb_next
        return True


def _dashboard(client) -> str | None:
    """The dashboard's address, None when the scheduler serves none (no bokeh)."""
    try:
        info = client.scheduler_info()
        if "dashboard" not in info.get("services", {}):
            return None
        return client.dashboard_link
    except Exception:  # (an optional nicety: never a reason to stop)
        return None
