"""results.csv (one row per finished cell, rewritten atomically) and the results.md table."""

from __future__ import annotations

import csv
import io
import os
import tempfile
from pathlib import Path

COLUMNS = (
    "season_pair", "db_season", "query_season", "method", "removed_pcs", "ds", "n_train",
    "n_test", "tolerance", "recall_at_1", "precision_at_full_recall", "auc_pr",
    "recall_at_100_precision", "recall_at_5", "recall_at_10", "fit_seconds",
    "encode_ms_per_image", "n_iter", "converged", "seed", "run",
)
INT_COLUMNS = {"removed_pcs", "ds", "n_train", "n_test", "tolerance", "n_iter", "converged",
               "seed"}
# Columns added since the first tables were written, with the value those tables meant.
ADDED_COLUMNS = {"ds": "1"}  # sequence length: 1 is single-image matching
TEXT_COLUMNS = {"season_pair", "db_season", "query_season", "method", "run"}


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


def cell_key(row: dict) -> tuple[str, str, int, int]:
    return row["season_pair"], row["method"], int(row["removed_pcs"]), int(row["ds"])


def _parse(row: dict) -> dict:
    out = {}
    for col in COLUMNS:
        value = row[col] if col in row else ADDED_COLUMNS[col]
        out[col] = value if col in TEXT_COLUMNS else int(value) if col in INT_COLUMNS \
            else float(value)
    return out


def read_results(path: Path) -> list[dict]:
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


def append_results(path: Path, new_rows: list[dict]) -> list[dict]:
    """Add rows to results.csv in one atomic rewrite; a crash leaves the old file whole."""
    rows = read_results(path) + [_parse({c: r[c] for c in COLUMNS}) for r in new_rows]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(path, buf.getvalue())
    return rows


def best_rows(rows: list[dict], metric: str = "recall_at_1") -> list[dict]:
    """Per (pair, method, ds), the row with the best metric (smallest removed_pcs on ties)."""
    best: dict[tuple[str, str, int], dict] = {}
    for row in sorted(rows, key=lambda r: r["removed_pcs"]):
        key = (row["season_pair"], row["method"], row["ds"])
        if key not in best or row[metric] > best[key][metric]:
            best[key] = row
    return list(best.values())


def markdown_table(rows: list[dict]) -> str:
    """results.md: the best removed-PC count per method (and sequence length), then every
    cell. The ds column appears once a sweep holds sequence-matching cells."""
    sequences = any(r["ds"] != 1 for r in rows)
    cols = ("season_pair", "method", "removed_pcs", *(("ds",) if sequences else ()),
            "recall_at_1", "auc_pr", "recall_at_100_precision", "recall_at_5", "recall_at_10",
            "fit_seconds", "encode_ms_per_image")

    def table(rs: list[dict]) -> list[str]:
        lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        for r in sorted(rs, key=lambda r: (r["season_pair"], r["method"], r["removed_pcs"],
                                           r["ds"])):
            cells = [f"{r[c]:.3f}" if isinstance(r[c], float) else str(r[c]) for c in cols]
            lines.append("| " + " | ".join(cells) + " |")
        return lines

    first = rows[0] if rows else {}
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
    stuck = [r for r in rows if not r["converged"]]
    if stuck:
        cells = ", ".join(f"{r['season_pair']} {r['method']} k={r['removed_pcs']}" for r in stuck)
        lines += [
            f"Not converged (stopped at the iteration limit, see sweep.log): {cells}.",
            "",
        ]
    return "\n".join(lines)
