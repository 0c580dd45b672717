"""Exporting a sweep's cells (``experiments.export``): the sweep's pairs read again, each
chosen cell's descriptors from its saved encoder (or the outside files), matched again to
the top-K, and written as one folder (``vpr_jax.outputs.export``)."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
from pathlib import Path

import numpy as np

from experiments.cells import INCOMPLETE, match, run_name
from experiments.encoders import read_listing
from experiments.plan import Plan, make_plan
from experiments.run import load_pair
from vpr_jax.config import SweepConfig, config_from_dict
from vpr_jax.data.pair import PairData
from vpr_jax.encoders.saved import FIT_JSON, stored_encoder, suite_version
from vpr_jax.errors import UserError
from vpr_jax.files import replace_folder
from vpr_jax.method_table import SWEEPS_REMOVED_PCS
from vpr_jax.methods import Descriptors
from vpr_jax.outputs import export as files
from vpr_jax.outputs.logdir import config_yaml, saved_config
from vpr_jax.outputs.results import ResultRow, read_results, selected_rows
from vpr_jax.progress import Log

SavedEncoders = dict[tuple[str, str, str], list[tuple[list[int], Path]]]


def sweep_config(logdir: Path) -> SweepConfig:
    """The config a finished sweep in ``logdir`` ran with (its config.yaml), writing there."""
    cfg = config_from_dict(saved_config(logdir / "config.yaml"))
    return dataclasses.replace(cfg, logdir=str(logdir))


def saved_encoders(logdir: Path) -> SavedEncoders:
    """(pair, method, objective) -> [(counts it serves, folder)], from the sweep's listing."""
    out: SavedEncoders = {}
    for entry in read_listing(logdir) if (logdir / "encoders.csv").exists() else []:
        folder = Path(entry["folder"])
        if not (folder / FIT_JSON).is_file():
            continue  # moved or deleted since: its cells export without an encoder
        fit = json.loads((folder / FIT_JSON).read_text())
        key = (entry["pair"], fit["name"], fit["objective"])
        out.setdefault(key, []).append((fit["counts"], folder))
    return out


def folder_name(row: ResultRow, all_settings: bool) -> str:
    """The cell's run name less its pair; less the removed-PC count too unless
    ``all_settings`` (``pca``, ``pca_k005``, ``fae_cross_season``, ``lda_ds10``)."""
    k = row.removed_pcs if all_settings else None
    return run_name(row.season_pair, row.method, k, row.ds, row.objective).split("/", 1)[1]


def export(logdir: Path, out: Path, *, top_k: int, all_settings: bool, log: Log) -> Path:
    """Every chosen cell of the sweep in ``logdir`` (its validation-selected ones, or every
    one with ``all_settings``) as a folder under ``out``, ``top_k`` matches per query."""
    rows = read_results(logdir / "results.csv")
    chosen = rows if all_settings else selected_rows(rows)
    if not chosen:
        raise UserError(f"logdir {logdir} has no finished cell yet: let the sweep finish")
    plan = make_plan(sweep_config(logdir), log)
    encoders = saved_encoders(logdir)
    for db, query in plan.pairs:
        mine = [r for r in chosen if r.season_pair == f"{db}-{query}"]
        if not mine:
            continue
        pair = load_pair(plan, db, query)
        for row in sorted(mine, key=lambda r: r.run):
            name = folder_name(row, all_settings)
            recall = export_cell(plan, pair, row, _saved_folder(encoders, row), out, name, top_k)
            log(f"{pair.name}/{name}: recall@1 {recall:.3f} (sweep: {row.recall_at_1:.3f})")
    shutil.rmtree(out / INCOMPLETE, ignore_errors=True)
    log(f"exported {len(chosen)} cells to {out}")
    return out


def _saved_folder(encoders: SavedEncoders, row: ResultRow) -> Path | None:
    for counts, folder in encoders.get((row.season_pair, row.method, row.objective), []):
        if row.removed_pcs in counts:
            return folder
    return None


def cell_descriptors(
    plan: Plan, pair: PairData, row: ResultRow, folder: Path | None
) -> tuple[np.ndarray, np.ndarray]:
    """(database, queries) descriptors of the cell: the outside files' rows, or the saved
    encoder's output on the sweep's (preprocessed) images, called as the sweep called it."""
    if row.method in plan.outside:
        sides = plan.outside[row.method]
        return sides["database"].of(pair.names.db), sides["queries"].of(pair.names.query)
    if folder is None:
        raise UserError(
            f"{row.run}: its saved encoder is missing (logdir's encoders.csv lists none for "
            f"{row.method}): rerun the sweep to save it again"
        )
    stored = stored_encoder(folder, row.removed_pcs)
    return tuple(
        np.asarray(stored.encode(stored.params, images), np.float32)
        for images in (pair.db, pair.query)
    )


def export_cell(
    plan: Plan,
    pair: PairData,
    row: ResultRow,
    folder: Path | None,
    out: Path,
    name: str,
    top_k: int,
) -> float:
    """Write one cell's folder ``out/<pair>/<name>`` (aside, then moved into place), its
    encoder copied from ``folder``; returns the recall@1 of its ``pairs.txt`` (the share of
    queries whose first line is correct)."""
    cfg, staging = plan.cfg, out / INCOMPLETE / pair.name / name
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    db, query = cell_descriptors(plan, pair, row, folder)
    desc = Descriptors(
        method=row.method,
        removed_pcs=(row.removed_pcs,),
        starts=(0,),
        db=db,
        query=query,
        val_db=None,
        val_query=None,
        fit_seconds=math.nan,
        encode_ms_per_image=math.nan,
    )
    ((scores, idx),) = match(desc, pair, row.ds, (row.removed_pcs,), cfg, None, k=top_k)
    correct = pair.truth.correct(idx)
    for side, names in (("database", pair.names.db), ("queries", pair.names.query)):
        files.write_names(staging, side, names)
    if row.ds == 1:
        files.write_descriptors(staging, "database", db)
        files.write_descriptors(staging, "queries", query)
    files.write_retrieval(staging, pair.names.query, pair.names.db, scores, idx, correct)
    if folder is not None:
        selection = {
            "removed_pcs": row.removed_pcs,
            "val_recall_at_1": row.val_recall_at_1,
            "test_recall_at_1": row.recall_at_1,
            "selected": bool(row.selected),
            "run": row.run,
        }
        files.copy_encoder(folder, staging, selection)
    recall = float(correct[:, 0].sum() / len(correct))  # metrics.evaluate_matches' recall@1
    facts = _facts(plan.logdir, top_k, pair, row, folder, recall, db.shape)
    (staging / "README.txt").write_text(files.readme(facts, config_yaml(cfg)))
    replace_folder(staging, out / pair.name / name)
    return recall


def _facts(logdir, top_k, pair: PairData, row: ResultRow, folder, recall: float, shape) -> dict:
    setting = f"removed_pcs={row.removed_pcs}" if row.method in SWEEPS_REMOVED_PCS else "-"
    return {
        "exported from": f"{logdir} (run {row.run})",
        "suite version": suite_version(),
        "pair": f"{pair.name}: database {pair.db_season}, queries {pair.query_season}",
        "method": row.method + (f", objective {row.objective}" if row.objective else ""),
        "setting": setting
        + (" (chosen on the validation places)" if row.selected else " (not the chosen one)"),
        "sequence length": f"ds={row.ds}" + (" (sequence scores)" if row.ds > 1 else ""),
        "queries": f"{len(pair.query):,} (queries.txt), database {len(pair.db):,} (database.txt)",
        "ground truth": pair.truth.describe(),
        "validation recall@1": f"{row.val_recall_at_1:.4f} (results.csv)",
        "test recall@1": f"{row.recall_at_1:.4f} (results.csv); {recall:.4f} from pairs.txt",
        "descriptors": f"database.npy, queries.npy: float32, {shape[1]} features, cosine"
        if row.ds == 1
        else "none: sequence matching ranks sequences of descriptors, not single ones",
        "pairs": f"pairs.txt, scores.csv: top {top_k} per query, best first",
        "encoder": "this folder: vpr_jax.load_encoder(folder) -> (encode_fn, params)"
        if folder is not None
        else "none: outside descriptors (precomputed), or its saved folder was missing",
    }
