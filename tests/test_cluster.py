"""A sweep's fits over a Ray cluster (``cluster.address``): a real two-node cluster
(``ray.cluster_utils.Cluster``, started once and shut down even when a check fails) gives
results.csv the one-process run's rows in every non-timing column, and a user's method that
fails there is the same one line as in one process. An address where nothing answers, Ray
missing and two ways to use several machines at once are one line each, nothing written."""

import csv
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from tests.conftest import (
    PROCESS_TIMEOUT_S,
    assert_one_line_error,
    one_ray_at_a_time,
    run_here,
    started,
)

ROUTE = [
    "data.n_frames=240",
    "split.n_train=100",
    "split.n_test=50",
    "split.gap=10",
    "season_pairs=summer-fall",
]
ARGS = [
    *ROUTE,
    "methods=[raw,pca,ica,lda,fae]",
    "removed_pcs=[0,5]",
    "ica.n_components=8",
    "fae.hidden=16",
    "fae.epochs=2",
    "fae.objective=[reconstruct]",
]
TIMING = {"fit_seconds", "encode_ms_per_image"}
BROKEN = """
class broken:
    @staticmethod
    def fit(train, aligned, key):
        raise RuntimeError("deliberately broken")

    @staticmethod
    def encode(state, images):
        return images
"""


def _rows(logdir) -> dict[str, dict]:
    with open(logdir / "results.csv", newline="") as f:
        return {row["run"]: row for row in csv.DictReader(f)}


@pytest.fixture(scope="module")
def two_nodes(tmp_path_factory):
    """A head and a second node of one CPU each, started once for this module's tests (a
    start costs seconds); its workers import the user's module folder ``mine`` as a user's
    would (PYTHONPATH). Shut down however the tests end."""
    from ray.cluster_utils import Cluster

    mine = tmp_path_factory.mktemp("mine")
    (mine / "broken_methods.py").write_text(textwrap.dedent(BROKEN))
    with one_ray_at_a_time(tmp_path_factory), pytest.MonkeyPatch.context() as env:
        env.setenv("PYTHONPATH", f"{mine}:{sys.path[0]}")
        env.setenv("RAY_USAGE_STATS_ENABLED", "0")  # nothing sent off this machine
        head = {"num_cpus": 1, "include_dashboard": False}  # nothing here reads it
        cluster = Cluster(initialize_head=True, head_node_args=head)
        try:
            cluster.add_node(num_cpus=1)
            cluster.wait_for_nodes()
            yield cluster, mine
        finally:
            cluster.shutdown()


def test_a_two_node_cluster_gives_the_one_process_rows(two_nodes, tmp_path):
    cluster, mine = two_nodes
    alone = run_here(*ARGS, f"logdir={tmp_path / 'alone'}")
    assert alone.returncode == 0, alone.stderr[-2000:]
    # threads=share: each worker held to its node's share of the cores before its JAX
    # starts (Ray's setup hook, sent by value): here a node's CPU is both cores, so its
    # JAX takes both, and the numbers are the one process's.
    spread = run_here(
        *ARGS,
        f"logdir={tmp_path / 'spread'}",
        f"cluster.address={cluster.address}",
        "cluster.threads=share",
    )
    assert spread.returncode == 0, spread.stderr[-2000:]
    one, many = _rows(tmp_path / "alone"), _rows(tmp_path / "spread")
    assert set(one) == set(many) and len(one) == 7  # raw, pca and ica at 2 counts, lda, fae
    for run, row in one.items():
        for column in set(row) - TIMING:
            assert many[run][column] == row[column], (run, column)
    log = (tmp_path / "spread" / "sweep.log").read_text()
    assert "cluster: " in log and "2 node(s)" in log
    every = ",".join(map(str, sorted(os.sched_getaffinity(0))))
    assert re.search(rf"fitted on node \S+ \(cores {every}\) in ", log), log
    # Every fitted state reached the driver's checkpoint folder, every run its logdir.
    folders = sorted(
        p.name for p in (tmp_path / "checkpoints" / "spread" / "summer-fall").iterdir()
    )
    assert folders == sorted(
        p.name for p in (tmp_path / "checkpoints" / "alone" / "summer-fall").iterdir()
    )
    for run in one:
        assert (tmp_path / "spread" / run / "curve.npz").is_file(), run
    # A user's method that fails on a worker: the one line it is in one process.
    broken = run_here(
        *ROUTE,
        "methods=[raw,broken_methods:broken]",
        f"logdir={tmp_path / 'broken'}",
        f"cluster.address={cluster.address}",
        path=[mine],
    )
    assert_one_line_error(broken, "method broken", "deliberately broken", "rerun the same command")


def test_every_thread_of_a_pinned_worker_is_held_to_its_core(two_nodes):
    """JAX's pool, BLAS's and Ray's threads exist before a worker pins itself: all of them
    are held to its core, while JAX keeps the width of the whole node."""
    import ray

    cluster, _ = two_nodes
    first = min(os.sched_getaffinity(0))

    def threads_allowed():  # on a worker (defined here: Ray sends it by value)
        from experiments import cluster_worker

        cluster_worker.start()
        allowed = set()
        for task in os.listdir("/proc/self/task"):
            with open(f"/proc/self/task/{task}/status") as f:
                allowed |= {line.split()[1] for line in f if line.startswith("Cpus_allowed_list:")}
        return cluster_worker.cores(), cluster_worker.width(), allowed

    ray.init(address=cluster.address, logging_level="WARNING", log_to_driver=False)
    try:
        env = {"env_vars": {"VPR_JAX_CORES_PER_WORKER": "1"}}
        probe = ray.remote(num_cpus=1)(threads_allowed).options(runtime_env=env)
        for cores, width, allowed in ray.get([probe.remote() for _ in range(2)], timeout=120):
            assert cores == (first,) and allowed == {str(first)}, (cores, allowed)
            assert width == len(os.sched_getaffinity(0))
    finally:
        ray.shutdown()


def test_an_address_where_nothing_answers_is_one_line_and_nothing_written(tmp_path):
    import socket

    with socket.socket() as s:  # a port of this machine that nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    logdir = tmp_path / "runs"
    proc = run_here(
        *ROUTE, "methods=[raw]", f"logdir={logdir}", f"cluster.address=127.0.0.1:{port}"
    )
    assert_one_line_error(proc, f"cluster.address=127.0.0.1:{port}", "ray start --head")
    assert not logdir.exists()


def test_ray_missing_is_one_line_naming_the_install(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # as if it were not installed
    logdir = tmp_path / "runs"
    proc = run_here(*ROUTE, "methods=[raw]", f"logdir={logdir}", "cluster.address=local")
    assert_one_line_error(proc, "needs Ray", '.[cluster]"')
    assert not logdir.exists()


def test_a_cluster_and_distributed_jax_at_once_are_refused(tmp_path):
    logdir = tmp_path / "runs"
    proc = run_here(
        *ROUTE,
        "methods=[raw]",
        f"logdir={logdir}",
        "cluster.address=local",
        "mesh.distributed=true",
    )
    assert_one_line_error(proc, "cluster.address and mesh.distributed=true", "not both")
    assert not logdir.exists()


def _fit_tasks() -> list[int]:
    """The process ids of Ray workers running a fit on this machine (``ray::_fit_task``)."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            if entry.name.isdigit() and (entry / "cmdline").read_bytes().startswith(
                b"ray::_fit_task"
            ):
                found.append(int(entry.name))
        except OSError:
            continue
    return found


@pytest.mark.slow
def test_a_worker_killed_mid_fit_costs_a_retry_not_a_row(two_nodes, tmp_path):
    """Opt-in (``-m slow``, about a minute): a busy worker SIGKILLed while the sweep runs;
    Ray runs its fit again and results.csv holds the one-process rows, each cell once."""
    cluster, _ = two_nodes
    args = [*ARGS, "fae.epochs=12", "fae.hidden=64", "fae.patience=20"]
    alone = run_here(*args, f"logdir={tmp_path / 'alone'}")
    assert alone.returncode == 0, alone.stderr[-2000:]
    command = [sys.executable, "-m", "experiments.sweep", *args]
    command += [f"logdir={tmp_path / 'spread'}", f"cluster.address={cluster.address}"]
    command += [f"train.checkpoint_dir={tmp_path / 'checkpoints'}"]
    with started(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE) as proc:
        killed = None
        while killed is None and proc.poll() is None:
            busy = _fit_tasks()
            if busy:
                time.sleep(1.0)  # well into its fit
                os.kill(busy[0], signal.SIGKILL)
                killed = busy[0]
            time.sleep(0.2)
        out, err = proc.communicate(timeout=PROCESS_TIMEOUT_S)
    assert killed is not None and proc.returncode == 0, err[-3000:]
    one, many = _rows(tmp_path / "alone"), _rows(tmp_path / "spread")
    runs = [r["run"] for r in csv.DictReader(open(tmp_path / "spread" / "results.csv"))]
    assert sorted(runs) == sorted(one)  # each cell once
    for run, row in one.items():
        for column in set(row) - TIMING:
            assert many[run][column] == row[column], (run, column)
