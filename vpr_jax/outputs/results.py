"""results.csv: one typed row per finished cell, rewritten atomically; the keys that name a
cell and its group, and the validation selection that marks each group's chosen setting.

A group (one pair, method, objective and sequence length) holds a choice per setting and
removed count; a choice holds a row per seed (``seeds``). The choice with the best mean
validation recall@1 over its seeds is ``selected``, every one of its rows; a tie goes to the
best mean validation margin (``metrics.match_margin``: recall@1 saturates on easy places,
the margin does not), then to the simpler choice, the first in ``choice_order``.
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
import typing
from pathlib import Path
from typing import NamedTuple

import numpy as np

from vpr_jax.evaluation.metrics import SCALAR_NAMES
from vpr_jax.files import atomic_write_text
from vpr_jax.method_table import model_label
from vpr_jax.methods.contract import REPORT_COLUMNS, Report
from vpr_jax.methods.settings import label


class SweepKey(NamedTuple):
    """How a value of a sweep key is written in names: a run's or folder's suffix, a label
    in the run log and results.md."""

    suffix: str
    label: str


# The sweep's own keys a method takes as a setting of the same name (the removed count
# reaches pca, ica and diff_pca), each with a results.csv column.
SWEEP_KEYS = {"removed_pcs": SweepKey(suffix="_k{:03d}", label="k={}")}


def _column_type(name: str) -> type:
    """A report field's column type (a flag is written 0 or 1)."""
    hints = typing.get_type_hints(Report)
    kind = (
        hints[name]
        if name in hints
        else typing.get_type_hints(getattr(Report, name).fget)["return"]
    )
    return int if kind is bool else kind


# The columns of results.csv, in order, with their types: one row per finished cell.
ResultRow = NamedTuple(
    "ResultRow",
    [
        ("season_pair", str),  # db-query, e.g. summer-fall
        ("db_season", str),
        ("query_season", str),
        ("method", str),
        ("objective", str),  # the auto-encoders' training objective; empty for other methods
        ("setting", str),  # the method's swept settings, e.g. n_components=64; empty: none
        ("settings", str),  # every swept setting of the cell, JSON; the two columns around
        # it are made from it (``swept_columns``)
        *((key, int) for key in SWEEP_KEYS),  # each sweep key's value (0: not a setting)
        ("ds", int),  # sequence length; 1 = single images
        ("n_train", int),  # images the encoder was fitted on, both seasons
        ("n_test", int),  # queries
        ("tolerance", int),  # frames, for a tolerance ground truth; -1 for sets
        ("ground_truth", str),  # what defines a correct match: "+-2 frames", "within 25 m", ...
        ("protocol", str),  # fingerprint of the images, ground truth, direction and split
        # the row was measured on (vpr_jax.evaluation.protocol, docs/metrics.md)
        *((name, float) for name in SCALAR_NAMES),  # the seven metrics (evaluation.metrics)
        ("recall_at_1_ci_low", float),  # 95% block-bootstrap interval (evaluation.bootstrap)
        ("recall_at_1_ci_high", float),
        ("auc_pr_ci_low", float),
        ("auc_pr_ci_high", float),
        ("val_recall_at_1", float),  # on the validation places: what chooses the setting
        ("val_auc_pr", float),
        ("val_margin", float),  # breaks ties of val_recall_at_1 (it saturates on easy places)
        ("selected", int),  # 1: the best setting on validation of its pair x method x objective
        # x ds (every seed's row of it)
        ("fit_seconds", float),
        ("encode_ms_per_image", float),
        *((name, _column_type(name)) for name in REPORT_COLUMNS),  # what the fit reported
        # (methods.contract.Report): n_iter, converged, stopped_early, kept_epoch (0: the
        # start, untouched by training), epochs_trained, start; docs/guide.md says each
        ("seed", int),  # the fit's seed (seeds); the data's (seed) for methods that draw none
        ("run", str),  # the cell's TensorBoard run, relative to the logdir
    ],
)
COLUMNS: tuple[str, ...] = ResultRow._fields


def _optional_int(text) -> int | None:
    return None if text in ("", None) else int(text)


COLUMN_TYPES: dict[str, type] = {
    name: _optional_int if kind == int | None else kind
    for name, kind in ResultRow.__annotations__.items()
}
TIMING_NAMES = ("fit_seconds", "encode_ms_per_image")


def cell_name(method: str, objective: str, swept, seed: int | None = None) -> str:
    """A run's or a fitted state's name from its swept settings ((name, value) pairs in
    the method's order): their label, then the sweep's keys as their suffixes
    (``ica_n_components=64_seed1_k005``)."""
    plain = tuple((n, v) for n, v in swept if n not in SWEEP_KEYS)
    suffix = "".join(SWEEP_KEYS[n].suffix.format(v) for n, v in swept if n in SWEEP_KEYS)
    return model_label(method, objective, label(plain), seed) + suffix


def swept_columns(swept: dict) -> dict:
    """A cell's results.csv columns of its swept values (by name): all of them as JSON (the
    ``settings`` column), their label less the sweep's keys, and each sweep key's value (0
    for a cell without it)."""
    return {
        "setting": label(tuple((n, v) for n, v in swept.items() if n not in SWEEP_KEYS)),
        "settings": json.dumps(swept),
        **{key: int(swept.get(key, 0)) for key in SWEEP_KEYS},
    }


def swept_hparams(swept: dict) -> dict:
    """A cell's TensorBoard hparams of its swept values: their label less the sweep's
    keys, and each sweep key's value (a float: an hparam's axis)."""
    columns = swept_columns(swept)
    return {"setting": columns["setting"], **{key: float(columns[key]) for key in SWEEP_KEYS}}


def report_columns(report: Report) -> dict:
    """A fit's report as its results.csv columns."""
    values = {name: getattr(report, name) for name in REPORT_COLUMNS}
    return {k: int(v) if isinstance(v, bool) else v for k, v in values.items()}


def swept_of(row: ResultRow) -> dict:
    """A row's swept values, by name (its ``settings`` column, JSON)."""
    return json.loads(row.settings) if row.settings else {}


def sweep_labels(row: ResultRow) -> list[str]:
    """The sweep's keys the row's cell has, as the run log and results.md name them (k=5)."""
    values = swept_of(row)
    return [SWEEP_KEYS[k].label.format(values[k]) for k in SWEEP_KEYS if k in values]


def cell_key(row: ResultRow) -> str:
    """What identifies a cell: its run (the pair, the method, its settings, seed and ds);
    a resumed sweep skips the cells whose run is in the table."""
    return row.run


def _parse(row: dict) -> ResultRow:
    """A csv row of text (or a row of values) as a typed ResultRow."""
    return ResultRow(**{col: COLUMN_TYPES[col](row[col]) for col in COLUMNS})


def read_results(path: Path) -> list[ResultRow]:
    """Rows of an existing results.csv (typed), or [] when there is none.

    Raises ValueError naming the first problem when the file is not such a table.
    """
    path = Path(path)
    if not path.exists():
        return []
    with open(path, newline="") as f:
        try:
            reader = csv.DictReader(f)
            missing = set(COLUMNS) - set(reader.fieldnames or ())
            if missing:
                raise ValueError(f"lacks columns {', '.join(sorted(missing))}")
            if tuple(reader.fieldnames) != COLUMNS:
                raise ValueError("has other columns than this version writes")
            rows = []
            for row in reader:
                try:
                    rows.append(_parse(row))
                except (TypeError, ValueError):
                    raise ValueError(f"line {reader.line_num} is not a row of numbers") from None
            return rows
        except csv.Error as err:
            raise ValueError(str(err)) from None


class GroupKey(NamedTuple):
    """The cells a setting is chosen among: one pair, method, objective and ds (and value
    of each setting whose values are rows of their own: the training places), whatever
    setting, removed-PC count and seed."""

    season_pair: str
    method: str
    objective: str
    ds: int
    rows: tuple = ()  # (name, value) of the row keys the cell has (ROW_KEYS)


# Settings of the sweep whose values are rows of their own, never chosen among: the
# training places of a learning curve (split.train_places).
ROW_KEYS = ("train_places",)


def row_values(row: ResultRow) -> tuple:
    """(name, value) of the row keys the row's cell has."""
    values = swept_of(row)
    return tuple((k, values[k]) for k in ROW_KEYS if k in values)


def plain_setting(row: ResultRow) -> str:
    """The row's setting less the row keys (the training places of a learning curve)."""
    values = swept_of(row)
    if not any(k in values for k in ROW_KEYS):
        return row.setting
    keep = tuple((k, v) for k, v in values.items() if k not in (*SWEEP_KEYS, *ROW_KEYS))
    return label(keep)


def training_places(row: ResultRow) -> int | None:
    """The training places the row's method was fitted on (a learning curve's point);
    None: every training place."""
    return swept_of(row).get("train_places")


def largest_places(rows: list[ResultRow]) -> list[ResultRow]:
    """The rows of a learning curve at its largest value of training places (and every row
    without one): what the views of a sweep show beside the learning curves."""
    most: dict[tuple, int] = {}
    for r in rows:
        key = (r.season_pair, r.method, r.objective)
        most[key] = max(most.get(key, 0), training_places(r) or 0)
    return [
        r
        for r in rows
        if training_places(r) is None
        or training_places(r) == most[(r.season_pair, r.method, r.objective)]
    ]


def group_key(row: ResultRow) -> GroupKey:
    return GroupKey(
        season_pair=row.season_pair,
        method=row.method,
        objective=row.objective,
        ds=row.ds,
        rows=row_values(row),
    )


def natural_order(text: str) -> tuple:
    """``n_components=64`` before ``n_components=128``: numbers compare as numbers."""
    return tuple((0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", text))


def choice_order(row: ResultRow) -> tuple:
    """The order ties are decided in: settings in natural order, then the smallest values
    of the sweep's keys (the fewest removed PCs), then the seed."""
    values = swept_of(row)
    return (natural_order(row.setting), tuple(values.get(k, 0) for k in SWEEP_KEYS), row.seed)


class Choice(NamedTuple):
    """One setting and removed count of a group: its rows, one per seed."""

    rows: tuple[ResultRow, ...]

    def mean(self, metric: str) -> float:
        return float(np.mean([getattr(r, metric) for r in self.rows]))

    def val_score(self) -> tuple[float, float]:
        """The mean validation recall@1 and margin over seeds: what selects (rows without
        validation scores count -inf: they lose)."""
        scores = [_val_score(r) for r in self.rows]
        return tuple(float(np.mean(column)) for column in zip(*scores, strict=True))


def _val_score(row: ResultRow) -> tuple[float, float]:
    return tuple(-math.inf if math.isnan(v) else v for v in (row.val_recall_at_1, row.val_margin))


SELECTED_BY = ("validation recall@1", "validation margin", "order (all tied)", "one choice")


def selection_reasons(rows: list[ResultRow]) -> dict[str, str]:
    """Per run, what decided its group's selection (``decided_by``)."""
    return {
        r.run: decided_by(group) for group in choices(rows).values() for c in group for r in c.rows
    }


def decided_by(group: list[Choice]) -> str:
    """What decided a group's selection (``SELECTED_BY``): its validation recall@1, the
    margin among the settings tied on it, or their order where both tie (or are missing)."""
    if len(group) == 1:
        return SELECTED_BY[3]
    scores = sorted((c.val_score() for c in group), reverse=True)
    if scores[0][0] != scores[1][0]:
        return SELECTED_BY[0]
    return SELECTED_BY[1] if scores[0][1] != scores[1][1] else SELECTED_BY[2]


def choices(rows: list[ResultRow]) -> dict[GroupKey, list[Choice]]:
    """Each group's choices in ``choice_order``, each with its rows in seed order."""
    by_group: dict[GroupKey, dict[tuple, list[ResultRow]]] = {}
    for row in sorted(rows, key=choice_order):
        by_group.setdefault(group_key(row), {}).setdefault(row.settings, []).append(row)
    return {g: [Choice(tuple(c)) for c in cs.values()] for g, cs in by_group.items()}


def mark_selected(rows: list[ResultRow]) -> list[ResultRow]:
    """``selected = 1`` on every row of each group's choice with the best mean validation
    recall@1, then margin (the first choice on a tie); 0 on every other row."""
    chosen = {
        id(r) for group in choices(rows).values() for r in max(group, key=Choice.val_score).rows
    }
    return [r._replace(selected=int(id(r) in chosen)) for r in rows]


def append_results(path: Path, new_rows: list[ResultRow]) -> list[ResultRow]:
    """Add rows to results.csv in one atomic rewrite, each group's selected row marked
    again (``mark_selected``); a crash leaves the old file whole."""
    rows = mark_selected(read_results(path) + [_parse(r._asdict()) for r in new_rows])
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(COLUMNS)
    writer.writerows(rows)
    atomic_write_text(path, buf.getvalue())
    return rows


def best_rows(rows: list[ResultRow], metric: str = "recall_at_1") -> list[ResultRow]:
    """Per (pair, method, objective, ds), the rows of the choice with the best mean metric
    over seeds (the first on a tie): chosen on what it reports, so optimistic."""
    return [
        r for group in choices(rows).values() for r in max(group, key=lambda c: c.mean(metric)).rows
    ]


def selected_rows(rows: list[ResultRow]) -> list[ResultRow]:
    """The validation-selected rows of every pair x method x objective x ds."""
    return [r for r in mark_selected(rows) if r.selected]


def best_objectives(rows: list[ResultRow]) -> set[str]:
    """The runs of the selected rows that are their method's best objective: per pair,
    method and ds with more than one objective, the selected choice with the best mean
    validation recall@1 (then margin; the first objective on a tie)."""
    groups: dict[tuple, dict[str, list[ResultRow]]] = {}
    for row in selected_rows(rows):
        if row.objective:
            key = (row.season_pair, row.method, row.ds, row_values(row))
            groups.setdefault(key, {}).setdefault(row.objective, []).append(row)
    return {
        r.run
        for group in groups.values()
        if len(group) > 1
        for r in max((Choice(tuple(v)) for v in group.values()), key=Choice.val_score).rows
    }


def baseline_method(
    rows: list[ResultRow], baseline: str, outside: tuple[str, ...] = ()
) -> str | None:
    """What results.md's paired differences are to: the sweep's ``baseline`` (the paper's
    PCA by default) when the sweep ran it, else the first set of outside descriptors
    (``outside``, in the order given) that has rows, else None (no differences)."""
    methods = {r.method for r in rows}
    return next((m for m in (baseline, *outside) if m in methods), None)


def baseline_of(row: ResultRow, selected: list[ResultRow], baseline: str) -> ResultRow | None:
    """The baseline of a selected row: the ``baseline`` method's selected row of its pair
    at the same ds (and training places), of the same seed where it has several."""
    at = (row.season_pair, baseline, row.ds, row_values(row))
    mine = [
        other
        for other in selected
        if (other.season_pair, other.method, other.ds, row_values(other)) == at
    ]
    same_seed = [other for other in mine if other.seed == row.seed]
    return (same_seed or mine or [None])[0]
