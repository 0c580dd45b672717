"""results.csv (one row per finished cell, rewritten atomically) and the results.md table."""

from __future__ import annotations

import csv
import io
import math
import os
import tempfile
from pathlib import Path
from typing import NamedTuple

from vpr_jax.metrics import SCALAR_NAMES

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
        *((name, float) for name in SCALAR_NAMES),  # the seven metrics (vpr_jax.metrics)
        ("recall_at_1_ci_low", float),  # 95% block-bootstrap interval (vpr_jax.bootstrap)
        ("recall_at_1_ci_high", float),
        ("auc_pr_ci_low", float),
        ("auc_pr_ci_high", float),
        ("val_recall_at_1", float),  # on the validation places: what chooses the setting
        ("val_auc_pr", float),  # breaks ties of val_recall_at_1 (it saturates on easy routes)
        ("selected", int),  # 1: the best on validation of its pair x method x objective x ds
        ("fit_seconds", float),
        ("encode_ms_per_image", float),
        ("n_iter", int),  # iterations of an iterative fit (epochs for the auto-encoders)
        ("converged", int),  # 0 when the fit stopped at its iteration limit
        ("seed", int),
        ("run", str),  # the cell's TensorBoard run, relative to the logdir
    ],
)
COLUMNS: tuple[str, ...] = ResultRow._fields
COLUMN_TYPES: dict[str, type] = ResultRow.__annotations__
TIMING_NAMES = ("fit_seconds", "encode_ms_per_image")
# Columns added since the first tables were written, with the value those tables meant.
ADDED_COLUMNS = {
    "ds": lambda row: "1",  # sequence length: 1 is single-image matching
    "objective": lambda row: "reconstruct" if row["method"] in ("fae", "cae") else "",
    **{
        name: (lambda row: "nan")
        for name in (
            "recall_at_1_ci_low",
            "recall_at_1_ci_high",
            "auc_pr_ci_low",
            "auc_pr_ci_high",
            "val_recall_at_1",
            "val_auc_pr",
        )
    },
    "selected": lambda row: "0",  # marked again whenever the table is written
    "extended_precision": lambda row: "nan",
    "ground_truth": lambda row: f"+-{row['tolerance']} frames",
}


def atomic_write_text(path: Path, text: str) -> None:
    """Write via a temporary file in the same folder, fsynced, and ``os.replace``, then
    fsync the folder: all or nothing, also across a power loss."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", newline="") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)  # the rename itself survives a power loss
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


CellKey = tuple[str, str, str, int, int]  # (season pair, method, objective, removed PCs, ds)


def cell_key(row: ResultRow) -> CellKey:
    """What identifies a cell: a resumed sweep skips the cells whose key is in the table."""
    return row.season_pair, row.method, row.objective, row.removed_pcs, row.ds


def _parse(row: dict) -> ResultRow:
    """A csv row of text (or a row of values) as a typed ResultRow."""
    return ResultRow(
        *(COLUMN_TYPES[col](row[col] if col in row else ADDED_COLUMNS[col](row)) for col in COLUMNS)
    )


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
            missing = set(COLUMNS) - set(ADDED_COLUMNS) - set(reader.fieldnames or ())
            if missing:
                raise ValueError(f"lacks columns {', '.join(sorted(missing))}")
            rows = []
            for row in reader:
                try:
                    rows.append(_parse(row))
                except (TypeError, ValueError):
                    raise ValueError(f"line {reader.line_num} is not a row of numbers") from None
            return rows
        except csv.Error as err:
            raise ValueError(str(err)) from None


GroupKey = tuple[str, str, str, int]  # (season pair, method, objective, ds)


def group_key(row: ResultRow) -> GroupKey:
    """The cells a setting is chosen among: one pair, method, objective and ds, whatever
    removed-PC count."""
    return row.season_pair, row.method, row.objective, row.ds


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
    best: dict[tuple[str, str, str, int], ResultRow] = {}
    for row in sorted(rows, key=lambda r: r.removed_pcs):
        key = (row.season_pair, row.method, row.objective, row.ds)
        if key not in best or getattr(row, metric) > getattr(best[key], metric):
            best[key] = row
    return list(best.values())


def selected_rows(rows: list[ResultRow]) -> list[ResultRow]:
    """The validation-selected row of every pair x method x objective x ds."""
    return [r for r in mark_selected(rows) if r.selected]


def baseline_of(row: ResultRow, selected: list[ResultRow]) -> ResultRow | None:
    """The seed's baseline for a selected row: its pair's selected PCA row at the same ds."""
    for other in selected:
        if (other.season_pair, other.method, other.ds) == (row.season_pair, "pca", row.ds):
            return other
    return None


def _ci(low: float, high: float) -> str:
    return "" if math.isnan(low) else f"[{low:.3f}, {high:.3f}]"


def markdown_table(rows: list[ResultRow], differences: dict | None = None) -> str:
    """results.md: the validation-selected setting per method (recall@1 and AUC-PR with
    their 95% intervals, and the paired difference to PCA that ``differences`` holds per
    run: a ``vpr_jax.bootstrap.Difference``), then the best count chosen on the test
    queries (optimistic), then every cell. The ds column appears once a sweep holds
    sequence-matching cells."""
    differences = differences or {}
    sequences = any(r.ds != 1 for r in rows)
    ds_col = ("ds",) if sequences else ()
    cols = (
        "season_pair",
        "method",
        "objective",
        "removed_pcs",
        *ds_col,
        "recall_at_1",
        "auc_pr",
        "recall_at_100_precision",
        "recall_at_5",
        "recall_at_10",
        "fit_seconds",
        "encode_ms_per_image",
    )

    def order(rs: list[ResultRow]) -> list[ResultRow]:
        return sorted(rs, key=lambda r: (r.season_pair, r.method, r.objective, r.removed_pcs, r.ds))

    def table(rs: list[ResultRow]) -> list[str]:
        lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        for r in order(rs):
            values = [getattr(r, c) for c in cols]
            cells = [f"{v:.3f}" if isinstance(v, float) else str(v) for v in values]
            lines.append("| " + " | ".join(cells) + " |")
        return lines

    def headline(rs: list[ResultRow]) -> list[str]:
        head = (
            "season_pair",
            "method",
            "objective",
            "removed_pcs",
            *ds_col,
            "val_recall_at_1",
            "recall_at_1",
            "95% CI",
            "auc_pr",
            "95% CI",
            "recall@1 - PCA [95% CI]",
            "vs PCA",
        )
        lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for r in order(rs):
            diff = differences.get(r.run)
            if r.method == "pca":
                versus, label = "", "baseline"
            elif diff is None:
                versus, label = "", "n/a"
            else:
                versus = f"{diff.value:+.3f} [{diff.low:+.3f}, {diff.high:+.3f}]"
                label = diff.label
            cells = [
                r.season_pair,
                r.method,
                r.objective,
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
            lines.append("| " + " | ".join(cells) + " |")
        return lines

    first = rows[0]._asdict() if rows else {}
    lines = [
        "# Results",
        "",
        f"{first.get('n_test', '?')} queries per pair, a match is correct within "
        f"{first.get('ground_truth', '?')}, seed {first.get('seed', '?')}. recall_at_1 is the "
        "fraction of correct "
        "matches (= precision at 100% recall).",
        "",
        "## Each method at the setting chosen on the validation places",
        "",
        "The removed-PC count with the best recall@1 on the validation places (the end of "
        "each season's training stretch; for a benchmark trained on its database, its last "
        "queries, held out of the test), scored on the test places. Intervals: 95%, block "
        "bootstrap over the queries. vs PCA: a paired bootstrap of the difference to the "
        "pair's selected PCA row on the same queries; better / worse when its interval "
        "excludes 0.",
        "",
        *headline(selected_rows(rows)),
        "",
        "## Best removed-PC count per method, chosen on the test queries (optimistic)",
        "",
        *table(best_rows(rows)),
        "",
        "## Every cell",
        "",
        *table(rows),
        "",
    ]
    # For the auto-encoders converged=0 only says early stopping did not end the training.
    stuck = [r for r in rows if not r.converged and r.method not in ("fae", "cae")]
    if stuck:
        cells = ", ".join(f"{r.season_pair} {r.method} k={r.removed_pcs}" for r in stuck)
        lines += [
            f"Not converged (stopped at the iteration limit, see sweep.log): {cells}.",
            "",
        ]
    return "\n".join(lines)
