"""results.csv: one typed row per finished cell, rewritten atomically; the keys that name a
cell and its group, and the validation selection that marks each group's chosen row."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import NamedTuple

from vpr_jax.evaluation.metrics import SCALAR_NAMES
from vpr_jax.files import atomic_write_text

# The columns of results.csv, in order, with their types: one row per finished cell.
ResultRow = NamedTuple(
    "ResultRow",
    [
        ("season_pair", str),  # db-query, e.g. summer-fall
        ("db_season", str),
        ("query_season", str),
        ("method", str),
        ("objective", str),  # the auto-encoders' training objective; empty for other methods
        ("removed_pcs", int),  # 0 for methods without the removed-PC axis
        ("ds", int),  # sequence length; 1 = single images
        ("n_train", int),  # images the encoder was fitted on, both seasons
        ("n_test", int),  # queries
        ("tolerance", int),  # frames, for a tolerance ground truth; -1 for sets
        ("ground_truth", str),  # what defines a correct match: "+-2 frames", "within 25 m", ...
        *((name, float) for name in SCALAR_NAMES),  # the seven metrics (evaluation.metrics)
        ("recall_at_1_ci_low", float),  # 95% block-bootstrap interval (evaluation.bootstrap)
        ("recall_at_1_ci_high", float),
        ("auc_pr_ci_low", float),
        ("auc_pr_ci_high", float),
        ("val_recall_at_1", float),  # on the validation places: what chooses the setting
        ("val_auc_pr", float),  # breaks ties of val_recall_at_1 (it saturates on easy routes)
        ("selected", int),  # 1: the best on validation of its pair x method x objective x ds
        ("fit_seconds", float),
        ("encode_ms_per_image", float),
        ("n_iter", int),  # iterations of an iterative fit (epochs for the auto-encoders)
        ("converged", int),  # ICA: 0 when it stopped at ica.max_iter; 1 for the others
        ("stopped_early", int),  # auto-encoders: 1 when early stopping ended the training
        ("seed", int),
        ("run", str),  # the cell's TensorBoard run, relative to the logdir
    ],
)
COLUMNS: tuple[str, ...] = ResultRow._fields
COLUMN_TYPES: dict[str, type] = ResultRow.__annotations__
TIMING_NAMES = ("fit_seconds", "encode_ms_per_image")


class CellKey(NamedTuple):
    """What identifies a cell: a resumed sweep skips the cells whose key is in the table."""

    season_pair: str
    method: str
    objective: str  # "" for methods without the objective axis
    removed_pcs: int  # 0 for methods without the removed-PC axis
    ds: int  # sequence length; 1 = single images


def cell_key(row: ResultRow) -> CellKey:
    return CellKey(
        season_pair=row.season_pair,
        method=row.method,
        objective=row.objective,
        removed_pcs=row.removed_pcs,
        ds=row.ds,
    )


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
    """The cells a setting is chosen among: one pair, method, objective and ds, whatever
    removed-PC count."""

    season_pair: str
    method: str
    objective: str
    ds: int


def group_key(row: ResultRow) -> GroupKey:
    return GroupKey(
        season_pair=row.season_pair, method=row.method, objective=row.objective, ds=row.ds
    )


def mark_selected(rows: list[ResultRow]) -> list[ResultRow]:
    """``selected = 1`` on the row of each group (``group_key``) with the best validation
    recall@1, ties broken by validation AUC-PR, then by the fewest removed PCs (rows without
    a validation score lose); 0 on every other row."""
    best: dict[GroupKey, ResultRow] = {}
    for row in sorted(rows, key=lambda r: r.removed_pcs):
        key, score = group_key(row), _val_score(row)
        if key not in best or score > _val_score(best[key]):
            best[key] = row
    chosen = {id(r) for r in best.values()}
    return [r._replace(selected=int(id(r) in chosen)) for r in rows]


def _val_score(row: ResultRow) -> tuple[float, float]:
    return tuple(-1.0 if math.isnan(v) else v for v in (row.val_recall_at_1, row.val_auc_pr))


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
    """Per (pair, method, objective, ds), the row with the best metric (smallest
    removed_pcs on ties)."""
    best: dict[GroupKey, ResultRow] = {}
    for row in sorted(rows, key=lambda r: r.removed_pcs):
        key = group_key(row)
        if key not in best or getattr(row, metric) > getattr(best[key], metric):
            best[key] = row
    return list(best.values())


def selected_rows(rows: list[ResultRow]) -> list[ResultRow]:
    """The validation-selected row of every pair x method x objective x ds."""
    return [r for r in mark_selected(rows) if r.selected]


def best_objectives(rows: list[ResultRow]) -> set[str]:
    """The runs of the selected rows that are their method's best objective: per pair,
    method and ds with more than one objective, the selected row with the best validation
    recall@1 (then AUC-PR; the first objective on a tie), as ``mark_selected`` ranks."""
    groups: dict[tuple, list[ResultRow]] = {}
    for row in selected_rows(rows):
        if row.objective:
            groups.setdefault((row.season_pair, row.method, row.ds), []).append(row)
    return {max(group, key=_val_score).run for group in groups.values() if len(group) > 1}


def baseline_of(row: ResultRow, selected: list[ResultRow]) -> ResultRow | None:
    """The seed's baseline for a selected row: its pair's selected PCA row at the same ds."""
    for other in selected:
        if (other.season_pair, other.method, other.ds) == (row.season_pair, "pca", row.ds):
            return other
    return None
