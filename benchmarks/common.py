"""Helpers shared by the benchmark scripts: warm timing, the seed's training matrix, rows."""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np

from vpr_jax.data.synthetic import synthetic_route


def timed(fn, repeats: int) -> tuple[float, float]:
    """(first call seconds, median of ``repeats`` further calls); 0 repeats: first only."""
    start = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - start
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - start)
    return first, statistics.median(runs) if runs else first


def seed_route(n_train: int = 2500, gap: int = 100, n_test: int = 3569):
    """Summer and fall of the built-in route: the seed's training and test sizes.

    Returns (train (2 n_train, 2048): both seasons' training places, database (n_test,
    2048) summer, queries (n_test, 2048) fall), float32 in [0, 1].
    """
    route = synthetic_route(n_train + gap + n_test, ("summer", "fall"), seed=0)
    summer, fall = route.images["summer"], route.images["fall"]
    train = np.concatenate([summer[:n_train], fall[:n_train]]).reshape(2 * n_train, -1)
    return (
        train,
        summer[n_train + gap :].reshape(n_test, -1),
        fall[n_train + gap :].reshape(n_test, -1),
    )


def ratio_row(name: str, ours: float, peer: float, peer_name: str, goal: str) -> None:
    print(
        f"{name:<34} {ours:9.4f} s  {peer_name:<30} {peer:9.4f} s  "
        f"ratio {ours / peer:5.2f}x  (goal {goal})"
    )


REPO = Path(__file__).resolve().parent.parent
# Runs argv[1:] and prints that child's peak RSS in bytes as its last line (Linux ru_maxrss
# is KiB): the benchmark's own process holds arrays of its own, so a fresh one is measured.
_PEAK_RSS_WRAPPER = (
    "import resource, subprocess, sys; rc = subprocess.call(sys.argv[1:]); "
    "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024); sys.exit(rc)"
)


def sweep_in_fresh_process(args: list[str], logdir: Path, timeout: float | None = None):
    """``python -m experiments.sweep ARGS`` into ``logdir`` (checkpoints beside it), in a
    fresh process: (wall seconds, peak RSS bytes). Exits with the sweep's stderr on failure."""
    cmd = [
        sys.executable,
        "-m",
        "experiments.sweep",
        *args,
        f"logdir={logdir}",
        f"train.checkpoint_dir={logdir.parent / 'checkpoints'}",
    ]
    print(f"  running: {' '.join(cmd[1:])}", flush=True)
    start = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-c", _PEAK_RSS_WRAPPER, *cmd],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        print(proc.stderr[-3000:], file=sys.stderr)
        raise SystemExit(f"{' '.join(args)} failed (exit {proc.returncode})")
    return wall, int(proc.stdout.strip().splitlines()[-1])
