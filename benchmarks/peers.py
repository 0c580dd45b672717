"""The peers of the benchmarks, each run in a fresh process on its native BLAS kernel.

    python benchmarks/peers.py TASK [--repeats 3] [--tiny]     # prints one JSON line

On our machines OPENBLAS_CORETYPE (and OPENBLAS_L2_SIZE) are set and force an older
OpenBLAS kernel on numpy and scikit-learn (threadpoolctl then reports 'Haswell' where the
CPU is a SkylakeX): scikit-learn's FastICA took 33 s with them and 13 s without. ``run_peer``
starts this script with both removed from the environment, so a peer runs as it would on a
machine without them, while our side runs in the benchmark's own process as a user's would.
Every task builds the same data as the benchmarks (``common.paper_route``) and reports the
median of warm runs, the first run, and the BLAS libraries threadpoolctl saw; with
``--tiny``, the benchmarks' tiny data (``common.route_sizes(tiny=True)``, FastICA of
``common.TINY_ICA_COMPONENTS`` components), as their own ``--tiny`` builds it. A benchmark's
``--tiny`` runs its peers in its own process (``run_peer(..., tiny=True)``): its figures mean
nothing, and a fresh interpreter per peer is most of a tiny run's time (tests/
test_benchmark_scripts.py starts this script itself, test_peers).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
import warnings
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
FORCING = ("OPENBLAS_CORETYPE", "OPENBLAS_L2_SIZE")  # variables that pick the BLAS kernel


def blas_report() -> str:
    """The BLAS libraries loaded in this process and the kernel each uses (threadpoolctl)."""
    from threadpoolctl import threadpool_info

    found = [
        f"{i.get('internal_api')} {i.get('version')} {i.get('architecture')} "
        f"({i.get('num_threads')} threads)"
        for i in threadpool_info()
        if i.get("user_api") == "blas"
    ]
    return "; ".join(found) or "no BLAS library loaded"


def ours_report() -> str:
    """What our side computes with: XLA's CPU kernels, plus any BLAS loaded here (jaxlib's
    LAPACK calls, e.g. eigh, go through scipy's OpenBLAS) and the forcing variables."""
    forced = ", ".join(f"{k}={os.environ[k]}" for k in FORCING if k in os.environ) or "none"
    return f"XLA:CPU; BLAS here: {blas_report()}; forcing variables: {forced}"


def run_peer(task: str, repeats: int, tiny: bool = False) -> dict:
    """Run ``task`` in a fresh process without the kernel-forcing variables; returns its
    JSON (``seconds``: warm median, ``first``, ``blas``, and task extras). ``tiny``: on the
    tiny data, in this process (``measure``; its ``blas`` says so)."""
    if tiny:
        report = measure(task, repeats, tiny=True)
        return {**report, "blas": f"{report['blas']} (in this process: --tiny)"}
    env = {k: v for k, v in os.environ.items() if k not in FORCING}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), str(HERE)])
    cmd = [sys.executable, str(HERE / "peers.py"), task, "--repeats", str(repeats)]
    proc = subprocess.run(
        [*cmd, "--tiny"] if tiny else cmd,
        env=env,
        capture_output=True,
        text=True,
    )
    if proc.returncode:
        raise SystemExit(f"peer {task} failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _timed(fn, repeats: int) -> tuple[float, float]:
    start = time.perf_counter()
    fn()
    first = time.perf_counter() - start
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - start)
    return first, statistics.median(runs) if runs else first


def numpy_top_k(q, d, k: int = 10):
    """Brute-force cosine top-k in numpy: the matching peer."""
    import numpy as np

    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    s = q @ d.T
    part = np.argpartition(-s, k, axis=1)[:, :k]
    order = np.argsort(-np.take_along_axis(s, part, 1), axis=1)
    idx = np.take_along_axis(part, order, 1)
    return np.take_along_axis(s, idx, 1), idx


def native_blas_process() -> None:
    """Re-run this benchmark (the whole process, both sides) without the kernel-forcing
    variables, for benchmarks whose peers run in-process; does nothing when none is set."""
    if any(k in os.environ for k in FORCING):
        env = {k: v for k, v in os.environ.items() if k not in FORCING}
        print(
            f"re-running without {', '.join(FORCING)} (the peers' native BLAS kernel)", flush=True
        )
        os.execve(sys.executable, [sys.executable, *sys.argv], env)


def _tasks(tiny: bool):
    from common import ica_components, paper_route, route_sizes
    from sklearn.decomposition import PCA, FastICA

    train, db, query = paper_route(**route_sizes(tiny))

    def fastica():
        model = FastICA(
            ica_components(tiny),
            algorithm="parallel",
            whiten="unit-variance",
            whiten_solver="svd",
            random_state=0,
            fun="logcosh",
            max_iter=200,
            tol=1e-4,
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # ConvergenceWarning
            model.fit(train)

    return {
        "pca_covariance_eigh": (lambda: PCA(svd_solver="covariance_eigh").fit(train), None),
        "pca_randomized_100": (
            lambda: PCA(100, svd_solver="randomized", random_state=0).fit(train),
            None,
        ),
        "fastica_256": (fastica, 0),  # one run: it takes seconds
        "numpy_top_k": (lambda: numpy_top_k(query, db), None),
    }


TASKS = ("pca_covariance_eigh", "pca_randomized_100", "fastica_256", "numpy_top_k")


def measure(task: str, repeats: int, tiny: bool = False) -> dict:
    """``task`` timed in this process: ``task``, ``seconds`` (warm median of ``repeats``
    runs; FastICA: the first), ``first`` and ``blas`` (the BLAS libraries loaded here)."""
    fn, fixed = _tasks(tiny)[task]
    first, seconds = _timed(fn, repeats if fixed is None else fixed)
    return {"task": task, "seconds": seconds, "first": first, "blas": blas_report()}


def main() -> None:
    from common import TINY_HELP

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("task", choices=TASKS)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--tiny", action="store_true", help=TINY_HELP)
    args = parser.parse_args()
    print(json.dumps(measure(args.task, args.repeats, args.tiny)))


if __name__ == "__main__":
    main()
