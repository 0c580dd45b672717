"""The same numbers on a device mesh: 8 virtual CPU devices, and two processes on loopback.

Virtual devices must exist before JAX starts, so every check runs in a fresh process
(``XLA_FLAGS=--xla_force_host_platform_device_count=N``) and is compared here with the
single-device run of the same code, or with numpy.
"""

import contextlib
import json
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import (
    REPO,
    assert_one_line_error,
    env_with_repo,
    numpy_cosine,
    run_here,
    run_process,
    shared_folder,
    started,
)
from vpr_jax.evaluation.metrics import SCALAR_NAMES
from vpr_jax.outputs.results import read_results

EIGHT = {"XLA_FLAGS": "--xla_force_host_platform_device_count=8"}
METRICS = SCALAR_NAMES


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run_checks(folder: Path) -> None:
    proc = run_process(
        [sys.executable, str(REPO / "tests" / "sharded_checks.py"), str(folder)],
        env=env_with_repo(**EIGHT),
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    (folder / "checks.json").write_text(proc.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def checks(tmp_path_factory):
    """The checks of sharded_checks.py on eight devices, and the sweep's answer there to a
    batch that does not split over them (its logdir in ``folder``): run once per session,
    whichever worker asks first."""
    folder = shared_folder(tmp_path_factory, "sharded_checks", _run_checks)
    return {**json.loads((folder / "checks.json").read_text()), "folder": folder}


def test_the_mesh_spans_eight_devices(checks):
    assert checks["devices"] == 8


def test_pca_with_samples_split_over_devices_equals_one_device(checks):
    assert checks["pca_components"] < 1e-4
    assert checks["pca_variance_rel"] < 1e-5
    assert checks["pca_mean"] < 1e-6


def test_the_sharded_fit_and_matcher_state_float32(checks):
    """The PCA scatter and the matcher split over devices: every product float32."""
    assert checks["sharded_products"] >= 3
    assert checks["sharded_unpinned"] == []


def test_matching_with_the_database_split_equals_one_device(checks):
    assert checks["match_same_indices"]
    assert checks["match_scores"] < 1e-6
    assert checks["match_tie_order"] == [3, 500, 900]  # ties: lowest database index first


@pytest.mark.parametrize("model", ["FAESpec", "CAESpec"])
def test_data_parallel_training_equals_one_device(checks, model):
    assert checks[f"{model}_param_devices"] == 8  # replicated over the mesh
    assert checks[f"{model}_grad_rel"] < 1e-5
    assert checks[f"{model}_params"] < 1e-5
    one, split = checks[f"{model}_val_loss"]
    assert split == pytest.approx(one, rel=1e-5)


def test_the_training_step_splits_each_batch(checks):
    assert 2 in checks["step_batch_shapes"]  # 16 images / 8 devices
    assert checks["step_all_reduces"] >= 1  # the gradients


def _same_rows(a: list[dict], b: list[dict]) -> None:
    """Same cells, same metrics: closed-form methods to rounding. Trained auto-encoders only
    closely: Adam turns rounding-level gradient differences of nearly dead units into whole
    steps (tests above check gradients and SGD fits to rounding)."""
    key = lambda r: (r.season_pair, r.method, r.objective, r.removed_pcs, r.seed)  # noqa: E731
    assert sorted(map(key, a)) == sorted(map(key, b))
    other = {key(r): r for r in b}
    for row in a:
        tol = 0.02 if row.method in ("fae", "cae") else 1e-6
        for metric in METRICS:
            expected = getattr(other[key(row)], metric)
            assert getattr(row, metric) == pytest.approx(expected, abs=tol), (key(row), metric)


def test_the_sweep_on_eight_devices_equals_the_single_device_sweep(small_sweep, checks):
    """One pair of the small sweep, run on the eight devices of sharded_checks.py's process
    (its methods that use them: ``EIGHT_DEVICE_SWEEP``)."""
    logdir, _ = small_sweep
    code, stdout, stderr = checks["eight"]
    assert code == 0, stderr[-3000:]
    assert "mesh: 8 cpu devices" in stdout
    single = [
        r
        for r in read_results(logdir / "results.csv")
        if r.season_pair == "summer-fall"
        and (r.method, r.objective)
        in {("raw", ""), ("pca", ""), ("diff_pca", ""), ("fae", "cross_season")}
    ]
    _same_rows(read_results(checks["folder"] / "eight" / "results.csv"), single)


def _run_together(commands: list[list[str]], logs: Path, **env: str) -> None:
    """Run cooperating processes to the end. One that fails would leave the others waiting
    in a collective for ever, so the rest are killed as soon as one exits non-zero (and all
    of them by ``started``'s watchdog if they hang)."""
    logs.mkdir(parents=True, exist_ok=True)
    with contextlib.ExitStack() as stack:
        procs = [
            stack.enter_context(
                started(
                    [sys.executable, *args],
                    env=env_with_repo(**env),
                    stdout=subprocess.DEVNULL,
                    stderr=stack.enter_context(open(logs / f"{i}.err", "w")),  # noqa: SIM115
                )
            )
            for i, args in enumerate(commands)
        ]
        while any(p.poll() is None for p in procs):
            if any(p.poll() not in (None, 0) for p in procs):
                break  # leaving the block kills the others
            time.sleep(0.2)
    report = "\n".join(
        f"process {i} exit {p.returncode}: {(logs / f'{i}.err').read_text()[-2000:]}"
        for i, p in enumerate(procs)
    )
    assert all(p.returncode == 0 for p in procs), report


def test_two_processes_on_loopback_compute_one_sharded_similarity(tmp_path):
    port, out = _free_port(), tmp_path / "matches.npz"
    worker = str(REPO / "tests" / "loopback_worker.py")
    _run_together([[worker, str(port), "2", str(i), str(out)] for i in range(2)], tmp_path / "logs")
    with np.load(out) as z:
        assert int(z["devices"]) == 4 and int(z["processes"]) == 2
        sim = numpy_cosine(z["query"], z["db"])
        order = np.argsort(-sim, axis=1, kind="stable")[:, :10]
        np.testing.assert_array_equal(z["indices"], order)
        np.testing.assert_allclose(z["scores"], np.take_along_axis(sim, order, 1), atol=1e-5)


def test_a_sweep_over_two_processes_equals_one_process_and_only_process_0_writes(
    cluster_benchmark,
):
    """benchmarks/cluster.py's run of two processes with ``mesh.distributed=true`` on
    loopback (a core and a device each; a tiny FAE trained on both among its fits) against
    its one-process run of the same sweep."""
    _, runs = cluster_benchmark
    one = read_results(runs / "one_process" / "results.csv")
    two = read_results(runs / "distributed" / "results.csv")
    _same_rows(two, one)
    assert len(two) == 9  # raw, pca at 2 counts, ica at 2 counts and fae, 2 seeds: written once
    assert (runs / "checkpoints" / "distributed" / "summer-fall" / "fae_seed1").is_dir()


def test_a_batch_that_does_not_split_over_the_devices_is_one_line(checks):
    """The sweep's ``main`` with train.batch_size=12, run on the eight devices of
    sharded_checks.py's process (virtual devices exist only in a process started with them)."""
    proc = subprocess.CompletedProcess(["experiments.sweep"], *checks["refusal"])
    # A cross_season step takes the batch as pairs of a place's two images: 16 for 8 devices.
    assert_one_line_error(proc, "fae.batch_size=12 (train.batch_size unless set)", "multiple of 16")
    assert not (checks["folder"] / "runs").exists()


def test_asking_for_more_devices_than_exist_is_one_line(tmp_path):
    proc = run_here("mesh.devices=64", f"logdir={tmp_path / 'runs'}")  # this process: 1 device
    assert_one_line_error(proc, "mesh.devices=64", "mesh.devices=0")
    assert not (tmp_path / "runs").exists()
