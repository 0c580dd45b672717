"""Where a sweep keeps what it fitted: each fit's state and ``fit.json`` as the fit ends
(``save_state``), and once the cells are scored each saved fit's ``encoder.json`` (the
served value the validation places chose) and the logdir's ``encoders.csv`` listing them
(``describe_saved``). ``vpr_jax.methods.loading.load_encoder`` reads them back."""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

import jax

from experiments.cells import run_name
from experiments.resolve import Fit
from vpr_jax.config import SweepConfig
from vpr_jax.data.preprocess import describe_preprocessing
from vpr_jax.encoders.saved import (
    FIT_JSON,
    describe_encoder,
    read_description,
    save_fitted,
    suite_version,
)
from vpr_jax.files import atomic_write_text
from vpr_jax.method_table import model_name
from vpr_jax.methods.settings import label as settings_label
from vpr_jax.outputs.logdir import ENCODERS_CSV, LISTING, fitted_root
from vpr_jax.outputs.results import ResultRow, read_results, swept_of
from vpr_jax.sharding import to_host


def save_state(fit: Fit, state: Any, cfg: SweepConfig, pair: str, fitted_dir: Path) -> None:
    """Keep what the method fitted in ``fitted_dir/<fit's folder>``, with its ``fit.json``,
    so ``vpr_jax.load_encoder`` gives it back (process 0; its ``encoder.json`` follows once
    the sweep's cells are scored, ``describe_saved``)."""
    state = jax.tree.map(to_host, state)  # on every process: it may gather
    if jax.process_index() != 0:
        return
    info = fit.method.info
    description = {
        "method": info.method,
        "name": info.name,
        "objective": fit.objective,
        "pair": pair,
        "settings": dict(fit.values),
        "cells": [{"run": p.run, "settings": p.swept, "served": p.values} for p in fit.served],
        "seed": fit.seed,
        "preprocessing": describe_preprocessing(
            cfg.preprocess, cfg.patchnorm.size, cfg.patchnorm.rounded
        ),
        "suite_version": suite_version(),
    }
    save_fitted(fitted_dir / fit.folder, state, description)


def encoders_csv(listing: list[dict]) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, LISTING, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    writer.writerows(listing)
    return out.getvalue()


def describe_encoders(root: Path, rows: list[ResultRow]) -> list[dict]:
    """Each saved encoder's ``encoder.json``, from its ``fit.json`` and the table: among the
    cells it serves (pca's removed counts), the one chosen on the validation places (single
    images), with its validation and test recall@1. Rewritten with every report, so a
    resumed sweep that adds counts moves the choice. Returns the descriptions, each with its
    folder."""
    shortest, listing = min(r.ds for r in rows), []
    by_run = {r.run: r for r in rows if r.ds == shortest}
    if not root.is_dir():
        return listing
    for pair in sorted({r.season_pair for r in rows}):
        for fit_file in sorted((root / pair).glob(f"*/{FIT_JSON}")):
            fit = read_description(fit_file.parent, FIT_JSON)
            mine = [
                (cell, by_run[run_name(pair, cell["run"], shortest)])
                for cell in fit.get("cells", [])
                if run_name(pair, cell["run"], shortest) in by_run
            ]
            if not mine:
                continue
            cell, chosen = max(
                mine, key=lambda t: (t[1].selected, t[1].val_recall_at_1, t[1].val_margin)
            )
            description = describe_encoder(
                fit_file.parent,
                {
                    "model": model_name(fit["name"], fit["objective"]),
                    "chosen": cell["served"],
                    "setting": chosen.setting,
                    "swept": swept_of(chosen),
                    "cell": settings_label(tuple(swept_of(chosen).items())),
                    "kept_epoch": chosen.kept_epoch,
                    "start": chosen.start,
                    "val_recall_at_1": chosen.val_recall_at_1,
                    "val_recall_at_1_by_served": {
                        settings_label(tuple(c["served"].items())): r.val_recall_at_1
                        for c, r in mine
                    },
                    "test_recall_at_1": chosen.recall_at_1,
                    "selected": bool(chosen.selected),
                    "run": chosen.run,
                },
            )
            listing.append(
                {
                    **description,
                    "method": fit["name"],
                    "selected": int(chosen.selected),
                    "folder": str(fit_file.parent),
                }
            )
    return listing


def describe_saved(logdir: Path, cfg: SweepConfig) -> None:
    """Every saved fit's ``encoder.json`` and the logdir's ``encoders.csv``, from every row
    of results.csv (rewritten whenever the sweep ends: a resumed sweep that adds values
    moves the choice)."""
    rows = read_results(logdir / "results.csv")
    if rows:
        listing = describe_encoders(fitted_root(cfg, logdir), rows)
        atomic_write_text(logdir / ENCODERS_CSV, encoders_csv(listing))
