"""What a sweep reports once its cells are written: results.md, the figures and one summary
TensorBoard run per season pair, all rebuilt from results.csv and the cells' curve.npz (this
run's cells and every earlier one's), so a resumed sweep reports the whole table. results.md's
tables are built by ``experiments.results_md``; the paired differences they show, here."""

from __future__ import annotations

import dataclasses
import functools
import re
import shutil
import traceback
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from experiments import resolve
from experiments.cells import INCOMPLETE, block_length
from experiments.results_md import Curves, markdown_table, same_models
from vpr_jax.config import SweepConfig, plain
from vpr_jax.errors import UserError, first_line
from vpr_jax.evaluation.bootstrap import Difference, paired_recall_difference
from vpr_jax.evaluation.metrics import SCALAR_NAMES, pr_curve
from vpr_jax.files import atomic_write_text, replace_folder
from vpr_jax.method_table import METHODS, NAMES, model_label
from vpr_jax.methods import settings as method_settings
from vpr_jax.methods.contract import ROWS
from vpr_jax.outputs.palette import (
    OBJECTIVE_ORDER,
    chart_groups,
    compare_labels,
    curve_label,
    label_of,
)
from vpr_jax.outputs.plots import (
    NotScored,
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
    choices,
    largest_places,
    read_results,
    selected_rows,
    sweep_labels,
    swept_of,
    training_places,
)
from vpr_jax.outputs.tb import CompareSeries, SummaryCell, write_method_run, write_pair_summary
from vpr_jax.progress import RunLog
from vpr_jax.untrusted import check_npy_fits

SUMMARY = "summary"  # logdir/summary/<pair>: each pair's selected cells in one run
COMPARE = "compare"  # logdir/compare/<method>: a run per method, its tags per pair


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

    methods = (*NAMES, *cfg.plugin, *cfg.precomputed)
    missing = functools.cache(lambda: not_scored(logdir / "sweep.log", rows, methods))
    steps = {
        "results.md": lambda: atomic_write_text(
            logdir / "results.md",
            markdown_table(
                rows,
                *differences_to_baseline(rows, curve, cfg),
                same_models(rows, curve),
                differences_to_start(rows, curve, cfg),
                wanted=cfg.baseline,
                not_scored=missing(),
                changed=changed_settings(cfg, {r.method for r in rows}),
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
            lambda path: learning_curves_figure(rows, path, missing()), "learning_curves.png"
        )
    return steps


# sweep.log's note on cells a fit could not serve (experiments.fitting), and a run name's
# training places (a learning curve's point)
_NOT_SCORED = re.compile(r"^note: (\S+) (.+?): not scored: (.+)$")
_PLACES = re.compile(r"(?:^|_)train_places=(\d+)(?=_|$)")


def not_scored(log: Path, rows: list[ResultRow], methods: Iterable[str]) -> NotScored:
    """The learning curves' points without rows whose runs sweep.log notes as not scored
    (``note: <pair> <runs>: not scored: <why>``, ``experiments.fitting``), by pair, method,
    objective and training places: the first run's reason, with the count of runs where
    several (each removed count, seed or setting). A run is the method and objective whose
    name (``model_label``; the rows', then ``methods`` x the objectives) is the longest
    start of it; a note of a resumed sweep's earlier run counts once."""
    if not log.exists():
        return {}
    labels = {curve_label(r): (r.method, r.objective) for r in rows}
    for method in methods:
        for objective in OBJECTIVE_ORDER:  # "" before the paper's objective: the same name
            labels.setdefault(model_label(method, objective), (method, objective))
    found: dict[tuple, dict[str, str]] = {}
    for line in log.read_text(errors="replace").splitlines():
        note = _NOT_SCORED.match(line)
        for run in note.group(2).split(", ") if note else ():
            places = _PLACES.search(run)
            names = [n for n in labels if run == n or run.startswith(n + "_")]
            if places and names:
                key = (note.group(1), *labels[max(names, key=len)], int(places.group(1)))
                found.setdefault(key, {})[run] = note.group(3)
    scored = {(r.season_pair, r.method, r.objective, training_places(r)) for r in rows}
    return {key: _reason(why) for key, why in found.items() if key not in scored}


def _reason(why: dict[str, str]) -> str:
    """The reason of a point's first run not scored, and how many were where several."""
    first = next(iter(why.values()))
    return first if len(why) == 1 else f"{first}; {len(why)} runs, sweep.log has each"


def changed_settings(cfg: SweepConfig, methods: Iterable[str]) -> dict[str, str]:
    """Per built-in method of ``methods`` (in the method table's order): its settings in
    ``cfg`` other than their defaults (its ``Settings``'; a training setting's: ``train.*``)
    that no column of results.md shows (not a sweep key, an axis or the objective), as
    ``whiten=64``."""
    out = {}
    for name in (m for m in NAMES if m in methods):
        method = resolve.load(METHODS[name])
        schema, given = method.settings, getattr(cfg, name)
        if not dataclasses.is_dataclass(schema):
            continue
        shown = {*SWEEP_KEYS, *(k for k, kind in method.axes(schema()).items() if kind == ROWS)}
        changed = tuple(
            (f.name, given[f.name])
            for f in dataclasses.fields(schema)
            if f.name in given
            and f.name not in shown
            and not method_settings.is_axis(schema, f.name, given[f.name])
            and plain(given[f.name]) != plain(_default(f, cfg))
        )
        if changed:
            out[name] = method_settings.label(changed)
    return out


def _default(field: dataclasses.Field, cfg: SweepConfig):
    """A setting's default: its field's, or for a training setting without one the sweep's
    ``train.*`` (which fills it in)."""
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    if field.default is None and hasattr(cfg.train, field.name):
        return getattr(cfg.train, field.name)
    return field.default


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
        path = (logdir / run / "curve.npz").resolve()
        fix = "rerun the sweep into a new logdir=PATH"
        if not path.is_relative_to(logdir.resolve()):
            raise UserError(f"{logdir / 'results.csv'} names the run {run}, outside it: {fix}")
        check_npy_fits(path, str(path), fix)  # a logdir may come from elsewhere
        with np.load(path, allow_pickle=False) as z:
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
    colours them, each run's tags under its chart group (``palette.chart_groups``: at most
    seven runs a chart, each its own colour); a method without the removed-PC axis is a
    flat line over its pair's counts."""
    shortest = min(r.ds for r in rows)
    every = [r for r in rows if r.ds == shortest]
    single = largest_places(every)
    staging = logdir / INCOMPLETE / COMPARE
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    groups = chart_groups(single)
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
            group=groups[label],
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
    values = swept_of(row)
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
