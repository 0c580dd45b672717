"""What a sweep's logdir holds to take away: every saved encoder, one line each.

    python -m experiments.encoders LOGDIR

Prints pair, method (and objective), its setting (swept settings, the removed-PC count
chosen on the validation places, the seed), its validation recall@1, ``*`` on the setting
the validation places chose, and the folder; ``vpr_jax.load_encoder(folder)`` gives the
encoder back as ``(encode_fn, params)``. Reads ``LOGDIR/encoders.csv``, which the sweep writes with
its report. Bad input: one line on stderr, exit code 2.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

from vpr_jax.errors import UserError, exit_code
from vpr_jax.outputs.logdir import ENCODERS_CSV, LISTING


def read_listing(logdir: Path) -> list[dict]:
    """The rows of ``LOGDIR/encoders.csv``; UserError when the logdir has none."""
    path = Path(logdir).expanduser() / ENCODERS_CSV
    if not path.exists():
        where = "is no folder" if not path.parent.is_dir() else f"has no {ENCODERS_CSV}"
        raise UserError(
            f"logdir {path.parent} {where}: name the logdir of a sweep that finished (its "
            "report lists the encoders), e.g. python -m experiments.encoders runs/quick"
        )
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if rows and set(LISTING) - set(rows[0]):
        raise UserError(f"{path} is not a listing of encoders: rerun the sweep to rewrite it")
    return rows


def format_listing(rows: list[dict]) -> str:
    header = ("pair", "method", "setting", "val recall@1", "chosen", "folder")
    lines = [
        (
            r["pair"],
            r["method"] + (f" {r['objective']}" if r["objective"] else ""),
            _setting(r),
            f"{float(r['val_recall_at_1']):.3f}",
            "*" if r["selected"] == "1" else "",
            r["folder"] + ("" if Path(r["folder"]).is_dir() else "  (missing)"),
        )
        for r in rows
    ]
    widths = [max(len(str(x)) for x in column) for column in zip(header, *lines, strict=True)]
    return "\n".join(
        "  ".join(str(x).ljust(w) for x, w in zip(line, widths, strict=True)).rstrip()
        for line in (header, *lines)
    )


def _setting(row: dict) -> str:
    parts = [
        row["cell"] if row["cell"] != row["setting"] else row["setting"],
        f"seed {row['seed']}" if row["seed"] not in ("", "0") else "",
        "(its start)" if row.get("kept_epoch") == "0" else "",
    ]
    return " ".join(p for p in parts if p)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("logdir", help="a sweep's logdir, e.g. runs/quick")
    args = parser.parse_args(argv)
    return exit_code(lambda: print(format_listing(read_listing(Path(args.logdir)))))


if __name__ == "__main__":
    sys.exit(main())
