"""results.md, the sweep's tables in markdown (``markdown_table``), from results.csv's rows
and what ``experiments.report`` computes from the cells' curve.npz. Its sections: the intro
(queries, ground truth, seeds, protocol fingerprints); each method at the setting chosen on
the validation places (recall@1 and AUC-PR with their 95% intervals, what decided the choice,
the paired difference to the baseline, or why there is none), with notes on the settings
other than the defaults, each auto-encoder's best objective, trained models kept at their
start and selected rows that are one model; the spread over seeds; trained methods against
their start; the learning curves (``split.train_places``; a point not scored says why);
the best setting per method chosen on the test queries (optimistic); every cell; the cells
that did not converge."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from vpr_jax.evaluation.bootstrap import Difference
from vpr_jax.method_table import NAMES as METHOD_NAMES
from vpr_jax.outputs.results import (
    SWEEP_KEYS,
    ResultRow,
    baseline_of,
    best_objectives,
    best_rows,
    choice_order,
    largest_places,
    plain_setting,
    selected_rows,
    selection_reasons,
    sweep_labels,
    training_places,
)

Curves = Callable[[str], dict[str, np.ndarray]]  # run -> its curve.npz arrays
# (pair, method, objective, training places) -> why a learning curve's point was not scored
NotScored = dict[tuple[str, str, str, int], str]

# What names a cell in a table: its pair, method, objective and settings, ds and seed.
CELL_NAME_COLUMNS = ("season_pair", "method", "objective", "setting", *SWEEP_KEYS, "ds", "seed")
CELL_COLUMNS = (
    *CELL_NAME_COLUMNS,
    "recall_at_1",
    "auc_pr",
    "recall_at_100_precision",
    "recall_at_5",
    "recall_at_10",
    "fit_seconds",
    "encode_ms_per_image",
)
HEADLINE_COLUMNS = (
    *CELL_NAME_COLUMNS,
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
    False: (
        "No paired differences (n/a in the vs column): they are to the pair's selected rows "
        "of the baseline, {wanted} (baseline={name}), or without it of the first outside "
        "set, and this sweep has neither: add {name} to methods, or set baseline to a "
        "method the sweep runs."
    ),
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
    *,
    wanted: str = "",
    not_scored: NotScored | None = None,
    changed: dict[str, str] | None = None,
) -> str:
    """results.md: the validation-selected setting per method (recall@1 and AUC-PR with
    their 95% intervals, what decided the choice, and the paired difference to the
    ``baseline`` method (PCA, or the first outside set) that ``differences`` holds per run;
    ``wanted``: the sweep's ``baseline``, named where the sweep lacks it), the methods run
    with settings other than their defaults (``changed``: method -> ``whiten=64``), the
    spread over seeds where there are several, the learning curves (a point ``not_scored``
    gives a reason for: that reason), then the best setting chosen on the test queries
    (optimistic), then every cell. The setting, ds and seed columns appear once a sweep has
    more than one value of them."""
    base = _label(baseline)
    shown = _shown(rows)
    # runs marked "best": a learning curve's at its largest training places, the others'
    # objectives there
    preferred = best_objectives(largest_places(rows))
    versus = _versus_texts(rows, differences or {}, baseline, wanted)
    lines = [
        "# Results",
        "",
        _intro(rows, shown),
        "",
        "## Each method at the setting chosen on the validation places",
        "",
        SELECTION_NOTE
        + VERSUS_NOTE[baseline is not None].format(base=base, wanted=_label(wanted), name=wanted),
        "",
        *_headline(rows, versus, shown, preferred, base),
        *_changed_settings(rows, changed or {}),
        *_best_objective_note(rows, preferred),
        *_kept_at_start(selected_rows(rows)),
        *_same_models(same_models),
        "",
        *_seed_spread(rows, differences or {}, base),
        *_against_start(rows, to_start or {}),
        *_learning_curves(rows, not_scored or {}),
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


def _intro(rows: list[ResultRow], shown: set[str]) -> str:
    """results.md's first paragraph: queries, ground truth, seeds, protocol fingerprints."""
    if not rows:
        return "No cells yet."
    first = rows[0]
    seeds = ", ".join(str(s) for s in sorted({r.seed for r in rows}))
    protocols = sorted({(r.season_pair, r.protocol) for r in rows})
    return (
        f"{first.n_test} queries per pair, a match is correct within {first.ground_truth}, "
        f"{'seeds' if 'seed' in shown else 'seed'} {seeds}. recall_at_1 is the fraction of "
        "correct matches (= precision at 100% recall). Protocol fingerprints (the images, "
        "ground truth, direction and validation places measured on; docs/metrics.md): "
        + ", ".join(f"{pair} {fp}" for pair, fp in protocols)
        + "."
    )


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


def _versus_texts(
    rows: list[ResultRow],
    differences: dict[str, Difference],
    baseline: str | None,
    wanted: str,
) -> dict[str, tuple[str, str]]:
    """Per selected run, the headline's (difference to the baseline with its interval, its
    label); where there is none, why: the baseline's own rows, no baseline in the sweep,
    no baseline row to pair with (its pair, ds and training places), other queries."""
    selected = selected_rows(rows)
    base = _label(baseline)
    out = {}
    for row in selected:
        diff = differences.get(row.run)
        if baseline is None:
            out[row.run] = "", f"n/a: no {_label(wanted)} in this sweep"
        elif row.method == baseline:
            out[row.run] = "", "baseline"
        elif diff is not None:
            out[row.run] = f"{diff.value:+.3f} [{diff.low:+.3f}, {diff.high:+.3f}]", diff.label
        elif baseline_of(row, selected, baseline) is None:
            out[row.run] = "", f"n/a: no {base} row to pair with"
        else:
            out[row.run] = "", f"n/a: other queries than {base}'s"
    return out


def _headline(
    rows: list[ResultRow],
    versus: dict[str, tuple[str, str]],
    shown: set[str],
    preferred: set[str],
    base: str,
) -> list[str]:
    body = []
    reasons = selection_reasons(rows)
    for r in _in_order(selected_rows(rows)):
        optional = {"setting": r.setting, "ds": str(r.ds), "seed": str(r.seed)}
        body.append(
            [
                r.season_pair,
                r.method,
                r.objective
                + (" best" if r.run in preferred else "")
                + (" (its start)" if r.kept_epoch == 0 else ""),
                *(optional[c] for c in ("setting",) if c in shown),
                *(str(getattr(r, k)) for k in SWEEP_KEYS),
                *(optional[c] for c in ("ds", "seed") if c in shown),
                f"{r.val_recall_at_1:.3f}",
                reasons[r.run],
                f"{r.recall_at_1:.3f}",
                _ci(r.recall_at_1_ci_low, r.recall_at_1_ci_high),
                f"{r.auc_pr:.3f}",
                _ci(r.auc_pr_ci_low, r.auc_pr_ci_high),
                *versus[r.run],
            ]
        )
    head = tuple(c.format(base=base) for c in _columns(HEADLINE_COLUMNS, shown))
    return _markdown(head, body)


def _changed_settings(rows: list[ResultRow], changed: dict[str, str]) -> list[str]:
    """A line naming the settings other than their defaults that no column shows (given
    on the command line or by the preset), per method of the table."""
    methods = {r.method for r in rows}
    named = "; ".join(f"{m} {text}" for m, text in changed.items() if m in methods)
    if not named:
        return []
    return [
        "",
        f"Settings other than the defaults (given on the command line or by the preset; the "
        f"setting column shows those swept): {named}.",
    ]


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
        key = (r.season_pair, r.method, r.objective, r.setting, r.settings, r.ds)
        groups.setdefault(key, []).append(r)
    several = {k: sorted(v, key=lambda r: r.seed) for k, v in groups.items() if len(v) > 1}
    if not several:
        return []
    body = []
    for (pair, method, objective, setting, _, ds), mine in sorted(several.items()):
        recalls = [r.recall_at_1 for r in mine]
        diffs = [differences.get(r.run) for r in mine]
        body.append(
            [
                pair,
                method,
                objective,
                setting,
                *(str(getattr(mine[0], k)) for k in SWEEP_KEYS),
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
        *SWEEP_KEYS,
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


def _learning_curves(rows: list[ResultRow], not_scored: NotScored) -> list[str]:
    """results.md's learning curves (``split.train_places``): per pair, method and
    objective, recall@1 with its interval at each value of training places (single images,
    the validation-selected setting at each; several seeds: the mean, then the seeds'
    range; a point not scored: why, from ``not_scored``)."""
    shortest = min((r.ds for r in rows), default=1)
    best = [r for r in selected_rows(rows) if r.ds == shortest and training_places(r) is not None]
    if not best:
        return []
    places = sorted({training_places(r) for r in best} | {k[3] for k in not_scored})
    table: dict[tuple, dict[int, list[ResultRow]]] = {}
    for r in _in_order(best):
        key = (r.season_pair, r.method, r.objective)
        table.setdefault(key, {}).setdefault(training_places(r), []).append(r)
    for key in sorted(k[:3] for k in not_scored):  # a curve never scored: its row too
        table.setdefault(key, {})

    def cell(key: tuple, p: int, own_setting: bool) -> str:
        mine = table[key].get(p)
        if not mine:
            why = not_scored.get((*key, p))
            return "not scored ({})".format(why.replace("|", "\\|")) if why else ""
        start = " (its start)" if all(r.kept_epoch == 0 for r in mine) else ""
        if len(mine) > 1:  # seeds
            values = [r.recall_at_1 for r in mine]
            return f"{float(np.mean(values)):.3f} ({_spread(values)}){start}"
        r = mine[0]
        text = f"{r.recall_at_1:.3f} {_ci(r.recall_at_1_ci_low, r.recall_at_1_ci_high)}{start}"
        return f"{text}, {plain_setting(r)}" if own_setting and plain_setting(r) else text

    body = []
    for key, by_places in sorted(table.items()):
        # the setting validation chose: in its column when one for every value, else per cell
        chosen = {plain_setting(r) for rs in by_places.values() for r in rs}
        one = chosen.pop() if len(chosen) == 1 else ""
        cells = (cell(key, p, own_setting=not one) for p in places)
        body.append([*key, one, *cells])
    head = ("season_pair", "method", "objective", "setting", *(f"{p} places" for p in places))
    return [
        "## Learning curves",
        "",
        "recall@1 [95% CI] of each method fitted on that many of each season's training "
        "places (split.train_places, spread evenly over the training stretch; the "
        "validation and test places are the same for every value, so is the protocol), at "
        "the setting the validation places choose for each. Every value is rows of its own, "
        "never chosen among: more data is not a choice. A value a method could not be "
        "scored at says why (sweep.log has the note of each run). "
        "figures/learning_curves.png draws them.",
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
    """A line naming each auto-encoder's best objective per pair (marked "best" above): one
    per method, a learning curve's at its largest training places."""
    best = [r for r in rows if r.run in preferred]
    if not best:
        return []
    named = ", ".join(
        dict.fromkeys(f"{r.season_pair} {r.method} {r.objective}" for r in _in_order(best))
    )
    where = (
        "; a learning curve's at its largest training places"
        if any(training_places(r) is not None for r in best)
        else ""
    )
    return ["", f"Best objective by validation recall@1 (marked best{where}): {named}."]


def _not_converged(rows: list[ResultRow]) -> list[str]:
    stuck = [r for r in rows if not r.converged]
    if not stuck:
        return []
    cells = ", ".join(
        " ".join(x for x in (r.season_pair, r.method, r.setting, *sweep_labels(r)) if x)
        for r in stuck
    )
    return [f"Not converged (stopped at the iteration limit, see sweep.log): {cells}.", ""]
