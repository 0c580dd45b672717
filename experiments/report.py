"""What a sweep reports once its cells are written: results.md, the figures and one summary
TensorBoard run per season pair, all rebuilt from results.csv and the cells' curve.npz (this
run's cells and every earlier one's), so a resumed sweep reports the whole table."""

from __future__ import annotations

import functools
import math
import shutil
import traceback
from collections.abc import Callable
from pathlib import Path

import numpy as np

from experiments.cells import INCOMPLETE, block_length
from vpr_jax.config import SweepConfig
from vpr_jax.errors import first_line
from vpr_jax.evaluation.bootstrap import Difference, paired_recall_difference
from vpr_jax.evaluation.metrics import SCALAR_NAMES, pr_curve
from vpr_jax.files import atomic_write_text, replace_folder
from vpr_jax.method_table import NAMES as METHOD_NAMES
from vpr_jax.outputs.palette import compare_labels, label_of
from vpr_jax.outputs.plots import (
    by_label,
    correct_matches_figure,
    learning_curves_figure,
    pr_curves_figure,
    recall_vs_ds_figure,
)
from vpr_jax.outputs.results import (
    SWEEP_KEYS,
    Choice,
    ResultRow,
    baseline_method,
    baseline_of,
    best_objectives,
    best_rows,
    choice_order,
    choices,
    largest_places,
    plain_setting,
    read_results,
    selected_rows,
    selection_reasons,
    settings_of,
    sweep_labels,
    training_places,
)
from vpr_jax.outputs.tb import CompareSeries, SummaryCell, write_method_run, write_pair_summary
from vpr_jax.progress import RunLog

SUMMARY = "summary"  # logdir/summary/<pair>: each pair's selected cells in one run
COMPARE = "compare"  # logdir/compare/<method>: a run per method, its tags per pair
Curves = Callable[[str], dict[str, np.ndarray]]  # run -> its curve.npz arrays


def report_steps(logdir: Path, cfg: SweepConfig, rows: list[ResultRow]) -> dict[str, Callable]:
    """What a report writes, by the name a warning gives it, in order: the tables first,
    so a failing figure cannot cost them."""
    curve = curve_reader(logdir)
    figures = logdir / "figures"
    main = largest_places(rows)  # a learning curve's largest point, beside every other row

    def figure(draw: Callable, name: str) -> Callable:
        def step():
            figures.mkdir(exist_ok=True)
            draw(figures / name)

        return step

    steps = {
        "results.md": lambda: atomic_write_text(
            logdir / "results.md",
            markdown_table(
                rows,
                *differences_to_baseline(rows, curve, cfg),
                same_models(rows, curve),
                differences_to_start(rows, curve, cfg),
            ),
        ),
        f"the {SUMMARY} runs": lambda: write_tb_summaries(logdir, main, curve, cfg),
        f"the {COMPARE} runs": lambda: write_tb_compare(logdir, rows, curve, cfg),
        "figures/pr_curves.png": figure(
            lambda path: pr_curves_figure(
                main, lambda mine: pooled_curve(mine, curve, cfg.pr_convention), path
            ),
            "pr_curves.png",
        ),
        "figures/correct_matches.png": figure(
            lambda path: correct_matches_figure(main, path), "correct_matches.png"
        ),
    }
    if len({r.ds for r in rows}) > 1:
        steps["figures/recall_vs_ds.png"] = figure(
            lambda path: recall_vs_ds_figure(main, path), "recall_vs_ds.png"
        )
    if any(training_places(r) is not None for r in rows):
        steps["figures/learning_curves.png"] = figure(
            lambda path: learning_curves_figure(rows, path), "learning_curves.png"
        )
    return steps


def write_report(logdir: Path, cfg: SweepConfig, log: RunLog) -> list[str]:
    """results.md, the summary and compare runs and the figures, from every row of
    results.csv (``run_steps``). Returns the names of the failed steps."""
    rows = read_results(logdir / "results.csv")
    return run_steps(report_steps(logdir, cfg, rows), log) if rows else []


def run_steps(steps: dict[str, Callable], log: RunLog) -> list[str]:
    """Run each step; one that fails is skipped with one warning naming it (its traceback
    in sweep.log): the cells are fine, the other outputs are written, and the next run of
    the same command tries it again. Returns the names of the failed steps."""
    failed = []
    for name, step in steps.items():
        try:
            step()
        except Exception as err:  # a report is never worth the results it reports
            failed.append(name)
            log(
                f"warning: {name} not written ({type(err).__name__}: {first_line(err)}); the "
                "cells are kept and the rest of the report is written: rerun the same command "
                "to try again (the traceback is in sweep.log)"
            )
            log.record(traceback.format_exc())
    return failed


def pooled_curve(rows: list[ResultRow], curve: "Curves", pr_convention: str) -> tuple:
    """(precision, recall) of a method's rows: its own curve, or with several seeds the
    curve of all their queries pooled."""
    if len(rows) == 1:
        return curve(rows[0].run)["precision"], curve(rows[0].run)["recall"]
    arrays = pooled_arrays(rows, curve)
    precision, recall, _ = pr_curve(
        arrays["best_scores"],
        arrays["best_correct"].astype(bool),
        arrays["has_match"].astype(bool),
        pr_convention=pr_convention,
    )
    return precision, recall


def pooled_arrays(rows: list[ResultRow], curve: "Curves") -> dict[str, np.ndarray]:
    """best_scores, best_correct and has_match of a method's rows, its seeds' queries one
    after another."""
    return {
        name: np.concatenate([curve(r.run)[name] for r in rows])
        for name in ("best_scores", "best_correct", "has_match")
    }


def curve_reader(logdir: Path) -> Curves:
    """``run -> curve.npz`` as a dict of arrays, each file read once: results.md's paired
    differences, the summary runs and the figures all read the selected rows' curves."""

    @functools.cache
    def curve(run: str) -> dict[str, np.ndarray]:
        with np.load(logdir / run / "curve.npz") as z:
            return {name: z[name] for name in z.files}

    return curve


def _setting_text(row: ResultRow) -> str:
    """A cell's setting in words: its swept settings and the sweep's keys (k=5), and a
    trained model kept at its start says so."""
    start = f"(its start: {row.start}, no epoch beat it)" if row.kept_epoch == 0 else ""
    return " ".join(x for x in (row.setting, *sweep_labels(row), start) if x)


def _seeds_text(rows: list[ResultRow]) -> str:
    return f"(mean of {len(rows)} seeds)" if len(rows) > 1 else ""


def write_tb_summaries(logdir: Path, rows: list[ResultRow], curve: Curves, cfg: SweepConfig):
    """Per season pair, one TensorBoard run holding every method's selected cell
    (``vpr_jax.outputs.tb.write_pair_summary``; several seeds: their mean, the PR curve of
    their queries pooled), rewritten whole (aside, then moved into place).
    ``tensorboard --logdir LOGDIR/summary`` opens on them."""
    by_pair: dict[str, list[SummaryCell]] = {}
    for (pair, label), mine in by_label(selected_rows(rows)).items():
        for ds in sorted({r.ds for r in mine}):
            at_ds = [r for r in mine if r.ds == ds]
            by_pair.setdefault(pair, []).append(
                SummaryCell(
                    label=label + (f"_ds{ds:02d}" if ds != 1 else ""),
                    setting=" ".join(x for x in (_setting_text(at_ds[0]), _seeds_text(at_ds)) if x),
                    scalars={
                        name: float(np.mean([getattr(r, name) for r in at_ds]))
                        for name in SCALAR_NAMES
                    },
                    **pooled_arrays(at_ds, curve),
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
    """``LOGDIR/compare/<label>``: one run per method, objective and swept setting
    (``tb.write_method_run``) over the single-image cells (the shortest ds), rewritten
    whole: recall@1 and AUC-PR against the removed count (several seeds: their mean), and
    the PR curve of the setting the validation places choose (pooled over seeds). Runs are
    written one after another in ``palette.compare_labels`` order, which is how TensorBoard
    colours them (``vpr_jax.outputs.palette``); a method without the removed-PC axis is a
    flat line over its pair's counts."""
    shortest = min(r.ds for r in rows)
    every = [r for r in rows if r.ds == shortest]
    single = largest_places(every)
    staging = logdir / INCOMPLETE / COMPARE
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    for label in compare_labels(single):
        series = {}
        for pair in dict.fromkeys(r.season_pair for r in single):
            mine = [r for r in single if r.season_pair == pair and label_of(r) == label]
            if not mine:
                continue
            steps = sorted({_step(r) for r in single if r.season_pair == pair} - {None})
            by_step: dict[int, list[ResultRow]] = {}
            for r in mine:
                by_step.setdefault(_step(r) or 0, []).append(r)
            points = [
                (k, _mean(v, "recall_at_1"), _mean(v, "auc_pr")) for k, v in sorted(by_step.items())
            ]
            if _step(mine[0]) is None:  # a flat line over the pair's steps
                points = [(k, points[0][1], points[0][2]) for k in steps or [0]]
            chosen = max(next(iter(choices(mine).values())), key=Choice.val_score)
            series[pair] = CompareSeries(
                points=points,
                **pooled_arrays(list(chosen.rows), curve),
                learning=_learning_points(every, pair, label),
            )
        write_method_run(
            staging / label,
            series,
            pr_convention=cfg.pr_convention,
            n_thresholds=cfg.tb.pr_thresholds,
        )
    replace_folder(staging, logdir / COMPARE)


def _learning_points(rows: list[ResultRow], pair: str, label: str) -> tuple:
    """(training places, recall@1, AUC-PR) of a label's selected rows of a learning curve,
    the mean over seeds."""
    by_places: dict[int, list[ResultRow]] = {}
    for r in selected_rows(rows):
        if r.season_pair == pair and label_of(r) == label and training_places(r) is not None:
            by_places.setdefault(training_places(r), []).append(r)
    return tuple(
        (p, _mean(v, "recall_at_1"), _mean(v, "auc_pr")) for p, v in sorted(by_places.items())
    )


def _step(row: ResultRow) -> int | None:
    """Where a row sits on the compare view's step axis: the value of the sweep's key it
    has (its removed count), or None for a method without one."""
    values = settings_of(row)
    return next((int(values[k]) for k in SWEEP_KEYS if k in values), None)


def _mean(rows: list[ResultRow], metric: str) -> float:
    return float(np.mean([getattr(r, metric) for r in rows]))


def differences_to_baseline(
    rows: list[ResultRow], curve: Curves, cfg: SweepConfig
) -> tuple[dict[str, Difference], str | None]:
    """Per selected row (by run), recall@1 minus its pair's selected baseline row's (PCA's,
    or the first outside set's without PCA: ``baseline_method``), paired on the same queries
    (``vpr_jax.evaluation.bootstrap``); rows whose queries differ from the baseline's in
    number (no pairing possible) are left out. Returns them and the baseline's name."""
    selected = selected_rows(rows)
    baseline = baseline_method(rows, cfg.baseline, tuple(cfg.precomputed))
    out = {}
    for row in selected:
        base = None if baseline is None else baseline_of(row, selected, baseline)
        if row.method == baseline or base is None:
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
    return out, baseline


def differences_to_start(
    rows: list[ResultRow], curve: Curves, cfg: SweepConfig
) -> dict[str, Difference]:
    """Per selected row of a trained method (by run): its recall@1 minus its start's (the
    untouched starting weights) on the same queries, paired as ``differences_to_baseline``;
    exactly 0 for a model kept at its start (it is its start). Cells saved without their
    start's matches are left out."""
    out = {}
    for row in selected_rows(rows):
        if row.kept_epoch is None:
            continue
        if row.kept_epoch == 0:
            out[row.run] = Difference(0.0, 0.0, 0.0)
            continue
        arrays = curve(row.run)
        if "start_correct" not in arrays:
            continue
        out[row.run] = paired_recall_difference(
            arrays["best_correct"],
            arrays["start_correct"],
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
    "setting",
    "removed_pcs",
    "ds",
    "seed",
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
    "setting",
    "removed_pcs",
    "ds",
    "seed",
    "val_recall_at_1",
    "chosen by",
    "recall_at_1",
    "95% CI",
    "auc_pr",
    "95% CI",
    "recall@1 - {base} [95% CI]",
    "vs {base}",
)
OPTIONAL = ("setting", "ds", "seed")  # columns shown when a sweep has more than one value
SELECTION_NOTE = (
    "The setting (removed-PC count, and the method's swept settings) with the best recall@1 "
    "on the validation places (the end of each season's training stretch; for a benchmark "
    "trained on its database, its last queries, held out of the test), scored on the test "
    "places; with several seeds, the best mean over them, every seed's row shown. Settings "
    "tied on it are told apart by their validation margin (val_margin in results.csv: the "
    "best correct match's cosine minus the best wrong one's, averaged over the queries; "
    "docs/metrics.md), then the simpler setting (fewer removed PCs, the first value) wins; "
    "'chosen by' says which decided. Intervals: 95%, block bootstrap over the queries. "
)
VERSUS_NOTE = {
    True: (
        "vs {base}: a paired bootstrap of the difference to the pair's selected {base} row on "
        "the same queries; better / worse when its interval excludes 0."
    ),
    False: "No PCA or outside set in this sweep: no paired differences.",
}


def _shown(rows: list[ResultRow]) -> set[str]:
    """The optional columns this table needs: a setting swept, sequences, several seeds."""
    shown = set()
    if any(r.setting for r in rows):
        shown.add("setting")
    if any(r.ds != 1 for r in rows):
        shown.add("ds")
    if len({r.seed for r in rows}) > 1:
        shown.add("seed")
    return shown


def markdown_table(
    rows: list[ResultRow],
    differences: dict[str, Difference] | None = None,
    baseline: str | None = None,
    same_models: list[list[ResultRow]] = (),
    to_start: dict[str, Difference] | None = None,
) -> str:
    """results.md: the validation-selected setting per method (recall@1 and AUC-PR with
    their 95% intervals, what decided the choice, and the paired difference to the
    ``baseline`` method (PCA, or the first outside set) that ``differences`` holds per run),
    the spread over seeds where there are several, then the best setting chosen on the test
    queries (optimistic), then every cell. The setting, ds and seed columns appear once a
    sweep has more than one value of them."""
    base = _label(baseline)
    shown = _shown(rows)
    preferred = best_objectives(rows)  # runs marked "best"
    first = rows[0] if rows else None
    seeds = ", ".join(str(s) for s in sorted({r.seed for r in rows}))
    protocols = sorted({(r.season_pair, r.protocol) for r in rows})
    intro = (
        f"{first.n_test} queries per pair, a match is correct within {first.ground_truth}, "
        f"{'seeds' if 'seed' in shown else 'seed'} {seeds}. recall_at_1 is the fraction of "
        "correct matches (= precision at 100% recall). Protocol fingerprints (the images, "
        "ground truth, direction and validation places measured on; docs/metrics.md): "
        + ", ".join(f"{pair} {fp}" for pair, fp in protocols)
        + "."
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
        SELECTION_NOTE + VERSUS_NOTE[baseline is not None].format(base=base),
        "",
        *_headline(rows, differences or {}, shown, preferred, base),
        *_best_objective_note(rows, preferred),
        *_kept_at_start(selected_rows(rows)),
        *_same_models(same_models),
        "",
        *_seed_spread(rows, differences or {}, base),
        *_against_start(rows, to_start or {}),
        *_learning_curves(rows),
        "## Best setting per method, chosen on the test queries (optimistic)",
        "",
        *_cell_table(best_rows(rows), shown),
        "",
        "## Every cell",
        "",
        *_cell_table(rows, shown),
        "",
        *_not_converged(rows),
    ]
    return "\n".join(lines)


def _in_order(rows: list[ResultRow]) -> list[ResultRow]:
    return sorted(
        rows,
        key=lambda r: (r.season_pair, r.method, r.objective, *choice_order(r)[:2], r.ds, r.seed),
    )


def _markdown(head: tuple[str, ...], body: list[list[str]]) -> list[str]:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    return lines + ["| " + " | ".join(cells) + " |" for cells in body]


def _columns(columns: tuple[str, ...], shown: set[str]) -> tuple[str, ...]:
    return tuple(c for c in columns if c not in OPTIONAL or c in shown)


def _cell_table(rows: list[ResultRow], shown: set[str]) -> list[str]:
    cols = _columns(CELL_COLUMNS, shown)
    body = [
        [f"{v:.3f}" if isinstance(v, float) else str(v) for v in (getattr(r, c) for c in cols)]
        for r in _in_order(rows)
    ]
    return _markdown(cols, body)


def _ci(low: float, high: float) -> str:
    return "" if math.isnan(low) else f"[{low:.3f}, {high:.3f}]"


def _label(baseline: str | None) -> str:
    """How results.md names the baseline: a built-in method in capitals (PCA, LDA), a
    user's method or an outside set by its name."""
    if baseline is None:
        return "the baseline"
    return baseline.upper() if baseline in METHOD_NAMES else baseline


def _versus(row: ResultRow, differences: dict[str, Difference], base: str) -> tuple[str, str]:
    """(the difference to the baseline with its interval, its label) for the headline."""
    diff = differences.get(row.run)
    if _label(row.method) == base:
        return "", "baseline"
    if diff is None:
        return "", "n/a"
    return f"{diff.value:+.3f} [{diff.low:+.3f}, {diff.high:+.3f}]", diff.label


def _headline(
    rows: list[ResultRow],
    differences: dict[str, Difference],
    shown: set[str],
    preferred: set[str],
    base: str,
) -> list[str]:
    body = []
    reasons = selection_reasons(rows)
    for r in _in_order(selected_rows(rows)):
        versus, label = _versus(r, differences, base)
        optional = {"setting": r.setting, "ds": str(r.ds), "seed": str(r.seed)}
        body.append(
            [
                r.season_pair,
                r.method,
                r.objective
                + (" best" if r.run in preferred else "")
                + (" (its start)" if r.kept_epoch == 0 else ""),
                *(optional[c] for c in ("setting",) if c in shown),
                str(r.removed_pcs),
                *(optional[c] for c in ("ds", "seed") if c in shown),
                f"{r.val_recall_at_1:.3f}",
                reasons[r.run],
                f"{r.recall_at_1:.3f}",
                _ci(r.recall_at_1_ci_low, r.recall_at_1_ci_high),
                f"{r.auc_pr:.3f}",
                _ci(r.auc_pr_ci_low, r.auc_pr_ci_high),
                versus,
                label,
            ]
        )
    head = tuple(c.format(base=base) for c in _columns(HEADLINE_COLUMNS, shown))
    return _markdown(head, body)


def _spread(values: list[float]) -> str:
    """min-max for two seeds, the standard deviation for three or more."""
    if len(values) < 3:
        return f"{min(values):.3f}-{max(values):.3f}"
    return f"sd {float(np.std(values, ddof=1)):.3f}"


def _seed_spread(rows: list[ResultRow], differences: dict[str, Difference], base: str) -> list[str]:
    """results.md's seed section: per selected setting fitted with several seeds, the mean
    recall@1 over them, its spread, and each seed's paired difference to the baseline."""
    groups: dict[tuple, list[ResultRow]] = {}
    for r in selected_rows(rows):
        key = (r.season_pair, r.method, r.objective, r.setting, r.removed_pcs, r.ds)
        groups.setdefault(key, []).append(r)
    several = {k: sorted(v, key=lambda r: r.seed) for k, v in groups.items() if len(v) > 1}
    if not several:
        return []
    body = []
    for (pair, method, objective, setting, k, ds), mine in sorted(several.items()):
        recalls = [r.recall_at_1 for r in mine]
        diffs = [differences.get(r.run) for r in mine]
        body.append(
            [
                pair,
                method,
                objective,
                setting,
                str(k),
                str(ds),
                ", ".join(str(r.seed) for r in mine),
                f"{float(np.mean(recalls)):.3f}",
                _spread(recalls),
                "; ".join(f"{d.value:+.3f} ({d.label})" if d is not None else "n/a" for d in diffs),
            ]
        )
    head = (
        "season_pair",
        "method",
        "objective",
        "setting",
        "removed_pcs",
        "ds",
        "seeds",
        "mean recall_at_1",
        "spread",
        f"recall@1 - {base} per seed",
    )
    return [
        "## Seeds",
        "",
        "Each selected setting fitted with several seeds (``seeds``; the data, split and "
        "route follow ``seed`` and never change with them): the mean recall@1 over the "
        "seeds, its spread (min-max for two seeds, the standard deviation for three or "
        f"more) and each seed's paired difference to {base}. A difference between methods "
        "smaller than this spread is seed noise.",
        "",
        *_markdown(head, body),
        "",
    ]


def _learning_curves(rows: list[ResultRow]) -> list[str]:
    """results.md's learning curves (``split.train_places``): per pair, method and
    objective, recall@1 with its interval at each value of training places (single images,
    the validation-selected setting at each; several seeds: the mean, then the seeds'
    range)."""
    shortest = min((r.ds for r in rows), default=1)
    best = [r for r in selected_rows(rows) if r.ds == shortest and training_places(r) is not None]
    if not best:
        return []
    places = sorted({training_places(r) for r in best})
    table: dict[tuple, dict[int, list[ResultRow]]] = {}
    for r in _in_order(best):
        key = (r.season_pair, r.method, r.objective)
        table.setdefault(key, {}).setdefault(training_places(r), []).append(r)

    def cell(mine: list[ResultRow] | None, own_setting: bool) -> str:
        if not mine:
            return ""
        start = " (its start)" if all(r.kept_epoch == 0 for r in mine) else ""
        if len(mine) > 1:  # seeds
            values = [r.recall_at_1 for r in mine]
            return f"{float(np.mean(values)):.3f} ({_spread(values)}){start}"
        r = mine[0]
        text = f"{r.recall_at_1:.3f} {_ci(r.recall_at_1_ci_low, r.recall_at_1_ci_high)}{start}"
        return f"{text}, {plain_setting(r)}" if own_setting and plain_setting(r) else text

    body = []
    for key, by_places in table.items():
        # the setting validation chose: in its column when one for every value, else per cell
        chosen = {plain_setting(r) for rs in by_places.values() for r in rs}
        one = chosen.pop() if len(chosen) == 1 else ""
        cells = (cell(by_places.get(p), own_setting=not one) for p in places)
        body.append([*key, one, *cells])
    head = ("season_pair", "method", "objective", "setting", *(f"{p} places" for p in places))
    return [
        "## Learning curves",
        "",
        "recall@1 [95% CI] of each method fitted on that many of each season's training "
        "places (split.train_places, spread evenly over the training stretch; the "
        "validation and test places are the same for every value, so is the protocol), at "
        "the setting the validation places choose for each. Every value is rows of its own, "
        "never chosen among: more data is not a choice. figures/learning_curves.png draws "
        "them.",
        "",
        *_markdown(head, body),
        "",
    ]


def _against_start(rows: list[ResultRow], to_start: dict[str, Difference]) -> list[str]:
    """results.md's trained-against-start table: per selected row of a trained method, the
    epoch it kept, its recall@1 and its start's, and the paired difference."""
    trained = [r for r in _in_order(selected_rows(rows)) if r.run in to_start]
    if not trained:
        return []
    body = []
    for r in trained:
        d = to_start[r.run]
        body.append(
            [
                r.season_pair,
                r.method,
                r.objective,
                r.setting,
                str(r.seed),
                f"{r.kept_epoch} of {r.epochs_trained}",
                f"{r.recall_at_1:.3f}",
                f"{r.recall_at_1 - d.value:.3f}",
                "0 (the start itself)"
                if r.kept_epoch == 0
                else f"{d.value:+.3f} [{d.low:+.3f}, {d.high:+.3f}] ({d.label})",
            ]
        )
    head = ("season_pair", "method", "objective", "setting", "seed", "kept epoch")
    return [
        "## Trained against their start",
        "",
        "recall@1 of each trained method's kept model and of its start (the starting "
        "weights, untouched by training) on the same queries, and their paired difference "
        "with its 95% block-bootstrap interval: what training added. A model kept at its "
        "start is its start.",
        "",
        *_markdown((*head, "recall_at_1", "start's recall_at_1", "- start [95% CI]"), body),
        "",
    ]


def _kept_at_start(selected: list[ResultRow]) -> list[str]:
    """A line naming the trained rows whose kept model is their start (marked "its start"
    above): no epoch of training beat it on the validation places."""
    start = [r for r in _in_order(selected) if r.kept_epoch == 0]
    if not start:
        return []
    named = "; ".join(
        dict.fromkeys(
            f"{r.season_pair} {r.method} {r.objective}".rstrip()
            + (f" {r.setting}" if r.setting else "")
            + f" ({r.start}, {r.epochs_trained} epoch{'' if r.epochs_trained == 1 else 's'} "
            "trained)"
            for r in start
        )
    )
    return [
        "",
        "Kept at their start, untouched by training (no epoch beat it on the validation "
        f"places; marked its start): {named}.",
    ]


def _same_models(groups: list[list[ResultRow]]) -> list[str]:
    """A line per group of selected rows that are one model: identical scores and matches
    on every query."""
    lines = []
    several_seeds = len({r.seed for group in groups for r in group}) > 1
    for group in groups:
        named = ", ".join(f"{r.method} {r.objective}".rstrip() for r in group)
        at_start = all(r.kept_epoch == 0 for r in group) and len({r.start for r in group}) == 1
        why = f", all kept at their start ({group[0].start})" if at_start else ""
        places = {training_places(r) for r in group}
        where = group[0].season_pair
        if places != {None}:  # a learning curve's point
            where += f" at train_places={'/'.join(str(p) for p in sorted(places, key=str))}"
        if several_seeds:
            where += f" seed {group[0].seed}"
        lines.append(f"{where}: {named} score every query identically: one model{why}.")
    return ["", *lines] if lines else []


def same_models(rows: list[ResultRow], curve: Curves) -> list[list[ResultRow]]:
    """Groups of selected rows (a pair, ds and seed; other methods or objectives) whose
    every query's best score, correctness and match are identical: the same model under
    two names (the auto-encoders kept at one linear start)."""
    groups: dict[tuple, list[ResultRow]] = {}
    for r in _in_order(selected_rows(rows)):
        arrays = curve(r.run)
        key = (
            r.season_pair,
            r.ds,
            r.seed,
            arrays["best_scores"].tobytes(),
            arrays["best_correct"].tobytes(),
        )
        groups.setdefault(key, []).append(r)
    return [g for g in groups.values() if len({(r.method, r.objective) for r in g}) > 1]


def _best_objective_note(rows: list[ResultRow], preferred: set[str]) -> list[str]:
    """A line naming each auto-encoder's best objective per pair (marked "best" above)."""
    best = [r for r in rows if r.run in preferred]
    if not best:
        return []
    named = ", ".join(
        dict.fromkeys(f"{r.season_pair} {r.method} {r.objective}" for r in _in_order(best))
    )
    return ["", f"Best objective by validation recall@1 (marked best): {named}."]


def _not_converged(rows: list[ResultRow]) -> list[str]:
    stuck = [r for r in rows if not r.converged]
    if not stuck:
        return []
    cells = ", ".join(f"{r.season_pair} {r.method} k={r.removed_pcs}" for r in stuck)
    return [f"Not converged (stopped at the iteration limit, see sweep.log): {cells}.", ""]
