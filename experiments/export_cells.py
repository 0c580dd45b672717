"""Exporting a sweep's cells (``experiments.export``): the sweep's pairs read again, each
chosen cell's descriptors from its saved encoder (a set of outside descriptors' too),
matched again to the top-K, and written as one folder (``vpr_jax.outputs.export``)."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
from pathlib import Path

import numpy as np

from experiments.cells import INCOMPLETE, match, run_name
from experiments.encoders import read_listing
from experiments.fitting import load_pair
from experiments.plan import Plan, make_plan
from vpr_jax.command_line import config_from_dict
from vpr_jax.config import SweepConfig
from vpr_jax.data.pair import PairData
from vpr_jax.encoders.saved import FIT_JSON, suite_version
from vpr_jax.errors import UserError
from vpr_jax.files import replace_folder
from vpr_jax.method_table import is_plugin, known_info
from vpr_jax.methods.descriptors import Descriptors, Part
from vpr_jax.methods.loading import stored_encoder
from vpr_jax.outputs import export as files
from vpr_jax.outputs.logdir import config_yaml, fitted_root, saved_config
from vpr_jax.outputs.results import (
    SWEEP_KEYS,
    ResultRow,
    cell_name,
    read_results,
    selected_rows,
    swept_of,
)
from vpr_jax.progress import Log

# README.txt lines of a single-image cell: its hloc file and how hloc reads it
HLOC_FEATS = (
    "global-feats.h5: the same rows L2-normalised (float32) in hloc's layout, a group per "
    "name of database.txt and queries.txt (a / in a name nests groups) holding "
    "global_descriptor; no name is both a database and a query image"
)
HLOC_USE = (
    "python -m hloc.pairs_from_retrieval --descriptors global-feats.h5 --output "
    "pairs-hloc.txt --num_matched {top_k} --db_list database.txt --query_list queries.txt: "
    "its dot product on these rows is the cosine, so it ranks as pairs.txt does, but drops "
    "pairs scoring below 0 (min_score=0)"
)
SavedEncoders = dict[str, tuple[Path, dict]]  # a cell's run (less ds) -> its fit's folder, served


def sweep_config(logdir: Path, plugins: tuple[str, ...] = ()) -> SweepConfig:
    """The config a finished sweep in ``logdir`` ran with (its config.yaml), writing there.
    A user's method it lists that ``plugins`` does not name: UserError, nothing imported."""
    cfg = config_from_dict(saved_config(logdir / "config.yaml"))
    unnamed = [m for m in cfg.methods if is_plugin(m) and known_info(m, plugins) is None]
    if unnamed:
        raise UserError(
            f"{logdir / 'config.yaml'} lists methods of a user's own, {', '.join(unnamed)}: "
            "a logdir is data, so nothing was imported; if you trust them, name them: "
            f"python -m experiments.export {logdir} plugins={','.join(unnamed)}"
        )
    return dataclasses.replace(cfg, logdir=str(logdir))


def saved_encoders(logdir: Path, root: Path) -> SavedEncoders:
    """Each cell's run (less its ds) -> the folder of the fit that serves it and what it
    serves it with, from the sweep's listing: folders under ``root`` (the logdir's own
    checkpoint folder) only."""
    out: SavedEncoders = {}
    for entry in read_listing(logdir) if (logdir / "encoders.csv").exists() else []:
        folder = Path(entry["folder"]).resolve()
        if not folder.is_relative_to(root):
            raise UserError(
                f"{logdir / 'encoders.csv'} lists the folder {entry['folder']}, outside this "
                f"logdir's checkpoint folder {root}: nothing read there; a sweep lists only its "
                "own folders: run the export from the folder the sweep ran in (a relative "
                "train.checkpoint_dir is taken from there), with the logdir as the sweep wrote it"
            )
        if not (folder / FIT_JSON).is_file():
            continue  # moved or deleted since: its cells export without an encoder
        fit = json.loads((folder / FIT_JSON).read_text())
        for cell in fit.get("cells", []):
            out[run_name(entry["pair"], cell["run"])] = (folder, cell["served"])
    return out


def _single_image_run(row: ResultRow) -> str:
    """The row's run without its sequence length: the run of its single-image cell."""
    ds = f"_ds{row.ds:02d}"
    return row.run.removesuffix(ds) if row.ds != 1 else row.run


def folder_name(row: ResultRow, all_settings: bool, data_seed: int) -> str:
    """The cell's run name less its pair; less the sweep's keys (the removed-PC count) too
    unless ``all_settings`` (``pca``, ``pca_k005``, ``fae_cross_season``, ``lda_ds10``)."""
    if all_settings:
        return row.run.split("/", 1)[1]
    swept = tuple((n, v) for n, v in swept_of(row).items() if n not in SWEEP_KEYS)
    seed = row.seed if row.seed != data_seed else None
    ds = f"_ds{row.ds:02d}" if row.ds != 1 else ""
    return cell_name(row.method, row.objective, swept, seed) + ds


def export(
    logdir: Path,
    out: Path,
    *,
    top_k: int,
    all_settings: bool,
    log: Log,
    plugins: tuple[str, ...] = (),
) -> Path:
    """Every chosen cell of the sweep in ``logdir`` (its validation-selected ones, or every
    one with ``all_settings``) as a folder under ``out``, ``top_k`` matches per query."""
    rows = read_results(logdir / "results.csv")
    chosen = rows if all_settings else selected_rows(rows)
    if not chosen:
        raise UserError(f"logdir {logdir} has no finished cell yet: let the sweep finish")
    cfg = sweep_config(logdir, plugins)
    encoders = saved_encoders(logdir, fitted_root(cfg, logdir))
    plan = make_plan(cfg, log)
    for db, query in plan.pairs:
        mine = [r for r in chosen if r.season_pair == f"{db}-{query}"]
        if not mine:
            continue
        pair = load_pair(plan, db, query)
        for row in sorted(mine, key=lambda r: r.run):
            name = folder_name(row, all_settings, plan.cfg.seed)
            saved = encoders.get(_single_image_run(row))
            recall = export_cell(plan, pair, row, saved, out, name, top_k, plugins)
            log(f"{pair.name}/{name}: recall@1 {recall:.3f} (sweep: {row.recall_at_1:.3f})")
    shutil.rmtree(out / INCOMPLETE, ignore_errors=True)
    log(f"exported {len(chosen)} cells to {out}")
    return out


def cell_descriptors(
    plan: Plan,
    pair: PairData,
    row: ResultRow,
    saved: tuple[Path, dict] | None,
    plugins: tuple[str, ...] = (),
) -> tuple[np.ndarray, np.ndarray]:
    """(database, queries) descriptors of the cell: the saved encoder's output on the
    sweep's (preprocessed) images, called as the sweep called it (a set of outside
    descriptors too: its rows)."""
    if saved is None:
        raise UserError(
            f"{row.run}: its saved encoder is missing (logdir's encoders.csv lists none for "
            f"{row.method}): rerun the sweep to save it again"
        )
    stored = stored_encoder(saved[0], served=saved[1], plugins=plugins)
    return tuple(
        np.asarray(stored.encode(stored.params, images), np.float32)
        for images in (pair.db, pair.query)
    )


def export_cell(
    plan: Plan,
    pair: PairData,
    row: ResultRow,
    saved: tuple[Path, dict] | None,
    out: Path,
    name: str,
    top_k: int,
    plugins: tuple[str, ...] = (),
) -> float:
    """Write one cell's folder ``out/<pair>/<name>`` (aside, then moved into place), its
    encoder copied from ``folder``; returns the recall@1 of its ``pairs.txt`` (the share of
    queries whose first line is correct)."""
    cfg, staging = plan.cfg, out / INCOMPLETE / pair.name / name
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    db, query = cell_descriptors(plan, pair, row, saved, plugins)
    folder = saved[0] if saved is not None else None
    desc = Descriptors(
        method=row.method,
        objective=row.objective,
        seed=row.seed,
        parts=(Part(swept=swept_of(row), run=name),),
        starts=(0,),
        db=db,
        query=query,
        val_db=None,
        val_query=None,
        fit_seconds=math.nan,
        encode_ms_per_image=math.nan,
    )
    ((scores, idx),) = match(desc, pair, row.ds, (0,), cfg, None, k=top_k)
    correct = pair.truth.correct(idx)
    for side, names in (("database", pair.names.db), ("queries", pair.names.query)):
        files.write_names(staging, side, names)
    if row.ds == 1:
        files.write_descriptors(staging, "database", db)
        files.write_descriptors(staging, "queries", query)
        files.write_global_features(staging, pair.names.db, db, pair.names.query, query)
    files.write_retrieval(staging, pair.names.query, pair.names.db, scores, idx, correct)
    if folder is not None:
        selection = {
            "chosen": saved[1],
            "setting": row.setting,
            "swept": swept_of(row),
            "val_recall_at_1": row.val_recall_at_1,
            "test_recall_at_1": row.recall_at_1,
            "selected": bool(row.selected),
            "run": row.run,
        }
        files.copy_encoder(folder, staging, selection)
    recall = float(correct[:, 0].sum() / len(correct))  # metrics.evaluate_matches' recall@1
    facts = _facts(plan, top_k, pair, row, folder, recall, db.shape)
    (staging / "README.txt").write_text(files.readme(facts, config_yaml(cfg)))
    replace_folder(staging, out / pair.name / name)
    return recall


def _facts(plan: Plan, top_k, pair: PairData, row: ResultRow, folder, recall: float, shape) -> dict:
    keys = [f"{k}={v}" for k, v in swept_of(row).items() if k in SWEEP_KEYS]
    setting = " ".join(x for x in (row.setting, *keys) if x) or "-"
    return {
        "exported from": f"{plan.logdir} (run {row.run})",
        "suite version": suite_version(),
        "pair": f"{pair.name}: database {pair.db_season}, queries {pair.query_season}",
        "method": row.method
        + (f", objective {row.objective}" if row.objective else "")
        + (f", seed {row.seed}" if row.seed != plan.cfg.seed else ""),
        "setting": setting
        + (" (chosen on the validation places)" if row.selected else " (not the chosen one)"),
        "sequence length": f"ds={row.ds}" + (" (sequence scores)" if row.ds > 1 else ""),
        "queries": f"{len(pair.query):,} (queries.txt), database {len(pair.db):,} (database.txt)",
        "ground truth": pair.truth.describe(),
        "protocol": f"{row.protocol} (results.csv: the fingerprint of the images, ground truth, "
        "direction and validation places these numbers were measured on; docs/metrics.md)",
        "validation recall@1": f"{row.val_recall_at_1:.4f} (results.csv)",
        "test recall@1": f"{row.recall_at_1:.4f} (results.csv); {recall:.4f} from pairs.txt",
        "descriptors": f"database.npy, queries.npy: float32, {shape[1]} features, as the "
        "encoder produced them (not normalised: the sweep ranked them by cosine)"
        if row.ds == 1
        else "none: sequence matching ranks sequences of descriptors, not single ones",
        "global features": HLOC_FEATS
        if row.ds == 1
        else "none (no global-feats.h5): hloc ranks single images, pairs.txt sequences",
        **({"with hloc": HLOC_USE.format(top_k=top_k)} if row.ds == 1 else {}),
        "pairs": f"pairs.txt, scores.csv: top {top_k} per query, best first",
        "encoder": "this folder: vpr_jax.load_encoder(folder) -> (encode_fn, params)"
        if folder is not None
        else "none: its saved folder was missing",
    }
