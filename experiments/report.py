"""What a sweep reports once its cells are written: results.md, the figures and one summary
TensorBoard run per season pair, all rebuilt from results.csv and the cells' curve.npz (this
run's cells and every earlier one's), so a resumed sweep reports the whole table."""

from __future__ import annotations

import csv
import functools
import io
import math
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np

from experiments.cells import INCOMPLETE, block_length
from vpr_jax.config import SweepConfig
from vpr_jax.encoders.saved import FIT_JSON, describe_encoder, read_description
from vpr_jax.evaluation.bootstrap import Difference, paired_recall_difference
from vpr_jax.evaluation.metrics import SCALAR_NAMES
from vpr_jax.files import atomic_write_text, replace_folder
from vpr_jax.method_table import SWEEPS_REMOVED_PCS
from vpr_jax.methods import model_name
from vpr_jax.outputs.logdir import ENCODERS_CSV, LISTING, fitted_root
from vpr_jax.outputs.palette import compare_labels, label_of
from vpr_jax.outputs.plots import correct_matches_figure, pr_curves_figure, recall_vs_ds_figure
from vpr_jax.outputs.results import (
    ResultRow,
    baseline_of,
    best_objectives,
    best_rows,
    read_results,
    selected_rows,
)
from vpr_jax.outputs.tb import CompareSeries, SummaryCell, write_method_run, write_pair_summary

SUMMARY = "summary"  # logdir/summary/<pair>: each pair's selected cells in one run
COMPARE = "compare"  # logdir/compare/<method>: a run per method, its tags per pair
Curves = Callable[[str], dict[str, np.ndarray]]  # run -> its curve.npz arrays


def write_report(logdir: Path, cfg: SweepConfig) -> None:
    """results.md, the figures and the summary runs, from every row of results.csv."""
    rows = read_results(logdir / "results.csv")
    if not rows:
        return
    curve = curve_reader(logdir)
    atomic_write_text(
        logdir / "results.md", markdown_table(rows, differences_to_pca(rows, curve, cfg))
    )
    figures = logdir / "figures"
    figures.mkdir(exist_ok=True)
    write_tb_summaries(logdir, rows, curve, cfg)
    write_tb_compare(logdir, rows, curve, cfg)
    pr_curves_figure(
        rows,
        lambda row: (curve(row.run)["precision"], curve(row.run)["recall"]),
        figures / "pr_curves.png",
    )
    correct_matches_figure(rows, figures / "correct_matches.png")
    if len({r.ds for r in rows}) > 1:
        recall_vs_ds_figure(rows, figures / "recall_vs_ds.png")
    listing = describe_encoders(fitted_root(cfg, logdir), rows)
    atomic_write_text(logdir / ENCODERS_CSV, encoders_csv(listing))


def encoders_csv(listing: list[dict]) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, LISTING, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(listing)
    return out.getvalue()


def describe_encoders(root: Path, rows: list[ResultRow]) -> list[dict]:
    """Each saved encoder's ``encoder.json``, from its ``fit.json`` and the table: the
    removed-PC count chosen on the validation places among those it serves (single images),
    with its validation and test recall@1. Rewritten with every report, so a resumed sweep
    that adds counts moves the choice. Returns the descriptions, each with its folder."""
    shortest, listing = min(r.ds for r in rows), []
    if not root.is_dir():
        return listing
    for pair in sorted({r.season_pair for r in rows}):
        for fit_file in sorted((root / pair).glob(f"*/{FIT_JSON}")):
            fit = read_description(fit_file.parent, FIT_JSON)
            mine = [
                r
                for r in rows
                if (r.season_pair, r.method, r.objective, r.ds)
                == (pair, fit["name"], fit["objective"], shortest)
                and r.removed_pcs in fit["counts"]
            ]
            if not mine:
                continue
            chosen = max(mine, key=lambda r: (r.selected, r.val_recall_at_1, r.val_auc_pr))
            by_count = {str(r.removed_pcs): r.val_recall_at_1 for r in mine}
            description = describe_encoder(
                fit_file.parent,
                {
                    "removed_pcs": chosen.removed_pcs,
                    "val_recall_at_1": chosen.val_recall_at_1,
                    "val_recall_at_1_by_count": by_count,
                    "test_recall_at_1": chosen.recall_at_1,
                    "selected": bool(chosen.selected),
                    "run": chosen.run,
                },
            )
            listing.append({**description, "folder": str(fit_file.parent)})
    return listing


def curve_reader(logdir: Path) -> Curves:
    """``run -> curve.npz`` as a dict of arrays, each file read once: results.md's paired
    differences, the summary runs and the figures all read the selected rows' curves."""

    @functools.cache
    def curve(run: str) -> dict[str, np.ndarray]:
        with np.load(logdir / run / "curve.npz") as z:
            return {name: z[name] for name in z.files}

    return curve


def write_tb_summaries(logdir: Path, rows: list[ResultRow], curve: Curves, cfg: SweepConfig):
    """Per season pair, one TensorBoard run holding every method's selected cell
    (``vpr_jax.outputs.tb.write_pair_summary``), rewritten whole (aside, then moved into place).
    ``tensorboard --logdir LOGDIR/summary`` opens on them."""
    by_pair: dict[str, list[SummaryCell]] = {}
    for row in selected_rows(rows):
        label = model_name(row.method, row.objective)
        by_pair.setdefault(row.season_pair, []).append(
            SummaryCell(
                label=label + (f"_ds{row.ds:02d}" if row.ds != 1 else ""),
                setting=f"k={row.removed_pcs}" if row.method in SWEEPS_REMOVED_PCS else "",
                scalars={name: getattr(row, name) for name in SCALAR_NAMES},
                best_scores=curve(row.run)["best_scores"],
                best_correct=curve(row.run)["best_correct"],
                has_match=curve(row.run)["has_match"],
            )
        )
    for pair, cells in by_pair.items():
        staging = logdir / INCOMPLETE / SUMMARY / pair
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir(parents=True)
        write_pair_summary(
            staging, cells, pr_convention=cfg.pr_convention, n_thresholds=cfg.tb.pr_thresholds
        )
        replace_folder(staging, logdir / SUMMARY / pair)


def write_tb_compare(logdir: Path, rows: list[ResultRow], curve: Curves, cfg: SweepConfig):
    """``LOGDIR/compare/<method>``: one run per method (``tb.write_method_run``) over the
    single-image cells (the shortest ds), rewritten whole. Runs are written one after
    another in ``palette.compare_labels`` order, which is how TensorBoard colours them
    (``vpr_jax.outputs.palette``); a method without the removed-PC axis is a flat line over
    its pair's counts."""
    shortest = min(r.ds for r in rows)
    single = [r for r in rows if r.ds == shortest]
    staging = logdir / INCOMPLETE / COMPARE
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    for label in compare_labels(single):
        series = {}
        for pair in dict.fromkeys(r.season_pair for r in single):
            mine = sorted(
                (r for r in single if r.season_pair == pair and label_of(r) == label),
                key=lambda r: r.removed_pcs,
            )
            if not mine:
                continue
            counts = sorted({r.removed_pcs for r in single if r.season_pair == pair})
            points = [(r.removed_pcs, r.recall_at_1, r.auc_pr) for r in mine]
            if mine[0].method not in SWEEPS_REMOVED_PCS:
                points = [(k, mine[0].recall_at_1, mine[0].auc_pr) for k in counts]
            chosen = curve(next(r for r in mine if r.selected).run)
            series[pair] = CompareSeries(
                points=points,
                best_scores=chosen["best_scores"],
                best_correct=chosen["best_correct"],
                has_match=chosen["has_match"],
            )
        write_method_run(
            staging / label,
            series,
            pr_convention=cfg.pr_convention,
            n_thresholds=cfg.tb.pr_thresholds,
        )
    replace_folder(staging, logdir / COMPARE)


def differences_to_pca(
    rows: list[ResultRow], curve: Curves, cfg: SweepConfig
) -> dict[str, Difference]:
    """Per selected row (by run), recall@1 minus its pair's selected PCA row's, paired on
    the same queries (``vpr_jax.evaluation.bootstrap``); rows whose queries differ from PCA's in
    number (no pairing possible) are left out."""
    selected = selected_rows(rows)
    out = {}
    for row in selected:
        base = baseline_of(row, selected)
        if row.method == "pca" or base is None:
            continue
        mine, theirs = curve(row.run)["best_correct"], curve(base.run)["best_correct"]
        if mine.shape != theirs.shape:
            continue
        out[row.run] = paired_recall_difference(
            mine,
            theirs,
            block_length=block_length(cfg, row.ds),
            resamples=cfg.bootstrap.resamples,
            seed=cfg.seed,
        )
    return out


# ---------------------------------------------------------------------------- results.md

CELL_COLUMNS = (
    "season_pair",
    "method",
    "objective",
    "removed_pcs",
    "ds",
    "recall_at_1",
    "auc_pr",
    "recall_at_100_precision",
    "recall_at_5",
    "recall_at_10",
    "fit_seconds",
    "encode_ms_per_image",
)
HEADLINE_COLUMNS = (
    "season_pair",
    "method",
    "objective",
    "removed_pcs",
    "ds",
    "val_recall_at_1",
    "recall_at_1",
    "95% CI",
    "auc_pr",
    "95% CI",
    "recall@1 - PCA [95% CI]",
    "vs PCA",
)
SELECTION_NOTE = (
    "The removed-PC count with the best recall@1 on the validation places (the end of "
    "each season's training stretch; for a benchmark trained on its database, its last "
    "queries, held out of the test), scored on the test places. Intervals: 95%, block "
    "bootstrap over the queries. vs PCA: a paired bootstrap of the difference to the "
    "pair's selected PCA row on the same queries; better / worse when its interval "
    "excludes 0."
)


def markdown_table(rows: list[ResultRow], differences: dict[str, Difference] | None = None) -> str:
    """results.md: the validation-selected setting per method (recall@1 and AUC-PR with
    their 95% intervals, and the paired difference to PCA that ``differences`` holds per
    run), then the best count chosen on the test queries (optimistic), then every cell.
    The ds column appears once a sweep holds sequence-matching cells."""
    sequences = any(r.ds != 1 for r in rows)
    preferred = best_objectives(rows)  # runs marked "best"
    first = rows[0] if rows else None
    intro = (
        f"{first.n_test} queries per pair, a match is correct within {first.ground_truth}, "
        f"seed {first.seed}. recall_at_1 is the fraction of correct matches (= precision at "
        "100% recall)."
        if first
        else "No cells yet."
    )
    lines = [
        "# Results",
        "",
        intro,
        "",
        "## Each method at the setting chosen on the validation places",
        "",
        SELECTION_NOTE,
        "",
        *_headline(selected_rows(rows), differences or {}, sequences, preferred),
        *_best_objective_note(rows, preferred),
        "",
        "## Best removed-PC count per method, chosen on the test queries (optimistic)",
        "",
        *_cell_table(best_rows(rows), sequences),
        "",
        "## Every cell",
        "",
        *_cell_table(rows, sequences),
        "",
        *_not_converged(rows),
    ]
    return "\n".join(lines)


def _in_order(rows: list[ResultRow]) -> list[ResultRow]:
    return sorted(rows, key=lambda r: (r.season_pair, r.method, r.objective, r.removed_pcs, r.ds))


def _markdown(head: tuple[str, ...], body: list[list[str]]) -> list[str]:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    return lines + ["| " + " | ".join(cells) + " |" for cells in body]


def _without_ds(columns: tuple[str, ...], sequences: bool) -> tuple[str, ...]:
    return columns if sequences else tuple(c for c in columns if c != "ds")


def _cell_table(rows: list[ResultRow], sequences: bool) -> list[str]:
    cols = _without_ds(CELL_COLUMNS, sequences)
    body = [
        [f"{v:.3f}" if isinstance(v, float) else str(v) for v in (getattr(r, c) for c in cols)]
        for r in _in_order(rows)
    ]
    return _markdown(cols, body)


def _ci(low: float, high: float) -> str:
    return "" if math.isnan(low) else f"[{low:.3f}, {high:.3f}]"


def _versus_pca(row: ResultRow, differences: dict[str, Difference]) -> tuple[str, str]:
    """(the difference to PCA with its interval, its label) for the headline table."""
    diff = differences.get(row.run)
    if row.method == "pca":
        return "", "baseline"
    if diff is None:
        return "", "n/a"
    return f"{diff.value:+.3f} [{diff.low:+.3f}, {diff.high:+.3f}]", diff.label


def _headline(
    rows: list[ResultRow],
    differences: dict[str, Difference],
    sequences: bool,
    preferred: set[str],
) -> list[str]:
    body = []
    for r in _in_order(rows):
        versus, label = _versus_pca(r, differences)
        body.append(
            [
                r.season_pair,
                r.method,
                r.objective + (" best" if r.run in preferred else ""),
                str(r.removed_pcs),
                *((str(r.ds),) if sequences else ()),
                f"{r.val_recall_at_1:.3f}",
                f"{r.recall_at_1:.3f}",
                _ci(r.recall_at_1_ci_low, r.recall_at_1_ci_high),
                f"{r.auc_pr:.3f}",
                _ci(r.auc_pr_ci_low, r.auc_pr_ci_high),
                versus,
                label,
            ]
        )
    return _markdown(_without_ds(HEADLINE_COLUMNS, sequences), body)


def _best_objective_note(rows: list[ResultRow], preferred: set[str]) -> list[str]:
    """A line naming each auto-encoder's best objective per pair (marked "best" above)."""
    best = [r for r in rows if r.run in preferred]
    if not best:
        return []
    named = ", ".join(f"{r.season_pair} {r.method} {r.objective}" for r in _in_order(best))
    return ["", f"Best objective by validation recall@1 (marked best): {named}."]


def _not_converged(rows: list[ResultRow]) -> list[str]:
    stuck = [r for r in rows if not r.converged]
    if not stuck:
        return []
    cells = ", ".join(f"{r.season_pair} {r.method} k={r.removed_pcs}" for r in stuck)
    return [f"Not converged (stopped at the iteration limit, see sweep.log): {cells}.", ""]
