"""One sweep cell, in one direction: a method's descriptors -> matches -> metrics -> its
TensorBoard run and results.csv row.

A cell is (season pair, method, objective, swept settings, sequence length ds, seed), its
run's name; the objective is the auto-encoders' (empty for the other methods). ``match``
turns descriptors into each query's top-K database matches: for ds = 1 one blockwise cosine
pass scores every cell's feature suffix at once (a removed-PC count's); for ds > 1
sequence matching runs on one suffix. ``save_cell`` evaluates the matches and writes the
cell; ``save_descriptors`` does both for every cell of one fit's descriptors still to do.
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np
from jax.sharding import Mesh

from vpr_jax.config import SweepConfig
from vpr_jax.data.ground_truth import Tolerance
from vpr_jax.data.pair import PairData
from vpr_jax.evaluation.bootstrap import cell_intervals
from vpr_jax.evaluation.matching import top_k_matches
from vpr_jax.evaluation.metrics import Evaluation, evaluate_matches
from vpr_jax.evaluation.sequence import sequence_top_k_cosine, velocities
from vpr_jax.files import replace_folder
from vpr_jax.methods.descriptors import Descriptors, Part
from vpr_jax.outputs.results import (
    ResultRow,
    append_results,
    report_columns,
    sweep_labels,
    swept_columns,
    swept_hparams,
)
from vpr_jax.outputs.tb import match_examples, write_cell_run
from vpr_jax.progress import Log

TOP_K = 10  # matches kept per query: enough for recall@10
INCOMPLETE = ".incomplete"  # TensorBoard runs being written; moved into place when whole
TopK = tuple[np.ndarray, np.ndarray]  # (scores, database indices), each (n_queries, K)


def _part(desc: Descriptors, pair: PairData, part: str):
    """(queries, database, query ids, database ids) of the test or the validation places."""
    if part == "test":
        return desc.query, desc.db, pair.query_ids, pair.db_ids
    return desc.val_query, desc.val_db, pair.val_query_ids, pair.val_db_ids


def _top_k(query, db, k: int, starts: tuple[int, ...], cfg: SweepConfig, mesh: Mesh | None):
    """``top_k_matches`` in the config's blocks and precision (``matching.*``)."""
    matching = cfg.matching
    return top_k_matches(
        query,
        db,
        k,
        starts=starts,
        block_size=matching.block_size,
        mesh=mesh,
        precision=matching.precision,
    )


def match(
    desc: Descriptors,
    pair: PairData,
    ds: int,
    starts: tuple[int, ...],
    cfg: SweepConfig,
    mesh: Mesh | None,
    part: str = "test",
    k: int = TOP_K,
) -> list[TopK]:
    """The top-``k`` matches of every query for each feature-suffix start in ``starts`` (a
    cell's: ``desc.starts``), in that order; ``part="val"``: of the validation queries
    against the validation database.

    ds = 1: plain cosine, one blockwise pass for all starts, split over the mesh. ds > 1:
    sequence matching (``vpr_jax.evaluation.sequence``) of ds frames on each suffix, on one
    device.
    """
    query, db, query_ids, db_ids = _part(desc, pair, part)
    if ds == 1:
        scores, idx = _top_k(query, db, k, starts, cfg, mesh)
        return list(zip(scores, idx, strict=True))
    seq = cfg.sequence
    return [
        sequence_top_k_cosine(
            query[:, start:],
            db[:, start:],
            ds,
            query_ids=query_ids,
            db_ids=db_ids,
            vels=velocities(seq.v_min, seq.v_max, seq.v_step),
            contrast_window=seq.contrast_window,
            uniqueness_window=seq.uniqueness_window,
            k=k,
            precision=cfg.matching.precision,
        )
        for start in starts
    ]


def run_name(pair: str, run: str, ds: int = 1) -> str:
    """``summer-fall/pca_k005``, ``summer-fall/fae_cross_season``,
    ``summer-fall/ica_n_components=64_k005``; sequence cells add ``_ds10``. ``run``: the
    cell's ``Part.run``."""
    name = f"{pair}/{run}"
    return name if ds == 1 else f"{name}_ds{ds:02d}"


def _write_run(
    logdir: Path,
    name: str,
    cfg: SweepConfig,
    pair: PairData,
    desc: Descriptors,
    cell: int,
    ds: int,
    top: TopK,
    ev: Evaluation,
    start: Evaluation | None = None,
) -> None:
    """The cell's TensorBoard run, written aside and moved into place whole (``start``: a
    trained model's start on the same queries, whose correctness curve.npz keeps as
    ``start_correct``)."""
    staging = logdir / INCOMPLETE / name
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    write_cell_run(
        staging,
        ev,
        scalars={
            "timing/fit_seconds": desc.fit_seconds,
            "timing/encode_ms_per_image": desc.encode_ms_per_image,
            "fit/n_iter": desc.report.n_iter,
            "fit/converged": int(desc.report.converged),
            "fit/stopped_early": int(desc.report.stopped_early),
        },
        hparams={
            "season_pair": pair.name,
            "method": desc.method,
            "objective": desc.objective,
            **swept_hparams(desc.parts[cell].swept),
            "ds": float(ds),
            "seed": float(desc.seed),
        },
        trial_id=name,
        n_thresholds=cfg.tb.pr_thresholds,
        examples=match_examples(
            pair.query, pair.db, pair.truth, top[1][:, 0], cfg.tb.n_match_examples
        ),
        basis_images=desc.basis[cell],
        basis_tag=f"basis/{desc.report.basis_name}",
    )
    np.savez(
        staging / "curve.npz",
        precision=ev.pr_precision,
        recall=ev.pr_recall,
        best_scores=ev.best_scores,
        best_correct=ev.best_correct,
        has_match=ev.has_match,
        **({} if start is None else {"start_correct": start.best_correct}),
    )
    replace_folder(staging, logdir / name)


def block_length(cfg: SweepConfig, ds: int) -> int:
    """Queries per bootstrap block: ``bootstrap.block_length``, at least the sequence."""
    return max(cfg.bootstrap.block_length, ds)


class ValidationScores(NamedTuple):
    """How a cell does on the validation places: recall@1 selects, margin breaks its ties."""

    recall_at_1: float
    auc_pr: float
    margin: float  # metrics.match_margin


def _validation_scores(cfg: SweepConfig, pair: PairData, val_top: TopK | None):
    """The validation queries' scores from their matches; NaN without them."""
    if val_top is None:
        return ValidationScores(math.nan, math.nan, math.nan)
    val = evaluate_matches(*val_top, pair.val_truth, pr_convention=cfg.pr_convention)
    return ValidationScores(val.recall_at_1, val.auc_pr, val.margin)


def validation_scores(pair: PairData, cfg: SweepConfig, mesh: Mesh | None) -> Callable:
    """The pair's validation scorer: ``(validation database, validation query descriptors,
    suffix starts) -> (recall@1, margin) per start``, matched and scored as every cell's
    validation places are (``match``, ``_validation_scores``)."""

    def scores(val_db, val_query, starts: tuple[int, ...]) -> list[tuple[float, float]]:
        top_scores, idx = _top_k(val_query, val_db, TOP_K, starts, cfg, mesh)
        scored = [_validation_scores(cfg, pair, top) for top in zip(top_scores, idx, strict=True)]
        return [(v.recall_at_1, v.margin) for v in scored]

    return scores


def _what_was_measured(pair: PairData, desc: Descriptors) -> dict:
    """A row's columns that describe its pair: seasons, sizes (the training places the fit
    used: all of the pair's unless ``split.train_places`` took fewer), ground truth,
    protocol."""
    return {
        "season_pair": pair.name,
        "db_season": pair.db_season,
        "query_season": pair.query_season,
        "n_train": len(pair.train) if desc.n_train is None else desc.n_train,
        "n_test": len(pair.query),
        "tolerance": pair.truth.tolerance if isinstance(pair.truth, Tolerance) else -1,
        "ground_truth": pair.truth.describe(),
        "protocol": pair.protocol,
    }


def _how_it_was_fitted(desc: Descriptors) -> dict:
    """results.csv's columns of the fit behind ``desc``: its time, what it reported, its
    seed."""
    return {
        "fit_seconds": desc.fit_seconds,
        "encode_ms_per_image": desc.encode_ms_per_image,
        **report_columns(desc.report),
        "seed": desc.seed,
    }


class CellMatches(NamedTuple):
    """A cell's top-K matches (``match``)."""

    test: TopK  # the test queries'
    val: TopK | None  # the validation queries' (None: the descriptors have none, NaN scores)
    start: TopK | None = None  # a trained model's start's, on the same test queries


def save_cell(
    logdir: Path,
    cfg: SweepConfig,
    pair: PairData,
    desc: Descriptors,
    cell: int,
    ds: int,
    matches: CellMatches,
) -> ResultRow:
    """Evaluate the matches of ``desc``'s ``cell``-th part, write its TensorBoard run, then
    its results.csv row (the row last: a run without a row is redone by a resumed sweep).
    Returns the row."""
    part: Part = desc.parts[cell]
    name = run_name(pair.name, part.run, ds)
    shutil.rmtree(logdir / name, ignore_errors=True)  # left by a crash before its row
    top = matches.test
    ev = evaluate_matches(*top, pair.truth, pr_convention=cfg.pr_convention)
    val = _validation_scores(cfg, pair, matches.val)
    ci = cell_intervals(
        ev.best_scores,
        ev.best_correct,
        ev.has_match,
        block_length=block_length(cfg, ds),
        resamples=cfg.bootstrap.resamples,
        seed=cfg.seed,
        pr_convention=cfg.pr_convention,
    )
    start = None
    if matches.start is not None:  # a trained model's start, on the same queries
        start = evaluate_matches(*matches.start, pair.truth, pr_convention=cfg.pr_convention)
    _write_run(logdir, name, cfg, pair, desc, cell, ds, top, ev, start)
    row = ResultRow(
        **_what_was_measured(pair, desc),
        method=desc.method,
        objective=desc.objective,
        **swept_columns(part.swept),
        ds=ds,
        **ev.scalars(),
        recall_at_1_ci_low=ci.recall_at_1.low,
        recall_at_1_ci_high=ci.recall_at_1.high,
        auc_pr_ci_low=ci.auc_pr.low,
        auc_pr_ci_high=ci.auc_pr.high,
        val_recall_at_1=val.recall_at_1,
        val_auc_pr=val.auc_pr,
        val_margin=val.margin,
        selected=0,
        **_how_it_was_fitted(desc),
        run=name,
    )
    append_results(logdir / "results.csv", [row])
    return row


def log_cell(log: Log, counter: str, row: ResultRow, warning: str | None, cfg_seed: int) -> None:
    """One plain line per finished cell (and its descriptors' warning, if any)."""
    k_text = f" {row.objective}" if row.objective else ""
    k_text += f" {row.setting}" if row.setting else ""
    k_text += "".join(f" {label}" for label in sweep_labels(row))
    k_text += f" seed={row.seed}" if row.seed != cfg_seed else ""
    k_text += f" ds={row.ds}" if row.ds != 1 else ""
    iters = f"  {row.n_iter} iterations" if row.n_iter else ""
    cost = f"fit {row.fit_seconds:.2f} s{iters}  {row.encode_ms_per_image:.4f} ms/img"
    if math.isnan(row.fit_seconds):  # outside descriptors: their cost was paid elsewhere
        cost = "descriptors computed elsewhere"
    log(
        f"{counter} {row.season_pair} {row.method}{k_text}: recall@1 {row.recall_at_1:.3f}  "
        f"auc_pr {row.auc_pr:.3f}  R@100P {row.recall_at_100_precision:.3f}  {cost}"
    )
    if warning:
        log(f"warning: {row.season_pair} {row.method}{k_text}: {warning}")


def parts_left(served: tuple, pair: str, todo: set[str], sequence_lengths) -> tuple:
    """The parts of a fit (``Served``) with a cell of ``pair`` still to do, at any ds."""
    return tuple(
        part
        for part in served
        if any(run_name(pair, part.run, ds) in todo for ds in sequence_lengths)
    )


def save_descriptors(
    out: Path,
    cfg,
    data: PairData,
    desc: Descriptors,
    todo: set[str],
    mesh: Mesh | None,
) -> Iterator[tuple[ResultRow, str | None]]:
    """Match, evaluate and save every cell of these descriptors still to do, part by part
    and ds by ds; yields (row, the descriptors' warning with their first cell only)."""
    single = {}  # per part of the pair (test, val), ds = 1 matches of every cell, one pass
    warning = desc.warning

    def matches(cell: int, ds: int, part: str):
        if part == "val" and desc.val_db is None:  # outside descriptors of route places
            return None
        if ds > 1:
            return match(desc, data, ds, (desc.starts[cell],), cfg, mesh, part)[0]
        if part not in single:
            single[part] = match(desc, data, 1, desc.starts, cfg, mesh, part)
        return single[part][cell]

    for cell, p in enumerate(desc.parts):
        for ds in cfg.sequence_lengths:
            if run_name(data.name, p.run, ds) not in todo:
                continue
            start = None
            if desc.start_query is not None:  # a trained model's start, same queries
                of_start = desc._replace(db=desc.start_db, query=desc.start_query)
                start = match(of_start, data, ds, (desc.starts[cell],), cfg, mesh)[0]
            found = CellMatches(matches(cell, ds, "test"), matches(cell, ds, "val"), start)
            row = save_cell(out, cfg, data, desc, cell, ds, found)
            yield row, warning
            warning = None
