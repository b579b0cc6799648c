"""The per-beam stages on a Dask cluster (ilt.parallel.cluster, --scheduler): the same files, hash
for hash, as the process pool; an unreachable scheduler and a dying worker."""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import pytest
from click.testing import CliRunner

from tests.capture_helpers import run_rig_toml

distributed = pytest.importorskip("distributed",
                                  reason="dask.distributed is not installed (pip install 'ilt[cluster]')")

from ilt.cli import cli  # noqa: E402
from ilt.io.manifest import fingerprint_file

#: 16 beams of 8 x 8 pixels, a 5-frame bracket, no photos (the per-beam stages only)
RIG = run_rig_toml(16, 8, "radiance_scale = 1.0e8", '[photos]\nsim = []\n')


def run(*args, ok=True):
    result = CliRunner().invoke(cli, [str(a) for a in args])
    if ok:
        assert result.exit_code == 0, result.output + repr(result.exception)
    return result


def hashes(directory: Path) -> dict[str, str]:
    """relative path -> sha256 of every file but the manifest (which records the run's paths)."""
    return {str(p.relative_to(directory)): fingerprint_file(p) for p in sorted(directory.rglob("*"))
            if p.is_file() and p.name != "manifest.json"}


def outputs(directory: Path) -> dict[str, str]:
    """A manifest's output fingerprints."""
    return json.loads((directory / "manifest.json").read_text())["outputs"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A captured scan (16 beams), merged, centroided and built on the process pool."""
    root = tmp_path_factory.mktemp("cluster")
    (root / "rig.toml").write_text(RIG)
    run("capture", root / "rig.toml", "-o", root / "capture")
    run("merge", root / "capture", "-o", root / "hdr", "-j", 2)
    run("centroids", root / "hdr", "-o", root / "spots", "-j", 2)
    run("build-isf", root / "hdr", root / "spots", "-o", root / "isf", "-j", 2)
    return root


@pytest.fixture(scope="module")
def local_cluster():
    """A LocalCluster of 2 single-threaded worker processes; yields its scheduler's address."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address="127.0.0.1:0", silence_logs=50) as cluster:
        yield cluster.scheduler_address


def test_merge_centroids_build_isf_on_a_local_cluster_equal_the_pool(data, local_cluster, tmp_path):
    """merge (through `--scheduler local`, a LocalCluster of -j 2 workers), centroids and
    build-isf (through a running LocalCluster's tcp:// address) write every file, hdr
    EXRs, spots.csv, T.npy, scales.npy and the rest, byte for byte as the pool did."""
    run("merge", data / "capture", "-o", tmp_path / "hdr", "--scheduler", "local", "-j", 2)
    assert hashes(tmp_path / "hdr") == hashes(data / "hdr")
    assert len([p for p in (tmp_path / "hdr").glob("beam-*.exr")]) == 16
    assert outputs(tmp_path / "hdr") == outputs(data / "hdr")
    run("centroids", tmp_path / "hdr", "-o", tmp_path / "spots", "--scheduler", local_cluster)
    assert hashes(tmp_path / "spots") == hashes(data / "spots")
    run("build-isf", tmp_path / "hdr", tmp_path / "spots", "-o", tmp_path / "isf", "--scheduler", local_cluster)
    assert hashes(tmp_path / "isf") == hashes(data / "isf")
    for name in ("T.npy", "scales.npy"):
        assert fingerprint_file(tmp_path / "isf" / name) == fingerprint_file(data / "isf" / name)
    # the same parameters recorded: the scheduler is a runtime option
    for stage in ("hdr", "spots", "isf"):
        a = json.loads((tmp_path / stage / "manifest.json").read_text())["parameters"]
        b = json.loads((data / stage / "manifest.json").read_text())["parameters"]
        assert a == b


def test_scheduler_from_the_environment(data, local_cluster, tmp_path, monkeypatch):
    """$DASK_SCHEDULER_ADDRESS is the default scheduler."""
    monkeypatch.setenv("DASK_SCHEDULER_ADDRESS", local_cluster)
    from ilt.parallel.cluster import ClusterExecutor, executor_for

    with executor_for(None) as ex:
        assert isinstance(ex, ClusterExecutor)
        assert ex.submit(os.getpid).result() != os.getpid()
    run("centroids", data / "hdr", "-o", tmp_path / "spots")
    assert hashes(tmp_path / "spots") == hashes(data / "spots")
    monkeypatch.delenv("DASK_SCHEDULER_ADDRESS")
    with executor_for(None) as ex:
        assert ex is None


def test_unreachable_scheduler_is_one_line_and_writes_nothing(data, tmp_path, monkeypatch):
    import ilt.parallel.cluster

    monkeypatch.setattr(ilt.parallel.cluster, "CONNECT_TIMEOUT", 1.0)
    address = f"tcp://127.0.0.1:{free_port()}"   # closed: nothing listens there
    result = run("merge", data / "capture", "-o", tmp_path / "hdr", "--scheduler", address, ok=False)
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and address in lines[0] and "1 s" in lines[0], result.output
    assert not (tmp_path / "hdr").exists()
    # ilt run: the config's [cluster] table, refused before the workspace is made
    (tmp_path / "rig.toml").write_text(RIG + f'\n[cluster]\nscheduler = "{address}"\n')
    result = run("run", tmp_path / "rig.toml", "-w", tmp_path / "ws", ok=False)
    assert result.exit_code == 1 and address in result.output and len(result.output.strip().splitlines()) == 1
    assert not (tmp_path / "ws").exists()


def test_cluster_table_is_checked(tmp_path):
    """[cluster]: its keys, their types; the files relative to the config; the command
    line's scheduler over the config's, the config's TLS files kept."""
    from ilt.capture.config import ConfigError
    from ilt.parallel.cluster import ClusterConfig
    from ilt.workspace.pipeline import load_run_config

    (tmp_path / "a.toml").write_text(RIG + '\n[cluster]\nscheduler = "tls://head:8786"\nca = "tls/ca.pem"\n'
                                     'cert = "/lab/cert.pem"\nkey = "~/key.pem"\n')
    cluster = load_run_config(tmp_path / "a.toml").cluster
    assert cluster == ClusterConfig("tls://head:8786", ca=tmp_path / "tls/ca.pem", cert=Path("/lab/cert.pem"),
                                    key=Path("~/key.pem").expanduser(), origin=f"{tmp_path / 'a.toml'}: [cluster]")
    assert ClusterConfig(scheduler_file=Path("s.json"), insecure=True).over(cluster) == ClusterConfig(
        scheduler_file=Path("s.json"), ca=cluster.ca, cert=cluster.cert, key=cluster.key, insecure=True,
        origin=cluster.origin)
    assert ClusterConfig().over(cluster) == cluster
    for i, (table, message) in enumerate([
            ("workers = 3", r"\[cluster\]: unknown key 'workers' \(known: ca, cert, insecure, key, scheduler, "),
            ('insecure = "yes"', r"\[cluster\]: insecure must be true or false"),
            ("ca = 1", r"\[cluster\]: ca must be a file's path"),
            ('scheduler = "local"\nscheduler-file = "s.json"', r"\[cluster\]: scheduler and scheduler-file both given; keep one")]):
        (tmp_path / f"{i}.toml").write_text(RIG + f"\n[cluster]\n{table}\n")
        with pytest.raises(ConfigError, match=rf"^{re.escape(str(tmp_path / f'{i}.toml'))}: {message}"):
            load_run_config(tmp_path / f"{i}.toml")


# ------------------------------------------------------------ a scheduler and workers by hand


def _dask(*args) -> list[str]:
    return [sys.executable, "-m", "distributed.cli.dask_" + args[0], *args[1:]]


@contextmanager
def dask_processes(log_dir: Path, workers: dict[str, list[str]], preload: Path | None = None,
                   tls: Path | None = None):
    """`dask scheduler` and one `dask worker --nworkers 1 --nthreads 1` process per name
    of ``workers`` (whose value prefixes its command line: e.g. ``unshare -m ...``) on
    127.0.0.1 (no nanny: killing one kills that worker); yields the scheduler's address
    and the processes by name ("scheduler" and the workers'), stopped at the end. The
    scheduler writes LOG_DIR/scheduler.json. ``tls``: a directory of cert.pem and key.pem
    (:func:`make_certificate`), the CA and certificate of the scheduler and every worker:
    ``--protocol tls``, the address tls://."""
    port = free_port()
    address = f"{'tls' if tls else 'tcp'}://127.0.0.1:{port}"
    log = open(log_dir / "dask.log", "w")
    procs: dict[str, subprocess.Popen] = {}
    extra = ["--preload", str(preload)] if preload else []
    certificates = ([f"--tls-{flag}={tls / name}" for flag, name in (("ca-file", "cert.pem"), ("cert", "cert.pem"),
                                                                      ("key", "key.pem"))] if tls else [])
    security = lab_security(tls) if tls else None
    try:
        procs["scheduler"] = subprocess.Popen(_dask("scheduler", "--host", "127.0.0.1", "--port", str(port),
                                                    "--no-dashboard", "--scheduler-file", str(log_dir / "scheduler.json"),
                                                    *(["--protocol", "tls", *certificates] if tls else [])),
                                              stdout=log, stderr=log)
        for name, prefix in workers.items():
            procs[name] = subprocess.Popen([*prefix, *_dask("worker", address, "--nworkers", "1", "--nthreads", "1",
                                                            "--no-nanny", "--no-dashboard", "--name", name, *extra,
                                                            *certificates)],
                                           stdout=log, stderr=log)
        with distributed.Client(address, timeout=30, security=security) as client:
            client.wait_for_workers(len(workers), timeout=30)
        yield address, procs
    finally:
        # the workers first: one whose scheduler is gone waits for it before it stops
        for p in reversed(procs.values()):
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(3)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        log.close()


@pytest.fixture(scope="module")
def dask_cluster(tmp_path_factory):
    """`dask scheduler` and two workers, w0 and w1 (:func:`dask_processes`)."""
    with dask_processes(tmp_path_factory.mktemp("dask"), {"w0": [], "w1": []}) as running:
        yield running


def test_ilt_run_on_a_dask_scheduler_equals_the_pool(dask_cluster, tmp_path, monkeypatch):
    """`ilt run --scheduler tcp://...` (a relative workspace: the workers run in the
    submitting process's directory) writes hdr/, spots/ and isf/ with the outputs, hash
    for hash, of `ilt run` on the pool; either workspace is up to date for the other."""
    address, _ = dask_cluster
    (tmp_path / "rig.toml").write_text(RIG)
    monkeypatch.chdir(tmp_path)
    run("run", "rig.toml", "-w", "pool")
    run("run", "rig.toml", "-w", "dask", "--scheduler", address)
    for stage in ("hdr", "spots", "isf"):
        assert outputs(tmp_path / "dask" / stage) == outputs(tmp_path / "pool" / stage), stage
    assert not (tmp_path / "dask" / ".frames-scratch").exists()
    result = run("run", tmp_path / "rig.toml", "-w", tmp_path / "dask", "--json")
    assert not any(s["ran"] for s in json.loads(result.stdout))


def test_a_worker_killed_mid_merge_changes_nothing(data, dask_cluster, tmp_path):
    """SIGKILL to a worker running beams after the first beams finished: Dask runs its
    beams again on the other, and the HDR directory is the pool's, file for file."""
    from ilt.hdr.stages import merge_capture
    from ilt.parallel.cluster import executor_for
    from ilt.workspace.pipeline import merge_options

    address, procs = dask_cluster
    killed: list[str] = []
    done = [0]
    options = merge_options({"gain": 1.0, "read_noise": 2.0, "margin": 0.03, "color": False,
                             "compression": "zip:1"})
    with executor_for(address) as ex:
        def progress(n):
            done[0] += n
            if killed:
                return
            busy = {w: keys for w, keys in ex.client.processing().items() if keys}
            names = {a: info["name"] for a, info in ex.client.scheduler_info()["workers"].items()}
            for worker in busy:
                if names.get(worker) in ("w0", "w1"):
                    killed.append(names[worker])
                    procs[names[worker]].send_signal(signal.SIGKILL)
                    return

        params = json.loads((data / "hdr" / "manifest.json").read_text())["parameters"]
        merge_capture(data / "capture", tmp_path / "hdr", options, executor=ex, parameters=params,
                      progress=progress)
    assert killed and done[0] == 16
    assert procs[killed[0]].wait(10) == -signal.SIGKILL
    assert hashes(tmp_path / "hdr") == hashes(data / "hdr")
    assert outputs(tmp_path / "hdr") == outputs(data / "hdr")


def test_a_beam_that_kills_every_worker_is_one_error_naming_it():
    """A task Dask gives up on (KilledWorker; here after one death) is the pool's
    WorkerError, one line naming the beams of the task: its chunk's, or those of the
    chunks batched into it (``chunks_per_task``).

    One task in flight: Dask gives up on every task the dying worker held, so with two
    in flight the chunk before the fatal one is named too when the worker had it still
    (8 runs beside 4 busy processes: 1 to 3 did), which is right but not this test's
    point."""
    import dask

    from ilt.parallel.chunks import WorkerError, run_chunks
    from ilt.parallel.cluster import executor_for

    def kill_at_4(beams):
        return os._exit(1) if 4 in beams else len(beams)

    with dask.config.set({"distributed.scheduler.allowed-failures": 0}), executor_for("local", 1) as ex:
        assert list(run_chunks(lambda beams: len(beams), [([0, 1],)], ex)) == [2]
        ex.chunks_per_task = 1
        with pytest.raises(WorkerError, match=r"^beams 4-5: the worker process running them was lost by the cluster"):
            list(run_chunks(kill_at_4, [([2, 3],), ([4, 5],)], ex, in_flight=1))
        ex.chunks_per_task = 2
        with pytest.raises(WorkerError, match=r"^beams 2-5: the worker process running them was lost by the cluster"):
            list(run_chunks(kill_at_4, [([2, 3],), ([4, 5],), ([6, 7],)], ex, in_flight=1))


def test_chunks_batched_into_tasks_give_the_same_results_and_progress():
    """An executor with ``chunks_per_task`` gets that many chunks in a task; the
    results come back one per chunk, in order, and progress counts each chunk's beams,
    as without batching."""
    from concurrent.futures import ThreadPoolExecutor

    from ilt.parallel.chunks import run_chunks

    tasks = [(list(range(b, b + 3)), b * 10) for b in range(0, 30, 3)]
    done = []

    class Batching(ThreadPoolExecutor):
        chunks_per_task = 4

    with Batching(2) as ex:
        batched = list(run_chunks(lambda beams, x: (beams[0], x), tasks, ex, in_flight=2, progress=done.append))
    assert batched == [(t[0][0], t[1]) for t in tasks]
    assert done == [3] * len(tasks)


def test_no_scheduler_is_the_process_pool_without_importing_dask():
    code = ("import sys\nfrom ilt.parallel.cluster import executor_for\nwith executor_for(None) as ex:\n    assert ex is None\n"
            "assert 'distributed' not in sys.modules and 'dask' not in sys.modules, 'dask imported'\n")
    env = {k: v for k, v in os.environ.items() if k != "DASK_SCHEDULER_ADDRESS"}
    subprocess.run([sys.executable, "-c", code], check=True, env=env, timeout=60)


# ------------------------------------------------------------ workers without the files; a lost scheduler


def test_an_input_a_worker_cannot_open_names_the_path_and_the_worker(local_cluster, tmp_path):
    """An OSError of a task (here: a path that does not exist where the worker runs)
    comes back through run_chunks as an OSError (ilt.parallel.cluster.WorkerOSError), one line
    naming the path and the worker's address, not as a WorkerError or a traceback."""
    from ilt.parallel.chunks import run_chunks
    from ilt.parallel.cluster import WorkerOSError, executor_for

    missing = tmp_path / "nowhere" / "beam-00003.exr"
    with executor_for(local_cluster) as ex:
        workers = set(ex.client.scheduler_info()["workers"])
        with pytest.raises(WorkerOSError) as info:
            list(run_chunks(lambda beams, path: open(path).read(), [([3], missing)], ex))
        assert ex.lost() == []
    message = str(info.value)
    assert isinstance(info.value, OSError) and "\n" not in message
    assert str(missing) in message and "No such file" in message
    assert any(f"on the Dask worker {w}" in message for w in workers), message


def _unshare_works() -> bool:
    try:
        return subprocess.run(["unshare", "-m", "sh", "-c", "mount -t tmpfs none /mnt"],
                              capture_output=True, timeout=10).returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False


@pytest.mark.skipif(sys.platform != "linux" or not _unshare_works(),
                    reason="needs unshare -m and mount (root): a worker with its own view of the files")
def test_a_worker_without_the_shared_storage_fails_merge_in_one_line(data, tmp_path):
    """`ilt merge CAPTURE -o HDR --scheduler ...` whose one worker runs in a mount
    namespace where CAPTURE is an empty tmpfs (a machine that does not see the shared
    storage; the ilt process sees it): exit 1, one line naming a frame under CAPTURE and
    the worker (address and name), no HDR directory, no hidden temporary beside it."""
    import shutil

    capture = tmp_path / "work" / "capture"
    shutil.copytree(data / "capture", capture)
    (tmp_path / "dask").mkdir()
    hide = ["unshare", "-m", "sh", "-c", f'mount -t tmpfs none "{capture}" && exec "$@"', "sh"]
    with dask_processes(tmp_path / "dask", {"blind": hide}) as (address, _):
        result = run("-q", "merge", capture, "-o", tmp_path / "work" / "hdr", "--scheduler", address, ok=False)
    assert result.exit_code == 1, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1, result.output
    assert str(capture) in lines[0] and "on the Dask worker tcp://127.0.0.1:" in lines[0] and "blind" in lines[0]
    assert "Traceback" not in result.output
    assert sorted(p.name for p in (tmp_path / "work").iterdir()) == ["capture"]


#: a worker preload: every merged beam takes 0.3 s more, so that the scheduler can be
#: stopped while beams remain
SLOW_MERGE = """
import time


def dask_setup(worker):
    import ilt.hdr.stages as stages

    merge_one = stages._merge_one

    def slow(*args, **kwargs):
        time.sleep(0.3)
        return merge_one(*args, **kwargs)

    stages._merge_one = slow
"""
# (patched in dask_setup, once the worker runs: a module-level `import ilt.hdr.stages`
# in the preload itself hangs the worker's first task)


def test_the_scheduler_stopped_mid_merge_is_one_line_and_leaves_nothing(data, tmp_path):
    """`ilt merge ... --scheduler tcp://...` (a subprocess; one worker, 0.3 s a beam)
    whose scheduler is killed once the first beams are in the staged directory: exit 1
    within 60 s, one line on stderr naming the scheduler's address, no HDR directory
    and no hidden temporary left."""
    (tmp_path / "slow_merge.py").write_text(SLOW_MERGE)
    (tmp_path / "dask").mkdir()
    out = tmp_path / "out"
    out.mkdir()
    with dask_processes(tmp_path / "dask", {"w": []}, preload=tmp_path / "slow_merge.py") as (address, procs):
        ilt = subprocess.Popen([sys.executable, "-m", "ilt", "-q", "merge", str(data / "capture"), "-o",
                                str(out / "hdr"), "--scheduler", address],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and ilt.poll() is None:
                if len(list(out.glob("*/beam-*.exr"))) >= 2:
                    break
                time.sleep(0.02)
            assert ilt.poll() is None, "merge finished before the scheduler could be stopped"
            assert list(out.glob("*/beam-*.exr")), "no beam merged within 30 s"
            procs["scheduler"].send_signal(signal.SIGKILL)
            stopped = time.monotonic()
            stdout, stderr = ilt.communicate(timeout=60)
            took = time.monotonic() - stopped
        finally:
            if ilt.poll() is None:
                ilt.kill()
                ilt.wait()
    assert ilt.returncode == 1, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and address in lines[0], stderr
    assert took < 60
    assert stdout == ""
    assert list(out.iterdir()) == [], list(out.iterdir())


# ------------------------------------------------------------ who can reach the scheduler: TLS, plain TCP, local


def make_certificate(directory: Path) -> Path:
    """cert.pem and key.pem in ``directory``: one self-signed certificate, the CA and the
    certificate of every member of a cluster, made as docs/cluster.md says."""
    directory.mkdir(parents=True)
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "365", "-subj",
                    "/CN=ilt-dask", "-keyout", "key.pem", "-out", "cert.pem"],
                   cwd=directory, check=True, capture_output=True, timeout=60)
    return directory


def lab_security(directory: Path):
    """A client's Security with the certificate of ``directory`` (:func:`make_certificate`)."""
    from distributed.security import Security

    return Security(tls_ca_file=str(directory / "cert.pem"), tls_client_cert=str(directory / "cert.pem"),
                    tls_client_key=str(directory / "key.pem"), require_encryption=True)


def dask_tls(directory: Path | None, ca: Path | None = None) -> dict:
    """Dask's configuration of a client's TLS files: ``directory``'s certificate and key,
    ``ca`` (default: the same certificate) as the CA; none for None."""
    if directory is None:
        return {}
    return {"distributed.comm.tls.ca-file": str(ca or directory / "cert.pem"),
            "distributed.comm.tls.client.cert": str(directory / "cert.pem"),
            "distributed.comm.tls.client.key": str(directory / "key.pem")}


@pytest.fixture(scope="module")
def certificates(tmp_path_factory):
    """Two certificates (:func:`make_certificate`): the lab's cluster's, and another's."""
    if shutil.which("openssl") is None:
        pytest.skip("no openssl to make a certificate with")
    root = tmp_path_factory.mktemp("tls")
    return {"lab": make_certificate(root / "lab"), "other": make_certificate(root / "other")}


@pytest.fixture(scope="module")
def tls_cluster(tmp_path_factory, certificates):
    """`dask scheduler --protocol tls` and two TLS workers, every one with the lab's
    certificate; yields its address and its scheduler file."""
    log_dir = tmp_path_factory.mktemp("dask-tls")
    with dask_processes(log_dir, {"t0": [], "t1": []}, tls=certificates["lab"]) as (address, _):
        yield address, log_dir / "scheduler.json"


def test_ilt_run_through_tls_with_the_rig_tomls_certificates_equals_the_pool(data, certificates, tls_cluster,
                                                                            tmp_path):
    """`ilt run` with [cluster] scheduler-file, ca, cert and key (a captured workspace):
    merge, centroids and build-isf run on the TLS cluster's workers and write every file
    of hdr/, spots/ and isf/ byte for byte as the process pool did."""
    address, scheduler_file = tls_cluster
    lab = certificates["lab"]
    (tmp_path / "rig.toml").write_text(RIG + f'\n[cluster]\nscheduler-file = "{scheduler_file}"\n'
                                       f'ca = "{lab / "cert.pem"}"\ncert = "{lab / "cert.pem"}"\n'
                                       f'key = "{lab / "key.pem"}"\n')
    shutil.copytree(data / "capture", tmp_path / "ws" / "capture")
    result = run("run", tmp_path / "rig.toml", "-w", tmp_path / "ws", "--json")
    assert [s["stage"] for s in json.loads(result.stdout) if s["ran"]] == ["merge", "centroids", "build-isf"]
    assert f"tasks run on the Dask scheduler at {address} (2 workers)" in result.stderr
    for stage in ("hdr", "spots", "isf"):
        made = {name: h for name, h in hashes(tmp_path / "ws" / stage).items() if name != ".stage.json"}
        assert made == hashes(data / stage), stage


def test_a_stage_through_tls_with_dasks_own_configuration_equals_the_pool(data, certificates, tls_cluster, tmp_path):
    """`ilt centroids --scheduler tls://...` with the certificates in Dask's configuration
    (distributed.comm.tls.*, as DASK_DISTRIBUTED__COMM__TLS__* set it): the pool's files."""
    import dask

    address, _ = tls_cluster
    with dask.config.set(dask_tls(certificates["lab"])):
        run("centroids", data / "hdr", "-o", tmp_path / "spots", "--scheduler", address)
    assert hashes(tmp_path / "spots") == hashes(data / "spots")


@pytest.mark.parametrize("client, ca, says", [
    (None, None, "no CA certificate (ca) and no client certificate (cert) for this TLS scheduler: set [cluster] ca"),
    ("other", None, "the scheduler's certificate is not signed by this client's CA (certificate verify failed"),
    ("other", "lab", "the scheduler refused this client's certificate ("),
], ids=["no certificates", "another cluster's", "another certificate"])
def test_a_client_without_the_clusters_certificates_is_refused_in_one_line(data, certificates, tls_cluster, tmp_path,
                                                                          client, ca, says):
    """No certificates (before any connection), another cluster's (the scheduler's is not
    signed by its CA), or the lab's CA with another certificate (the scheduler refuses
    it): exit 1, one line naming the address and what is wrong, nothing written."""
    import dask

    address, _ = tls_cluster
    settings = dask_tls(client and certificates[client], ca and certificates[ca] / "cert.pem")
    with dask.config.set(settings):
        result = run("merge", data / "capture", "-o", tmp_path / "hdr", "--scheduler", address, ok=False)
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert lines == [lines[0]] and lines[0].startswith(f"ilt: error: {address}: {says}"), result.output
    assert list(tmp_path.iterdir()) == []


def test_the_rig_tomls_tls_files_are_checked_before_any_connection(certificates, tmp_path, monkeypatch):
    """[cluster] ca, cert, key: a file not there, a key other users can read, a file that
    is no certificate: one line naming the config, the key and the file, before any
    connection; no workspace made."""
    monkeypatch.setattr(distributed, "Client", lambda *a, **k: pytest.fail("connected"))
    lab = certificates["lab"]
    (tmp_path / "open.pem").write_bytes((lab / "key.pem").read_bytes())
    (tmp_path / "open.pem").chmod(0o644)
    (tmp_path / "junk.pem").write_text("not a certificate\n")
    config = tmp_path / "rig.toml"
    for ca, key, says in [
            ("missing.pem", "key.pem", f"{config}: [cluster] ca = {tmp_path / 'missing.pem'}: no such file (TLS for "),
            (lab / "cert.pem", "open.pem", (f"{config}: [cluster] key = {tmp_path / 'open.pem'}: the private key "
                                            "is open to other users (mode 0644), who could join the cluster with it: "
                                            "chmod 600 ")),
            ("junk.pem", lab / "key.pem", f"tls://127.0.0.1:1: ca = {tmp_path / 'junk.pem'}, cert = ")]:
        config.write_text(RIG + f'\n[cluster]\nscheduler = "tls://127.0.0.1:1"\nca = "{ca}"\n'
                                f'cert = "{lab / "cert.pem"}"\nkey = "{key}"\n')
        result = run("run", config, "-w", tmp_path / "ws", ok=False)
        assert result.exit_code == 1
        lines = result.output.strip().splitlines()
        assert lines == [lines[0]] and lines[0].startswith(f"ilt: error: {says}"), result.output
        assert not (tmp_path / "ws").exists()


def test_plain_tcp_off_this_machine_is_refused_before_any_connection(data, tmp_path, monkeypatch):
    """A tcp:// (or scheme-less) address of another machine, by name or by address: one
    line saying why and how to use TLS, and no connection tried; --insecure, or [cluster]
    insecure = true, lets it through. A loopback address goes through as it is."""
    tried = []

    def no_scheduler(address, **kwargs):
        tried.append(address)
        raise OSError(f"Timed out trying to connect to {address}")

    monkeypatch.setattr(distributed, "Client", no_scheduler)
    for given in ("tcp://10.255.255.1:8786", "head:8786", "tcp://[2001:db8::1]:8786"):
        address = given if "://" in given else f"tcp://{given}"
        result = run("merge", data / "capture", "-o", tmp_path / "hdr", "--scheduler", given, ok=False)
        assert result.exit_code == 1 and tried == []
        lines = result.output.strip().splitlines()
        assert lines == [(f"ilt: error: {address}: refused: a plain tcp:// scheduler off this machine runs the code "
                          "of anyone who can reach its port; use a tls:// scheduler (certificates: [cluster] ca, cert, "
                          "key, or Dask's distributed.comm.tls.*; docs/cluster.md), or --insecure / [cluster] insecure "
                          "= true if only trusted users can reach that network")], result.output
        result = run("merge", data / "capture", "-o", tmp_path / "hdr", "--scheduler", given, "--insecure", ok=False)
        assert tried == [address] and "no Dask scheduler answered" in result.output
        tried.clear()
    (tmp_path / "rig.toml").write_text(RIG + '\n[cluster]\nscheduler = "tcp://10.255.255.1:8786"\ninsecure = true\n')
    result = run("run", tmp_path / "rig.toml", "-w", tmp_path / "ws", ok=False)
    assert tried == ["tcp://10.255.255.1:8786"] and "no Dask scheduler answered" in result.output
    tried.clear()
    for address in ("tcp://127.0.0.1:1", "tcp://localhost:1", "tcp://[::1]:1"):
        run("merge", data / "capture", "-o", tmp_path / "hdr", "--scheduler", address, ok=False)
    assert tried == ["tcp://127.0.0.1:1", "tcp://localhost:1", "tcp://[::1]:1"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.toml"]


def test_a_scheduler_file_that_is_missing_or_not_one_is_one_line(data, tmp_path, monkeypatch):
    import ilt.parallel.cluster

    monkeypatch.setattr(ilt.parallel.cluster, "CONNECT_TIMEOUT", 0.2)
    (tmp_path / "empty.json").write_text("{}")
    for name, says in [("none.json", "no scheduler file within 0.2 s ('dask scheduler --scheduler-file "),
                       ("empty.json", 'not a Dask scheduler file (JSON with the scheduler\'s "address")')]:
        result = run("centroids", data / "hdr", "-o", tmp_path / "spots", "--scheduler-file", tmp_path / name, ok=False)
        lines = result.output.strip().splitlines()
        assert result.exit_code == 1 and lines == [lines[0]], result.output
        assert lines[0].startswith(f"ilt: error: {tmp_path / name}: {says}"), result.output
    result = run("centroids", data / "hdr", "--scheduler", "local", "--scheduler-file", "s.json", ok=False)
    assert result.exit_code == 2 and "give --scheduler or --scheduler-file, not both" in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.json"]


def test_scheduler_local_listens_on_loopback_only():
    """Every port `--scheduler local` opens (the scheduler and its dashboard in this
    process, the nanny and the worker in theirs) is on 127.0.0.1: a worker, too, runs
    the functions it is sent."""
    import psutil

    from ilt.parallel.cluster import executor_for

    def listening() -> set:
        me = psutil.Process()
        return {(p.pid, c.laddr) for p in (me, *me.children(recursive=True))
                for c in p.net_connections(kind="inet") if c.status == psutil.CONN_LISTEN}

    before = listening()
    with executor_for("local", 1) as ex:
        opened = listening() - before
        [worker] = ex.client.run(os.getpid).values()
    assert {pid for pid, _ in opened} >= {os.getpid(), worker}
    assert len(opened) >= 4 and {addr.ip for _, addr in opened} == {"127.0.0.1"}, opened


# ------------------------------------------------------------ the compressed solver's blocks on the cluster


@pytest.fixture(scope="module")
def kernel_T(tmp_path_factory):
    """The cube-corner kernel ISF of m = 768 points, memory-mapped from its T.npy, and
    the points' 3-D positions."""
    from ilt.sim.kernel import corner_kernel_isf, corner_points

    path = tmp_path_factory.mktemp("kernel") / "T.npy"
    return corner_kernel_isf(path, 16), corner_points(16)[0]


def test_compressed_on_a_cluster_equals_this_process(kernel_T, local_cluster):
    """The blocks and leaves compressed as tasks on the cluster's workers, from T's
    file, give the operator bit for bit as threads of this process do with T in
    memory: the same ranks, T1 and solves (every block draws from its own generator
    and runs on one BLAS thread either way)."""
    import numpy as np

    from ilt.parallel.cluster import executor_for
    from ilt.transport.compressed import compressed_operator

    T, points = kernel_T
    here = compressed_operator(np.array(T), points=points, leaf=32)
    with executor_for(local_cluster) as ex:
        there = compressed_operator(T, points=points, leaf=32, executor=ex)
        assert ex.worker_threads() == 2
    assert there.root.ranks_by_level() == here.root.ranks_by_level()
    assert len(here.root.ranks_by_level()) == 5   # 768 -> 384 -> ... -> leaves of 24; 4 tasks on 2 workers
    assert np.array_equal(there.t1_unit, here.t1_unit)
    b = np.random.default_rng(0).standard_normal((T.shape[0], 2))
    assert np.array_equal(there.solve(b), here.solve(b))
    assert there.residual == here.residual and there.residual <= there.allowance


def test_compressed_on_a_cluster_from_t_in_memory_runs_here(kernel_T, local_cluster, caplog):
    """A T that is not a file the workers can map (changed in memory) is compressed in
    this process, with an INFO line saying so (nothing for the user to do), to the same operator."""
    import numpy as np

    from ilt.parallel.cluster import executor_for
    from ilt.transport.compressed import compressed_operator

    T, points = kernel_T
    with executor_for(local_cluster) as ex, caplog.at_level(logging.INFO, logger="ilt.transport.compressed"):
        op = compressed_operator(np.array(T), points=points, leaf=32, executor=ex)
    assert "not a memory-mapped .npy file" in caplog.text
    assert np.array_equal(op.t1_unit, compressed_operator(T, points=points, leaf=32).t1_unit)


def test_a_t_a_worker_cannot_map_names_the_file_and_the_worker(kernel_T, local_cluster, tmp_path, monkeypatch):
    """A worker that does not find T's file (no shared storage there, here: a copy of T
    removed after it was mapped) fails the build in one OSError naming the file and the
    worker."""
    import numpy as np

    import ilt.transport.compressed as compressed
    from ilt.parallel.cluster import WorkerOSError, executor_for

    path = tmp_path / "T.npy"
    np.save(path, kernel_T[0])
    T = np.load(path, mmap_mode="r")
    found = compressed.mapped_file(T)
    path.unlink()    # this process keeps its map; the workers look for the file
    monkeypatch.setattr(compressed, "mapped_file", lambda array: found)
    with executor_for(local_cluster) as ex:
        workers = set(ex.client.scheduler_info()["workers"])
        with pytest.raises(WorkerOSError) as info:
            compressed.compressed_operator(T, leaf=32, executor=ex)
    message = str(info.value)
    assert "\n" not in message and str(path) in message and "No such file" in message
    assert any(f"on the Dask worker {w}" in message for w in workers), message


def test_decompose_with_a_scheduler_writes_the_same_bounces(kernel_T, local_cluster, tmp_path):
    """`ilt decompose --solver compressed --scheduler ADDRESS` on a T.npy writes the
    bounces and residual byte for byte as without a scheduler."""
    import numpy as np

    T, _ = kernel_T
    photo = tmp_path / "photo.npy"
    np.save(photo, np.random.default_rng(4).uniform(size=(T.shape[0], 2)))
    common = ["decompose", photo, "--isf", T.filename, "--solver", "compressed", "--no-cache", "--bounces", 3]
    run(*common, "-o", tmp_path / "here")
    run(*common, "-o", tmp_path / "there", "--scheduler", local_cluster)
    for name in ("bounces.npy", "residual.npy"):
        assert fingerprint_file(tmp_path / "there" / "photo" / name) == \
            fingerprint_file(tmp_path / "here" / "photo" / name)


def test_a_cancelled_chunk_s_late_failure_is_not_logged_again():
    """After a stage fails on one chunk, ilt cancels the others; distributed then sets a
    cancelled chunk's failure on its concurrent future without checking, and tornado
    logged the InvalidStateError with a traceback: a second message after ilt's one line
    (about one run in five of the worker-without-storage test above). Driven here with
    distributed's own _cascade_future on a cancelled future: logged without the filter,
    not with it."""
    import asyncio
    import concurrent.futures as cf
    import logging

    from distributed.cfexecutor import _cascade_future
    from tornado.ioloop import IOLoop

    from ilt.parallel.cluster import _CancelledCascade, _quiet_dask

    class FailedTask:   # what a Dask future of a failed task gives _cascade_future
        status = "error"

        async def _result(self, raiseit=False):
            try:
                raise ValueError("beam 4: a bad frame")
            except ValueError as exc:
                return type(exc), exc, exc.__traceback__

    records = []

    class Keep(logging.Handler):
        def emit(self, record):
            records.append(record)

    tornado = logging.getLogger("tornado.application")
    handler = Keep()
    tornado.addHandler(handler)
    saved = [f for f in tornado.filters if isinstance(f, _CancelledCascade)]
    for f in saved:
        tornado.removeFilter(f)

    async def cascade():
        future = cf.Future()
        future.cancel()
        IOLoop.current().add_callback(_cascade_future, FailedTask(), future)
        await asyncio.sleep(0.2)

    try:
        asyncio.run(cascade())
        assert len(records) == 1 and isinstance(records[0].exc_info[1], cf.InvalidStateError)
        records.clear()
        _quiet_dask()
        asyncio.run(cascade())
        assert records == []
    finally:
        tornado.removeHandler(handler)


def test_a_scheduler_without_workers_says_the_stages_wait(caplog):
    """A scheduler no worker has joined yet: the stages would wait silently; the warning
    says so and how to start one."""
    from ilt.parallel.cluster import executor_for

    with distributed.LocalCluster(n_workers=0, processes=True, host="127.0.0.1", dashboard_address="127.0.0.1:0",
                                  silence_logs=50) as cluster:
        with caplog.at_level(logging.WARNING, logger="ilt.parallel"), executor_for(cluster.scheduler_address) as ex:
            assert ex is not None
    assert "has no workers yet: the stages wait for some ('dask worker" in caplog.text
