"""Helpers shared by the benchmark scripts: warm timing, the paper's training matrix, rows."""

from __future__ import annotations

import os
import runpy
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from vpr_jax.data.synthetic import synthetic_route


def timed(fn, repeats: int) -> tuple[float, float]:
    """(first call seconds, median of ``repeats`` further calls); 0 repeats: first only."""
    import jax  # here: the peers' processes (peers.py) build the data without loading JAX

    start = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - start
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - start)
    return first, statistics.median(runs) if runs else first


def run_script(script: Path, argv: list[str]) -> int | str:
    """``python SCRIPT ARGV`` as its ``__main__`` in this process (a ``--tiny`` run, whose
    fresh interpreter would pay JAX's import and its compilations again, most of the run):
    its exit code (0, or what it exited with)."""
    saved, sys.argv = sys.argv, [str(script), *argv]
    try:
        runpy.run_path(str(script), run_name="__main__")
    except SystemExit as stop:
        return stop.code or 0
    finally:
        sys.argv = saved
    return 0


def cpu_name() -> str:
    """The CPU a figure was measured on, as /proc/cpuinfo names it, with its family and
    model (one name covers several boxes: an Intel Xeon reads "Intel(R) Xeon(R)
    Processor") and the cores this process may use; "unknown CPU" where there is no
    /proc/cpuinfo."""
    fields = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                fields.setdefault(key.strip(), value.strip())
    except OSError:
        return "unknown CPU"
    name = fields.get("model name", "unknown CPU")
    family, model = fields.get("cpu family"), fields.get("model")
    kind = f" (family {family} model {model})" if family and model else ""
    return f"{name}{kind}, {len(os.sched_getaffinity(0))} cores"


def timed_alternately(fns, repeats: int) -> list[float]:
    """The median warm seconds of each of ``fns``, called in turn ``repeats`` times after a
    first call each: alternating, so the box's drift from minute to minute (10-50% here)
    falls on every one alike."""
    import jax

    for fn in fns:
        jax.block_until_ready(fn())
    runs = [[] for _ in fns]
    for _ in range(max(repeats, 1)):
        for fn, out in zip(fns, runs, strict=True):
            start = time.perf_counter()
            jax.block_until_ready(fn())
            out.append(time.perf_counter() - start)
    return [statistics.median(r) for r in runs]


# ``--tiny``, in every script: a run of seconds that exercises the whole script for the
# tests (tests/test_benchmark_scripts.py), on data too small for its figures to mean anything.
TINY_HELP = "a seconds-long run for the tests: sizes shrink, the figures mean nothing"
PAPER_SIZES = {"n_train": 2500, "gap": 100, "n_test": 3569, "pixel_step": 1}  # the paper's
# 300 training images, 100 queries x 100 database, every 8th pixel (256 values: a
# covariance's eigendecomposition takes milliseconds, not the seconds of 2,048 x 2,048).
TINY_SIZES = {"n_train": 150, "gap": 10, "n_test": 100, "pixel_step": 8}
ICA_COMPONENTS, TINY_ICA_COMPONENTS = 256, 8  # FastICA's components in run_all and peers


def ica_components(tiny: bool) -> int:
    return TINY_ICA_COMPONENTS if tiny else ICA_COMPONENTS


def route_sizes(tiny: bool, images: bool = False) -> dict[str, int]:
    """``paper_route``'s keyword arguments: the paper's sizes, or ``--tiny``'s; ``images``:
    whole images (every pixel), for the auto-encoders."""
    sizes = dict(TINY_SIZES if tiny else PAPER_SIZES)
    if images:
        sizes["pixel_step"] = 1
    return sizes


def paper_route(n_train: int = 2500, gap: int = 100, n_test: int = 3569, pixel_step: int = 1):
    """Summer and fall of the built-in route: the paper's training and test sizes by default
    (``route_sizes``); ``pixel_step``: every this-many-th value of each flattened image.

    Returns (train (2 n_train, 2048): both seasons' training places, database (n_test,
    2048) summer, queries (n_test, 2048) fall), float32 in [0, 1] (2,048 / ``pixel_step``
    values an image).
    """
    route = synthetic_route(n_train + gap + n_test, ("summer", "fall"), seed=0)
    summer, fall = route.images["summer"], route.images["fall"]
    train = np.concatenate([summer[:n_train], fall[:n_train]]).reshape(2 * n_train, -1)
    db, query = (x[n_train + gap :].reshape(n_test, -1) for x in (summer, fall))
    if pixel_step == 1:
        return train, db, query
    return tuple(np.ascontiguousarray(x[:, ::pixel_step]) for x in (train, db, query))


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


def sweep_in_fresh_process(
    args: list[str], logdir: Path, timeout: float | None = None, fresh: bool = True
):
    """``python -m experiments.sweep ARGS`` into ``logdir`` (checkpoints beside it), in a
    fresh process: (wall seconds, peak RSS bytes). Exits with the sweep's stderr on failure.
    ``fresh=False`` (``--tiny`` runs, whose figures mean nothing): its ``main`` in this
    process, its output kept back, and this process's peak RSS."""
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
    if not fresh:
        return _sweep_here(cmd[3:], start)
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


def _sweep_here(argv: list[str], start: float) -> tuple[float, int]:
    import contextlib
    import io
    import resource

    from experiments import sweep

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = sweep.main(argv)
    if code:
        print(err.getvalue()[-3000:], file=sys.stderr)
        raise SystemExit(f"{' '.join(argv)} failed (exit {code})")
    wall = time.perf_counter() - start
    return wall, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
