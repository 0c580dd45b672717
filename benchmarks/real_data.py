"""Every method on real frames, in one table: raw, PCA, diff_pca, ICA, LDA, and the FAE and
CAE with each objective, single images (ds = 1) and sequences of ten (ds = 10).

    python benchmarks/real_data.py DATA_ROOT [--seasons summer,winter] [--tiny] [KEY=VALUE ...]

DATA_ROOT holds one folder of frame-aligned images per season (``data.source=folders``:
any size, the frame number in each file name), e.g. ``../shared/data/nordland_dev`` with
``summer/`` and ``winter/``. It runs the sweep (``python -m experiments.sweep``) with the
paper's split scaled to 1,788 places by default (1,200 training places, a 10-frame gap, 450
test places, a match within +-1 frame; the last 120 training places validate, after another
10-frame gap), the first season as the database and the second as
the queries, into ``--logdir`` (default ``runs/real_data``; rerun to resume, or to add
objectives or sequence lengths), then prints one row per method and objective:
the removed-PC count with the best single-image recall@1 (chosen on the test queries:
optimistic), recall@1, AUC-PR, R@100P and recall@10 of single images, recall@1 of
sequences of ten, and the fit's seconds. Any further ``KEY=VALUE`` goes to the sweep as
it is (e.g. ``fae.epochs=100 train.augment=false``).

``--tiny`` (for the tests): 60 training places, a 4-frame gap and 30 test places unless the
options name others (a DATA_ROOT of 94 frames a season serves), and ``TINY_OVERRIDES``
(tiny models, one epoch, two removed-PC counts) before any KEY=VALUE given; the sweep runs
by its ``main`` in this process (a second interpreter would be most of a tiny run's time).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from common import TINY_HELP  # noqa: E402

from vpr_jax.method_table import NAMES  # noqa: E402
from vpr_jax.outputs.results import (  # noqa: E402
    SWEEP_KEYS,
    choice_order,
    read_results,
    selected_rows,
    swept_of,
)

ORDER = NAMES  # the method table's order; users' methods after it
SPLIT = {"n_train": 1200, "n_test": 450, "gap": 10}  # the defaults of the options
TINY_SPLIT = {"n_train": 60, "n_test": 30, "gap": 4}
TINY_OVERRIDES = [
    "removed_pcs=[0,5]",
    "ica.n_components=8",
    "lda.n_components=8",
    "fae.hidden=32",
    "cae.channels=[4,8]",
    "cae.code_channels=2",
    "train.epochs=1",
]


def sweep_args(args: argparse.Namespace) -> list[str]:
    seasons = [s.strip() for s in args.seasons.split(",")]
    if len(seasons) != 2:
        raise SystemExit(f"--seasons={args.seasons}: name two seasons, database first")
    return [
        "data.source=folders",
        f"data.root={Path(args.root).expanduser().resolve()}",
        f"data.seasons=[{','.join(seasons)}]",
        f"season_pairs={'-'.join(seasons)}",
        f"split.n_train={args.n_train}",
        f"split.n_test={args.n_test}",
        f"split.gap={args.gap}",
        f"tolerance={args.tolerance}",
        "sequence.enabled=true",
        "sequence.ds=[1,10]",
        f"logdir={args.logdir}",
        *(TINY_OVERRIDES if args.tiny else []),
        *args.overrides,
    ]


def run_sweep(argv: list[str], in_process: bool = False) -> int:
    """``python -m experiments.sweep ARGV`` in the repository (``in_process``: its ``main``
    here); its exit code."""
    if in_process:
        from experiments import sweep

        return sweep.main(argv)
    command = [sys.executable, "-m", "experiments.sweep", *argv]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run(command, cwd=REPO, env=env).returncode


def _sweep_values(row) -> str:
    """The values of the sweep's keys the row's cell has (its removed count), or ''."""
    values = swept_of(row)
    return " ".join(str(values[key]) for key in SWEEP_KEYS if key in values)


def table(rows) -> str:
    """One line per method and objective: the removed-PC count chosen on the validation
    places (``selected``), its test figures with the recall@1 interval, the selected row
    of sequences of ten, and the count chosen on the test queries (optimistic)."""
    lines = [
        "| method | objective | k | recall@1 [95% CI] | AUC-PR | R@100P | recall@10 | "
        "recall@1, ds=10 | optimistic k: recall@1 | fit s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    groups = sorted(
        {(r.method, r.objective) for r in rows},
        key=lambda g: (ORDER.index(g[0]) if g[0] in ORDER else len(ORDER), g[1]),
    )
    chosen = {(r.method, r.objective, r.ds): r for r in selected_rows(rows)}
    for method, objective in groups:
        single = [r for r in rows if (r.method, r.objective, r.ds) == (method, objective, 1)]
        if not single:
            continue
        sel = chosen[(method, objective, 1)]
        best = min(single, key=lambda r: (-r.recall_at_1, choice_order(r)))
        seq = chosen.get((method, objective, 10))
        k = _sweep_values(sel)
        ds10 = f"{seq.recall_at_1:.3f}" + (f" (k={_sweep_values(seq)})" if k else "") if seq else ""
        optimistic = f"{_sweep_values(best)}: {best.recall_at_1:.3f}" if k else ""
        lines.append(
            f"| {method} | {objective} | {k} | {sel.recall_at_1:.3f} "
            f"[{sel.recall_at_1_ci_low:.3f}, {sel.recall_at_1_ci_high:.3f}] | "
            f"{sel.auc_pr:.3f} | {sel.recall_at_100_precision:.3f} | "
            f"{sel.recall_at_10:.3f} | {ds10} | {optimistic} | "
            f"{sel.fit_seconds:.1f} |"
        )
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", help="folder with one folder of aligned frames per season")
    parser.add_argument("--seasons", default="summer,winter", help="database,query")
    parser.add_argument("--n-train", type=int, default=None, help="default 1200 (--tiny: 60)")
    parser.add_argument("--n-test", type=int, default=None, help="default 450 (--tiny: 30)")
    parser.add_argument("--gap", type=int, default=None, help="default 10 (--tiny: 4)")
    parser.add_argument("--tolerance", type=int, default=1)
    parser.add_argument("--logdir", default="runs/real_data")
    parser.add_argument("--tiny", action="store_true", help=TINY_HELP)
    parser.add_argument("overrides", nargs="*", help="more key=value for the sweep")
    args = parser.parse_intermixed_args()  # key=value may follow the options
    for key, value in (TINY_SPLIT if args.tiny else SPLIT).items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    args.logdir = str(Path(args.logdir).expanduser().resolve())  # the sweep runs in REPO
    code = run_sweep(sweep_args(args), in_process=args.tiny)
    if code:
        return code
    print(table(read_results(Path(args.logdir) / "results.csv")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
