"""The device check: what the suite computes on the device JAX sees, against the CPU.

    python benchmarks/device_check.py [--tiny] [--out FOLDER]

On whatever device JAX uses by default (a GPU where one is installed, else the CPU):
  1. the oracle tests of PCA, ICA, lda and diff_pca, the matcher and the metrics (tests/,
     against scikit-learn, numpy and the VPR_Tutorial definitions), run on that device;
  2. README's default sweep on that device and on the CPU, each in a fresh process; their
     results.csv compared cell by cell: the same cells, the same settings chosen on the
     validation places, recall@1 within 0.005 (every difference beyond it is printed, with
     the epochs a trained model kept on each side where they differ: the likely cause);
  3. run_all's table on that device, with its name and absolute times (the paper protocol,
     the whole route and the scaling exponents left out: see run_all.py for those).
Exit code 0 when the tests pass and the two sweeps agree, 1 otherwise; the lines say what.
Where the device is the CPU, step 2 compares two CPU runs (they must be identical).

``--tiny`` (for the tests): five oracle tests, a 400-frame sweep of raw and PCA, and
``run_all.py --tiny --skip-scaling``; where the device is the CPU, the sweeps and run_all
run in this process (the oracle tests, under pytest, in one of their own). ``--out``: keep
both sweeps' logdirs and run_all's table as JSON there (default: a temporary folder,
removed).
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
from common import TINY_HELP, run_script, sweep_in_fresh_process

from vpr_jax.outputs.results import ResultRow, read_results

REPO = Path(__file__).resolve().parent.parent
RECALL_TOLERANCE = 0.005  # recall@1 a cell may differ by between the device and the CPU
ORACLE_TESTS = [
    "tests/test_pca.py",
    "tests/test_ica.py",
    "tests/test_supervised_linear.py",
    "tests/test_matching.py",
    "tests/test_metrics.py",
]
TINY_ORACLE_TESTS = [
    "tests/test_pca.py::test_solvers_agree_and_components_orthonormal",
    "tests/test_ica.py::test_logcosh_alpha_and_a_tall_noisy_mixture_match_scikit_learn",
    "tests/test_supervised_linear.py::test_lda_equals_the_numpy_reference",
    "tests/test_matching.py::test_suffix_starts_equal_slicing",
    "tests/test_metrics.py::test_hand_made_tolerance_turns_a_wrong_match_right",
]
TINY_SWEEP = [
    "data.n_frames=400",
    "split.n_train=150",
    "split.n_test=60",
    "split.gap=10",
    "season_pairs=summer-fall",
    "methods=[raw,pca]",
    "removed_pcs=5",
]
TINY_RUN_ALL = ["--tiny", "--skip-scaling"]
RUN_ALL = ["--skip-protocol", "--skip-full-route", "--skip-scaling"]
STEP_TIMEOUT_S = 420  # one step's subprocess; the whole check stays under 8 minutes on a CPU


def platform_name() -> str:
    """What ``JAX_PLATFORMS`` calls the default device's platform (cuda, rocm, tpu, cpu)."""
    backend = jax.default_backend()
    if backend != "gpu":
        return backend
    for name in ("cuda", "rocm"):
        try:
            jax.devices(name)
            return name
        except RuntimeError:
            continue
    return backend


def environment(platform: str) -> dict:
    """The environment of a step on ``platform``: the repository on PYTHONPATH, JAX on that
    platform first (the CPU beside it), GPU memory taken as needed (several processes may
    share a card), and none of a surrounding pytest's variables (its workers' tell the
    tests' setup that it is done already)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}
    platforms = platform if platform == "cpu" else f"{platform},cpu"
    return {
        **env,
        "PYTHONPATH": str(REPO),
        "JAX_PLATFORMS": platforms,
        "XLA_PYTHON_CLIENT_PREALLOCATE": "false",
    }


def run(cmd: list[str], platform: str) -> subprocess.CompletedProcess:
    """``cmd`` in the repository on ``platform`` (the command line printed), its output
    captured."""
    env = environment(platform)
    print(f"$ JAX_PLATFORMS={env['JAX_PLATFORMS']} {' '.join(cmd)}", flush=True)
    return subprocess.run(
        cmd,
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=STEP_TIMEOUT_S,
        check=False,
    )


def oracle_tests(platform: str, tiny: bool) -> bool:
    tests = TINY_ORACLE_TESTS if tiny else ORACLE_TESTS
    workers = "0" if tiny else "auto"
    cmd = [sys.executable, "-m", "pytest", "-q", "-n", workers, "-p", "no:cacheprovider", *tests]
    proc = run(cmd, platform)
    print("\n".join(proc.stdout.strip().splitlines()[-3:]), flush=True)
    if proc.returncode != 0:
        print(proc.stdout[-3000:], proc.stderr[-3000:], sep="\n")
    return proc.returncode == 0


def here(tiny: bool, platform: str) -> bool:
    """Whether a step runs in this process: ``--tiny`` on the CPU, where this process's JAX
    is already the one the step needs and a fresh interpreter's start would be most of the
    step (as ``run_all.py --tiny`` runs its sweep)."""
    return tiny and platform == "cpu"


def sweep(platform: str, logdir: Path, tiny: bool) -> list[ResultRow]:
    """The default sweep (``tiny``: ``TINY_SWEEP``) on ``platform`` into ``logdir``."""
    if here(tiny, platform):
        wall, _ = sweep_in_fresh_process(TINY_SWEEP, logdir, fresh=False)
        print(f"  {wall:.0f} s", flush=True)
        return read_results(logdir / "results.csv")
    args = [*(TINY_SWEEP if tiny else []), f"logdir={logdir}"]
    args.append(f"train.checkpoint_dir={logdir.parent / 'checkpoints' / logdir.name}")
    start = time.perf_counter()
    proc = run([sys.executable, "-m", "experiments.sweep", *args], platform)
    if proc.returncode != 0:
        print(proc.stderr[-3000:])
        raise SystemExit(f"the sweep on {platform} failed (exit code {proc.returncode})")
    print(f"  {time.perf_counter() - start:.0f} s", flush=True)
    return read_results(logdir / "results.csv")


def compare(device: list[ResultRow], cpu: list[ResultRow], tolerance: float) -> list[str]:
    """What differs between two sweeps' rows beyond ``tolerance`` in recall@1, or in the
    cells they hold or the settings validation chose: one line each (none: they agree)."""
    a, b = ({r.run: r for r in rows} for rows in (device, cpu))
    problems = [f"cell {name} only on the device" for name in sorted(set(a) - set(b))]
    problems += [f"cell {name} only on the CPU" for name in sorted(set(b) - set(a))]
    for name in sorted(set(a) & set(b)):
        x, y = a[name], b[name]
        if x.selected != y.selected:
            problems.append(
                f"{name}: chosen on validation {'on the device' if x.selected else 'on the CPU'}"
                f" only (validation recall@1 {x.val_recall_at_1:.4f} / {y.val_recall_at_1:.4f})"
            )
        diff = x.recall_at_1 - y.recall_at_1
        if not abs(diff) <= tolerance:
            why = ""
            if x.kept_epoch != y.kept_epoch:
                why = f"; kept epoch {x.kept_epoch} on the device, {y.kept_epoch} on the CPU"
            problems.append(
                f"{name}: recall@1 {x.recall_at_1:.4f} on the device, {y.recall_at_1:.4f} on "
                f"the CPU ({diff:+.4f}){why}"
            )
    return problems


def largest_difference(device: list[ResultRow], cpu: list[ResultRow], metric: str) -> float:
    a, b = ({r.run: getattr(r, metric) for r in rows} for rows in (device, cpu))
    diffs = [abs(a[k] - b[k]) for k in set(a) & set(b) if not math.isnan(a[k] - b[k])]
    return max(diffs, default=0.0)


def sweeps_agree(platform: str, out: Path, tiny: bool) -> bool:
    """Step 2: the default sweep on ``platform`` and on the CPU, compared; the lines say
    how."""
    on_device = sweep(platform, out / "device", tiny)
    on_cpu = sweep("cpu", out / "cpu", tiny)
    problems = compare(on_device, on_cpu, RECALL_TOLERANCE)
    for line in problems:
        print(f"  differs: {line}")
    print(
        f"  {len(on_device)} cells compared: {len(problems)} differences beyond recall@1 "
        f"{RECALL_TOLERANCE} or in the settings chosen; largest |difference|: recall@1 "
        f"{largest_difference(on_device, on_cpu, 'recall_at_1'):.4f}, AUC-PR "
        f"{largest_difference(on_device, on_cpu, 'auc_pr'):.4f}",
        flush=True,
    )
    return not problems


def run_all(platform: str, out: Path, tiny: bool) -> bool:
    """Step 3: run_all's table on ``platform`` (and as JSON in ``out``)."""
    options = [*(TINY_RUN_ALL if tiny else RUN_ALL), "--json", str(out / "run_all.json")]
    if here(tiny, platform):
        script = REPO / "benchmarks" / "run_all.py"
        print(f"$ {script} {' '.join(options)}  (in this process)", flush=True)
        return run_script(script, options) == 0
    proc = run([sys.executable, "benchmarks/run_all.py", *options], platform)
    print(proc.stdout, flush=True)
    if proc.returncode != 0:
        print(proc.stderr[-3000:])
    return proc.returncode == 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tiny", action="store_true", help=TINY_HELP)
    parser.add_argument(
        "--out", type=Path, default=None, help="keep both sweeps' logdirs and run_all's JSON here"
    )
    args = parser.parse_args()
    start = time.perf_counter()
    device, platform = jax.devices()[0], platform_name()
    print(
        f"device: {device.device_kind} ({platform}), jax {jax.__version__}, "
        f"{jax.device_count()} device(s)",
        flush=True,
    )
    print("\n1. oracle tests on the device", flush=True)
    tests_pass = oracle_tests(platform, args.tiny)
    with tempfile.TemporaryDirectory(prefix="vpr_jax-device-") as tmp:
        out = args.out or Path(tmp)
        print("\n2. the default sweep on the device and on the CPU", flush=True)
        agree = sweeps_agree(platform, out, args.tiny)
        print("\n3. run_all on the device", flush=True)
        benchmarked = run_all(platform, out, args.tiny)
    agreed = tests_pass and agree and benchmarked
    print(
        f"device check {'passed' if agreed else 'FAILED'} on {device.device_kind} in "
        f"{time.perf_counter() - start:.0f} s"
    )
    raise SystemExit(0 if agreed else 1)


if __name__ == "__main__":
    main()
