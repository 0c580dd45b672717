"""Nothing lost, nothing silent: a run killed mid-training resumes to the uninterrupted
result, and the same seed gives the same table."""

import os
import shlex
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import (
    SMALL,
    assert_one_line_error,
    env_with_repo,
    private_xla_cache,
    read_run,
    run_cli,
    run_here,
    run_process,
    started,
    sweep_rows,
)
from vpr_jax import load_encoder
from vpr_jax.evaluation.metrics import SCALAR_NAMES
from vpr_jax.outputs.results import read_results

METRICS = (*SCALAR_NAMES, "n_iter", "converged", "stopped_early")
# Two pairs, raw pixels and an FAE trained 6 epochs on the cross_season objective (pairs of
# aligned places), checkpointed after every epoch.
KILLABLE = [
    "data.n_frames=400",
    "split.n_train=100",
    "split.n_test=60",
    "split.gap=10",
    "methods=[raw,fae]",
    "season_pairs=summer-fall,spring-fall",
    "fae.hidden=32",
    "fae.objective=cross_season",
    "fae.epochs=6",
    "train.batch_size=16",
    "train.patience=10",
    "train.checkpoint_every_s=0",
]


def _cells(rows: list[dict]) -> dict:
    key = lambda r: (r.season_pair, r.method, r.objective, r.removed_pcs)  # noqa: E731
    keys = [key(r) for r in rows]
    assert len(keys) == len(set(keys)), "a cell was written twice"
    return {key(r): {m: getattr(r, m) for m in METRICS} for r in rows}


# ``python -m experiments.sweep ARGS`` with Ctrl-C raising KeyboardInterrupt as in a terminal,
# also where the test runner was started with SIGINT ignored (a background job of a script).
AS_IN_A_TERMINAL = (
    "import runpy, signal, sys; "
    "signal.signal(signal.SIGINT, signal.default_int_handler); "
    "sys.argv[0] = 'experiments.sweep'; "
    "runpy.run_module('experiments.sweep', run_name='__main__', alter_sys=True)"
)


def _signal_during(line_part: str, args: list[str], tmp_path: Path, sig=signal.SIGKILL):
    """Start the sweep, send it ``sig`` once a line containing ``line_part`` is printed;
    returns (exit code, stdout up to there, stderr)."""
    pipes = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE}
    env = env_with_repo(**private_xla_cache(tmp_path))
    with started([sys.executable, "-c", AS_IN_A_TERMINAL, *args], env=env, **pipes) as proc:
        seen = []
        for line in proc.stdout:
            seen.append(line)
            if line_part in line:
                proc.send_signal(sig)
                break
        seen.extend(proc.stdout)
        err = proc.stderr.read()
        proc.wait()
    return proc.returncode, "".join(seen), err


def test_sigkill_in_autoencoder_training_resumes_to_the_uninterrupted_result(tmp_path):
    """The killed sweep is a process of its own; the uninterrupted one and the resume run in
    this process (what is compared is the files they leave)."""
    whole, _ = sweep_rows(*KILLABLE, f"logdir={tmp_path / 'whole' / 'runs'}")

    logdir, ck = tmp_path / "cut" / "runs", tmp_path / "cut" / "checkpoints"
    args = [*KILLABLE, f"logdir={logdir}", f"train.checkpoint_dir={ck}"]
    code, printed, _ = _signal_during("spring-fall fae_cross_season epoch 3/6", args, tmp_path)
    assert code == -signal.SIGKILL, printed[-2000:]
    assert "summer-fall fae cross_season:" in printed  # the first pair was done before the kill
    rows_at_kill = read_results(logdir / "results.csv")
    assert 0 < len(rows_at_kill) < 4

    rows, again = sweep_rows(*args)
    assert "resuming: 3 of 4 cells" in again.stdout
    # The kill may land before or during epoch 3's save: training resumes after 2 or 3.
    assert "spring-fall fae_cross_season: resuming after epoch" in again.stdout

    expected = _cells(whole)
    assert _cells(rows) == expected

    ea = read_run(logdir / "spring-fall" / "fae_cross_season_training")
    for tag in ("loss/train", "loss/validation"):
        steps = [e.step for e in ea.Scalars(tag)]
        assert len(steps) == len(set(steps)), f"{tag} has duplicated steps"
        assert steps == sorted(steps)
    assert len(ea.Scalars("loss/validation")) == 7  # the start and every epoch, none lost


def test_ctrl_c_saves_finished_cells_and_prints_the_resume_command(tmp_path):
    logdir, ck = tmp_path / "runs", tmp_path / "checkpoints"
    args = [*KILLABLE, f"logdir={logdir}", f"train.checkpoint_dir={ck}"]
    code, printed, err = _signal_during(
        "summer-fall fae_cross_season epoch 2/6", args, tmp_path, signal.SIGINT
    )
    assert code == 130, (printed[-2000:], err)
    assert "Traceback" not in err + printed
    (line,) = err.strip().splitlines()
    saved = f"interrupted: 1 finished cell(s) are saved in {logdir / 'results.csv'}; "
    assert line.startswith(saved + "resume with: python -m experiments.sweep "), line
    assert [r.method for r in read_results(logdir / "results.csv")] == ["raw"]

    command = shlex.split(line.split("resume with: ", 1)[1])
    assert command[:3] == ["python", "-m", "experiments.sweep"]
    rows, again = sweep_rows(*command[3:])  # its arguments, run in this process
    assert "resuming: 1 of 4 cells" in again.stdout
    assert "summer-fall fae_cross_season: resuming after epoch" in again.stdout
    assert len(_cells(rows)) == 4


def test_sigterm_stops_like_ctrl_c(tmp_path):
    args = [
        *KILLABLE,
        f"logdir={tmp_path / 'runs'}",
        f"train.checkpoint_dir={tmp_path / 'checkpoints'}",
    ]
    code, printed, err = _signal_during(
        "summer-fall fae_cross_season epoch 2/6", args, tmp_path, signal.SIGTERM
    )
    assert code == 128 + signal.SIGTERM, (printed[-2000:], err)
    (line,) = err.strip().splitlines()
    assert line.startswith("interrupted: 1 finished cell(s) are saved in "), line


def test_the_same_seed_gives_the_same_table(small_sweep, tmp_path):
    """One pair of the small sweep again, every method: the same cells to the last digit
    (a pair's fits depend on the seed and its own images only)."""
    first, _ = small_sweep
    rows, _ = sweep_rows(*SMALL, "season_pairs=spring-fall", f"logdir={tmp_path / 'runs'}")
    again = _cells(rows)
    whole = _cells(read_results(first / "results.csv"))
    assert len(again) == 15 and again == {k: v for k, v in whole.items() if k[0] == "spring-fall"}


def test_another_seed_gives_another_route_and_other_initial_weights(small_sweep, tmp_path):
    first, _ = small_sweep
    rows, _ = sweep_rows(
        *SMALL,
        "seed=1",
        "season_pairs=summer-fall",
        "methods=[raw,fae]",
        f"logdir={tmp_path / 'runs'}",
    )
    other = _cells(rows)
    same_seed = _cells(read_results(first / "results.csv"))
    key = ("summer-fall", "raw", "", 0)
    assert other[key] != same_seed[key]  # raw pixels: only the route can differ
    # The FAE's weights: (tiny FAEs can collapse to the same chance-level metrics).
    _, seed_0 = load_encoder(first.parent / "checkpoints" / "runs" / "summer-fall" / "fae")
    _, seed_1 = load_encoder(tmp_path / "checkpoints" / "runs" / "summer-fall" / "fae")
    assert not np.allclose(seed_0.params["encoder"]["kernel"], seed_1.params["encoder"]["kernel"])


HOLD_LOCK = (
    "import sys, time; from vpr_jax.outputs.logdir import lock_logdir; "
    "lock_logdir(__import__('pathlib').Path(sys.argv[1])); print('held', flush=True); "
    "time.sleep(600)"
)


def test_one_sweep_per_logdir_and_the_lock_dies_with_its_holder(tmp_path):
    logdir = tmp_path / "runs"
    args = [*SMALL, "methods=[raw]", "season_pairs=summer-fall", f"logdir={logdir}"]
    # A process of its own: a sweep in this process would hold the lock until the test
    # runner exits (the kernel drops it when its holder ends), and the holder below could
    # not take it. The refused and the third sweep run here.
    assert run_cli(*args).returncode == 0
    assert not (logdir / ".incomplete").exists()  # a finished sweep leaves nothing behind
    before = (logdir / "results.csv").read_bytes()
    # Leaving the block SIGKILLs the holder.
    with started([sys.executable, "-c", HOLD_LOCK, str(logdir)], stdout=subprocess.PIPE) as holder:
        assert holder.stdout.readline().strip() == "held"
        second = run_here(*args, "removed_pcs=[0,5]", "methods=[raw,pca]")
        words = ("in use by another sweep", f"pid {holder.pid}", "another logdir=PATH")
        assert_one_line_error(second, *words)
        assert (logdir / "results.csv").read_bytes() == before  # nothing touched
    # SIGKILL leaves no stale lock: the same command now runs and adds its cells once.
    rows, _ = sweep_rows(*args, "removed_pcs=[0,5]", "methods=[raw,pca]")
    assert sorted((r.method, r.removed_pcs) for r in rows) == [("pca", 0), ("pca", 5), ("raw", 0)]
    assert not (logdir / ".incomplete").exists()


def test_logdirs_of_one_name_cannot_train_into_the_same_checkpoint_folder(tmp_path):
    """runs/a/quick and runs/b/quick both map to checkpoints/quick/...: while one trains a
    model the other stops with one line instead of writing the same checkpoints."""
    checkpoints = tmp_path / "checkpoints"
    args = [
        *SMALL,
        "methods=[fae]",
        "fae.objective=reconstruct",
        "season_pairs=summer-fall",
        "fae.epochs=1",
        f"train.checkpoint_dir={checkpoints}",
    ]
    model = checkpoints / "quick" / "summer-fall" / "fae" / "training"
    with started([sys.executable, "-c", HOLD_LOCK, str(model)], stdout=subprocess.PIPE) as holder:
        assert holder.stdout.readline().strip() == "held"
        proc = run_here(*args, f"logdir={tmp_path / 'b' / 'quick'}")
        words = (f"checkpoint folder {model} is in use by another sweep", f"pid {holder.pid}")
        assert_one_line_error(proc, *words)
    assert run_here(*args, f"logdir={tmp_path / 'b' / 'quick'}").returncode == 0


def test_a_disk_fault_mid_sweep_is_one_line_and_the_rerun_completes(tmp_path):
    logdir = tmp_path / "runs"
    args = [*SMALL, "methods=[raw,pca]", "removed_pcs=[0,5,20]", f"logdir={logdir}"]
    args.append(f"train.checkpoint_dir={tmp_path / 'checkpoints'}")  # not the repository's
    # A cell's TensorBoard run without basis images is ~42 KB, with them ~54 KB: the first
    # PCA cell that shows removed components cannot be written.
    proc = _limited(args, 48, tmp_path)  # files up to 48 KiB
    line = assert_one_line_error(
        proc, "File too large", str(logdir), "rerun the same command", returncode=1
    )
    saved = read_results(logdir / "results.csv")
    assert 1 <= len(saved) < 3 * 4 and f"{len(saved)} finished cell(s) are saved" in line
    rows, _ = sweep_rows(*args)  # the rerun, in this process
    assert (
        len(rows) == 3 * 4 and len({(r.season_pair, r.method, r.removed_pcs) for r in rows}) == 12
    )
    kept = {r.run: r for r in rows}
    for row in saved:  # the cells saved before the fault were not redone (only which row
        assert kept[row.run]._replace(selected=0) == row._replace(selected=0)  # is selected)
    assert not (logdir / ".incomplete").exists()
    for row in rows:  # every cell's run is whole: TensorBoard reads its metrics back
        assert read_run(logdir / row.run).Scalars("metrics/recall_at_1")


def _limited(args: list[str], kib: int, tmp_path: Path) -> subprocess.CompletedProcess:
    """The sweep with files limited to ``kib`` KiB: past it writes fail with EFBIG, as on a
    full disk, since the shell ignores SIGXFSZ for the sweep it starts. A shell, not
    preexec_fn: forking this JAX process could deadlock."""
    sweep = shlex.join([sys.executable, "-m", "experiments.sweep", *args])
    limited = f"ulimit -f {kib}; trap '' XFSZ; exec {sweep}"
    return run_process(["bash", "-c", limited], env=env_with_repo(**private_xla_cache(tmp_path)))


def test_a_checkpoint_that_cannot_be_written_is_one_line_and_the_rerun_completes(tmp_path):
    logdir, models = tmp_path / "runs", tmp_path / "models"
    args = [
        "data.n_frames=400",
        "split.n_train=150",
        "split.n_test=60",
        "split.gap=10",
        "methods=[raw,fae]",
        "season_pairs=summer-fall",
        "fae.objective=reconstruct",
        "fae.hidden=32",
        "fae.epochs=1",
        f"logdir={logdir}",
        f"train.checkpoint_dir={models}",
    ]
    # TensorBoard runs stay under 100 KiB; the FAE's optimizer state is a file of ~1.1 MB,
    # which orbax (TensorStore, in its own threads) fails to write.
    proc = _limited(args, 600, tmp_path)
    line = assert_one_line_error(
        proc, "File too large (EFBIG)", str(models), "rerun the same command", returncode=1
    )
    saved = read_results(logdir / "results.csv")
    assert [r.method for r in saved] == ["raw"] and "1 finished cell(s)" in line
    rows, _ = sweep_rows(*args)  # the rerun, in this process
    assert sorted(r.method for r in rows) == ["fae", "raw"]
    encode, params = load_encoder(models / "runs" / "summer-fall" / "fae")
    assert encode(params, np.zeros((2, 32, 64), np.float32)).shape[0] == 2


def test_a_full_disk_is_one_line_and_the_same_command_completes_once_space_is_freed(tmp_path):
    """A real full file system: a 400 KB tmpfs (root only), grown to 20 MB afterwards."""
    mount = tmp_path / "small_disk"
    mount.mkdir()
    if (
        os.geteuid() != 0
        or run_process(
            ["mount", "-t", "tmpfs", "-o", "size=400k", "tmpfs", str(mount)], timeout=60
        ).returncode
    ):
        pytest.skip("mounting a tmpfs needs root")
    try:
        args = [*SMALL, "methods=[raw,pca]", "removed_pcs=[0,5,20]", f"logdir={mount / 'runs'}"]
        proc = run_cli(*args)
        line = assert_one_line_error(proc, "No space left on device (ENOSPC)", returncode=1)
        saved = read_results(mount / "runs" / "results.csv")
        assert f"{len(saved)} finished cell(s) are saved" in line
        remount = run_process(["mount", "-o", "remount,size=20m", str(mount)], timeout=60)
        assert remount.returncode == 0, remount.stderr
        # A process of its own: one in this process would keep files on the mount open.
        rows, _ = sweep_rows(*args, run=run_cli)
        assert len(rows) == len({r.run for r in rows}) == 12
        assert not (mount / "runs" / ".incomplete").exists()
    finally:
        run_process(["umount", str(mount)], timeout=60)
