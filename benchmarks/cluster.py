"""A sweep's fits over a Ray cluster against one process and against jax.distributed.

    python benchmarks/cluster.py [--preset paper] [--route-seeds 0,1,2] [--warm-up]
                                 [--keep DIR] [--tiny]

Five runs of ``python -m experiments.sweep preset=paper`` on this machine, each in fresh
processes, wall time from start to exit:

1. one process with every core;
2. ``cluster.address=local`` with one worker on one core (``cluster.workers=1
   cluster.threads=share cluster.cores_per_worker=1``: its JAX and BLAS start there);
3. ``cluster.address=local`` with two workers, a core each (``cluster.threads=share``);
4. ``cluster.address=local`` with two workers as the sweep runs them by default
   (``cluster.threads=node``: each worker's JAX over every core, the one process's numbers);
5. today's way to use two processes, ``mesh.distributed=true`` on loopback, each process
   held to one core (both compute every fit together).

Ratios: two workers against one (3 over 2, goal: at least 1.7x) and against one process (3
and 4 over 1, goal: no slower, at least 1x). The compiled programs come from the suite's
compile cache: the first run of a preset on a machine compiles them, so ``--warm-up`` runs
the preset once untimed first (or run the benchmark after one sweep of the preset).

Projection: the one-worker run's sweep.log gives each fit's wall time on one core ("fitted on
node ... in S s"); what is not fitting (start, data, the pairs' shared PCA fits, report) is
the rest of its wall time, kept serial. N workers cannot finish sooner than that rest plus
the longer of the longest fit and the fits' total over N (the critical path), printed for N
= 4, 16 and 64 with a greedy schedule (longest fit first to the least busy worker) beside it.
The same for the whole route with seeds: ``preset=full seeds=[...]`` on two workers of a
core each (``threads=share``; its fits: raw, pca and ica per pair, ica once per seed; the
rest is its wall time less the greedy schedule of its fits on two workers).

``--tiny`` (for the tests): a 240-frame route with raw and pca and two seeds of ica and of
a tiny FAE, one pair; the two workers' share run stands for the one-worker and the default
runs too (the same code, other keys) and for both projections, and the one process's run
is the sweep's main in this process; the figures mean nothing. With ``--keep``, the tests
also compare the runs' results.csv (tests/test_sharding.py: the two processes' rows are
the one process's).
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import TINY_HELP, cpu_name, sweep_in_fresh_process

REPO = Path(__file__).resolve().parent.parent
TIMEOUT_S = 3 * 3600  # one sweep's run, at most (the tests' --tiny: their own limit)
WORKERS = (4, 16, 64)  # the projection's cluster sizes
TINY = [
    "data.n_frames=240",
    "split.n_train=100",
    "split.n_test=50",
    "split.gap=10",
    "season_pairs=summer-fall",
    "methods=[raw,pca,ica,fae]",
    "removed_pcs=[0,5]",
    "ica.n_components=8",
    "fae.hidden=16",
    "fae.epochs=2",
    "fae.objective=reconstruct",
    "train.batch_size=16",
    "seeds=[0,1]",
]
# a fit's line in sweep.log (experiments.cluster): pair, fit folder, seconds
FITTED = re.compile(
    r"^(\S+) (\S+): fitted on node \S+ \((?:cores [\d,]+|not pinned)\) in ([\d.]+) s"
)


def sweep(args: list[str], logdir: Path, *, cores: set[int] | None = None) -> float:
    """``python -m experiments.sweep ARGS logdir=...`` (checkpoints beside it) in a fresh
    process, held to ``cores`` if given: its wall seconds. Exits with its stderr if it fails."""
    return _together([[*args, f"logdir={logdir}"]], logdir, cores=[cores])


def _together(argvs, logdir: Path, *, cores) -> float:
    """Every sweep of ``argvs`` started at once (the same logdir's checkpoints), each held
    to its ``cores``: the wall seconds until the last ends."""
    checkpoints = f"train.checkpoint_dir={logdir.parent / 'checkpoints'}"
    print(f"  running: {' '.join(argvs[0])}", flush=True)
    start = time.perf_counter()
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "experiments.sweep", *argv, checkpoints],
            cwd=REPO,
            env={**os.environ, "PYTHONPATH": str(REPO)},
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            preexec_fn=(lambda c=c: os.sched_setaffinity(0, c)) if c else None,
        )
        for argv, c in zip(argvs, cores, strict=True)
    ]
    try:
        errors = [proc.communicate(timeout=TIMEOUT_S)[1] for proc in procs]
    finally:  # a run past its time (or Ctrl-C) leaves no sweep behind
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    wall = time.perf_counter() - start
    for proc, err in zip(procs, errors, strict=True):
        if proc.returncode != 0:
            print(err[-3000:], file=sys.stderr)
            raise SystemExit(f"{' '.join(argvs[0])} failed (exit {proc.returncode})")
    return wall


def distributed(args: list[str], logdir: Path, cores: list[int]) -> float:
    """Two processes with ``mesh.distributed=true`` on loopback, one core each."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    common = [*args, f"logdir={logdir}", "mesh.distributed=true", "mesh.num_processes=2"]
    common.append(f"mesh.coordinator=127.0.0.1:{port}")
    argvs = [[*common, f"mesh.process_id={i}"] for i in range(2)]
    return _together(argvs, logdir, cores=[{c} for c in cores])


def fit_seconds(logdir: Path) -> list[float]:
    """Each fit's wall time on its worker, from the cluster run's sweep.log."""
    lines = (logdir / "sweep.log").read_text().splitlines()
    times = [float(m.group(3)) for line in lines if (m := FITTED.match(line))]
    if not times:
        raise SystemExit(f"{logdir / 'sweep.log'} names no fitted fit: not a cluster run?")
    return times


def greedy(times: list[float], workers: int) -> float:
    """The longest fit first to the least busy worker: when the last worker ends."""
    busy = [0.0] * workers
    for t in sorted(times, reverse=True):
        busy[busy.index(min(busy))] += t
    return max(busy)


def speed_up(name: str, ratio: float, goal: float) -> None:
    met = "met" if ratio >= goal else "not met"
    print(f"speed-up, {name}: ratio {ratio:5.2f}x (goal >= {goal:g}x: {met})")


def projection(name: str, wall: float, times: list[float], workers: int) -> None:
    """The critical path and a greedy schedule for ``WORKERS`` workers (module docstring),
    from a run on ``workers`` workers that took ``wall`` seconds."""
    rest = max(wall - greedy(times, workers), 0.0)
    print(
        f"projection, {name}: {len(times)} fits, {sum(times):.1f} s of fitting on one core "
        f"(longest {max(times):.1f} s), {rest:.1f} s besides (start, data, shared PCA, report)"
    )
    for n in WORKERS:
        bound = rest + max(max(times), sum(times) / n)
        print(
            f"  {n:>3} workers: at least {bound:8.1f} s (critical path), "
            f"{rest + greedy(times, n):8.1f} s scheduled longest first"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="paper", help="the sweep timed four ways")
    parser.add_argument("--route-seeds", default="0,1,2", help="seeds of the route's projection")
    parser.add_argument("--keep", type=Path, help="keep the logdirs here (default: a temp folder)")
    parser.add_argument(
        "--warm-up", action="store_true", help="one untimed run first, to fill the compile cache"
    )
    parser.add_argument("--tiny", action="store_true", help=TINY_HELP)
    opts = parser.parse_args()
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) < 2:
        raise SystemExit("this benchmark needs two cores: run it where it may use two or more")
    args = TINY if opts.tiny else [f"preset={opts.preset}"]
    route = args if opts.tiny else ["preset=full", f"seeds=[{opts.route_seeds}]"]
    print(f"cluster benchmark on {cpu_name()}: {' '.join(args)}")
    with tempfile.TemporaryDirectory(prefix="vpr_jax-cluster-") as tmp:
        root = opts.keep or Path(tmp)
        if root.is_dir() and any(root.iterdir()):  # a logdir there would resume, not run
            raise SystemExit(f"--keep {root} is not empty: give a new or empty folder")
        local = ["cluster.address=local"]
        if opts.warm_up:  # compiles what the runs below then take from the cache
            sweep(args, root / "warm_up")
        if opts.tiny:  # the sweep's main in this process: a fresh one is most of a tiny run
            one, _ = sweep_in_fresh_process(args, root / "one_process", fresh=False)
        else:
            one = sweep(args, root / "one_process")
        share = [*local, "cluster.threads=share"]
        one_worker = [*share, "cluster.workers=1", "cluster.cores_per_worker=1"]
        workers = sweep([*args, *share, "cluster.workers=2"], root / "two_workers")
        # --tiny: the same code as the run above, with other keys; a sweep (a Ray started
        # and stopped) is most of a tiny run, and the tests check pinning on their own
        one_worker_dir = root / ("two_workers" if opts.tiny else "one_worker")
        if opts.tiny:
            worker = default = workers
        else:
            worker = sweep([*args, *one_worker], one_worker_dir)
            default = sweep([*args, *local, "cluster.workers=2"], root / "two_workers_node")
        spmd = distributed(args, root / "distributed", cores[:2])
        for name, wall in (
            (f"one process, {len(cores)} cores", one),
            ("cluster.address=local, 1 worker on 1 core", worker),
            ("cluster.address=local, 2 workers, 1 core each", workers),
            ("cluster.address=local, 2 workers, threads=node", default),
            ("mesh.distributed=true, 2 processes, 1 core each", spmd),
        ):
            print(f"{name:<48} {wall:8.1f} s")
        speed_up("2 workers over 1 worker", worker / workers, 1.7)
        speed_up("2 workers over one process", one / workers, 1.0)
        speed_up("2 workers (threads=node) over one process", one / default, 1.0)
        projection(" ".join(args), worker, fit_seconds(one_worker_dir), 2 if opts.tiny else 1)
        if opts.tiny:  # the route's projection from the two workers' tiny run
            route_wall, route_dir = workers, root / "two_workers"
        else:
            route_dir = root / "route"
            route_wall = sweep([*route, *share, "cluster.workers=2"], route_dir)
        projection(" ".join(route), route_wall, fit_seconds(route_dir), 2)


if __name__ == "__main__":
    main()
