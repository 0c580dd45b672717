"""results.csv (one row per finished cell, rewritten atomically) and the results.md table."""

from __future__ import annotations

import csv
import io
import os
import tempfile
from pathlib import Path
from typing import NamedTuple

from vpr_jax.metrics import SCALAR_NAMES

# The columns of results.csv, in order, with their types: one row per finished cell.
ResultRow = NamedTuple("ResultRow", [
    ("season_pair", str),  # db-query, e.g. summer-fall
    ("db_season", str),
    ("query_season", str),
    ("method", str),
    ("objective", str),  # the auto-encoders' training objective; empty for other methods
    ("removed_pcs", int),  # 0 for methods without the removed-PC axis
    ("ds", int),  # sequence length; 1 = single images
    ("n_train", int),  # images the encoder was fitted on, both seasons
    ("n_test", int),  # queries
    ("tolerance", int),
    *((name, float) for name in SCALAR_NAMES),  # the six metrics (vpr_jax.metrics)
    ("fit_seconds", float),
    ("encode_ms_per_image", float),
    ("n_iter", int),  # iterations of an iterative fit (epochs for the auto-encoders)
    ("converged", int),  # 0 when the fit stopped at its iteration limit
    ("seed", int),
    ("run", str),  # the cell's TensorBoard run, relative to the logdir
])
COLUMNS: tuple[str, ...] = ResultRow._fields
COLUMN_TYPES: dict[str, type] = ResultRow.__annotations__
TIMING_NAMES = ("fit_seconds", "encode_ms_per_image")
# Columns added since the first tables were written, with the value those tables meant.
ADDED_COLUMNS = {
    "ds": lambda row: "1",  # sequence length: 1 is single-image matching
    "objective": lambda row: "reconstruct" if row["method"] in ("fae", "cae") else "",
}


def atomic_write_text(path: Path, text: str) -> None:
    """Write via a temporary file in the same folder and ``os.replace``: all or nothing."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", newline="") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


CellKey = tuple[str, str, str, int, int]  # (season pair, method, objective, removed PCs, ds)


def cell_key(row: ResultRow) -> CellKey:
    """What identifies a cell: a resumed sweep skips the cells whose key is in the table."""
    return row.season_pair, row.method, row.objective, row.removed_pcs, row.ds


def _parse(row: dict) -> ResultRow:
    """A csv row of text (or a row of values) as a typed ResultRow."""
    return ResultRow(*(COLUMN_TYPES[col](row[col] if col in row else ADDED_COLUMNS[col](row))
                       for col in COLUMNS))  # fmt: skip


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


def append_results(path: Path, new_rows: list[ResultRow]) -> list[ResultRow]:
    """Add rows to results.csv in one atomic rewrite; a crash leaves the old file whole."""
    rows = read_results(path) + [_parse(r._asdict()) for r in new_rows]
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


def markdown_table(rows: list[ResultRow]) -> str:
    """results.md: the best removed-PC count per method (and sequence length), then every
    cell. The ds column appears once a sweep holds sequence-matching cells."""
    sequences = any(r.ds != 1 for r in rows)
    cols = ("season_pair", "method", "objective", "removed_pcs", *(("ds",) if sequences else ()),
            "recall_at_1", "auc_pr", "recall_at_100_precision", "recall_at_5", "recall_at_10",
            "fit_seconds", "encode_ms_per_image")

    def table(rs: list[ResultRow]) -> list[str]:
        lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        for r in sorted(rs, key=lambda r: (r.season_pair, r.method, r.objective, r.removed_pcs,
                                           r.ds)):
            values = [getattr(r, c) for c in cols]
            cells = [f"{v:.3f}" if isinstance(v, float) else str(v) for v in values]
            lines.append("| " + " | ".join(cells) + " |")
        return lines

    first = rows[0]._asdict() if rows else {}
    lines = [
        "# Results",
        "",
        f"{first.get('n_test', '?')} queries per pair, tolerance +-{first.get('tolerance', '?')} "
        f"frames, seed {first.get('seed', '?')}. recall_at_1 is the fraction of correct "
        "matches (= precision at 100% recall).",
        "",
        "## Best removed-PC count per method (chosen on the test pairs: optimistic)",
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
