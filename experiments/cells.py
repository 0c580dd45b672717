"""The sweep's cells: devices, methods, evaluation, TensorBoard runs, results.csv, figures.

``experiments.sweep`` validates everything it can without JAX (config, logdir, data, split)
and only then imports this module, so a typo is answered in a second, not after JAX starts.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

import jax
import numpy as np
from jax.sharding import Mesh
from omegaconf import OmegaConf

from vpr_jax.config import SWEEPS_REMOVED_PCS, MeshConfig, SweepConfig, identity, to_dict
from vpr_jax.data import Route
from vpr_jax.data.splits import Split
from vpr_jax.encoders.train import check_batch_splits
from vpr_jax.errors import UserError
from vpr_jax.methods import METHODS, CellOutput, MethodContext, PairData, with_sequence
from vpr_jax.metrics import evaluate_top_k
from vpr_jax.plots import correct_matches_figure, pr_curves_figure, recall_vs_ds_figure
from vpr_jax.progress import Bar
from vpr_jax.results import (
    append_results,
    atomic_write_text,
    cell_key,
    markdown_table,
    read_results,
)
from vpr_jax.sharding import make_mesh, mesh_size
from vpr_jax.tb import TrainingRun, match_examples, write_cell_run, write_experiment_config

if TYPE_CHECKING:
    from experiments.sweep import RunLog

METRIC_KEYS = ("recall_at_1", "precision_at_full_recall", "auc_pr", "recall_at_100_precision",
               "recall_at_5", "recall_at_10")
TIMING_KEYS = ("fit_seconds", "encode_ms_per_image")
INCOMPLETE = ".incomplete"  # TensorBoard runs being written; moved into place when whole


def start_devices(cfg: MeshConfig, log: RunLog) -> Mesh | None:
    """Join the other processes (``mesh.distributed``), then build the device mesh."""
    if cfg.distributed:
        # CPU devices of several processes talk through gloo; GPUs use NCCL regardless.
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        try:
            jax.distributed.initialize(cfg.coordinator, cfg.num_processes, cfg.process_id)
        except (RuntimeError, ValueError) as err:
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise UserError(
                f"mesh.distributed=true could not join the other processes ({first}): start "
                "one process per host under a launcher JAX detects (SLURM, Open MPI), or set "
                "mesh.coordinator=HOST:PORT, mesh.num_processes and mesh.process_id"
            ) from None
    try:
        mesh = make_mesh(cfg.devices)
    except ValueError as err:
        raise UserError(str(err)) from None
    if mesh is not None:
        devices = mesh.devices.flat
        log(f"mesh: {mesh_size(mesh)} {devices[0].platform} devices in "
            f"{jax.process_count()} process(es); PCA samples, matching database and "
            "training batches are split over them")  # fmt: skip
    return mesh


def pair_data(route: Route, split: Split, db: str, query: str, database: str) -> PairData:
    """Images of one pair; ``database="all"`` matches the queries against every frame of the
    database season (training places included), not only its test places."""
    images = route.images
    everything = database == "all"  # the season's own array: no copy of the whole route
    return PairData(
        db_season=db,
        query_season=query,
        train=np.concatenate([images[db][split.train], images[query][split.train]]),
        db=images[db] if everything else images[db][split.test],
        query=images[query][split.test],
        db_ids=route.frame_ids if everything else route.frame_ids[split.test],
        query_ids=route.frame_ids[split.test],
        fits={},
    )


def method_context(
    cfg: SweepConfig, logdir: Path, out: Path, pair: str, log: RunLog, mesh: Mesh | None
) -> MethodContext:
    """Checkpoints under <train.checkpoint_dir>/<logdir name>/<pair>/<method>/; a training
    run per auto-encoder next to its cell's run (under ``out``, where this process writes)."""
    ident = identity(cfg)
    return MethodContext(
        checkpoint_dir=Path(cfg.train.checkpoint_dir).expanduser().resolve() / logdir.name / pair,
        training_log=lambda method: TrainingRun(out / pair / f"{method}_training", log),
        identity={k: ident[k] for k in ("data", "split", "seed")},  # + training settings
        mesh=mesh,
    )


def run_name(pair: str, method: str, k: int, ds: int = 1) -> str:
    """``summer-fall/pca_k005``, ``summer-fall/fae``; sequence cells add ``_ds10``."""
    name = f"{pair}/{method}_k{k:03d}" if method in SWEEPS_REMOVED_PCS else f"{pair}/{method}"
    return name if ds == 1 else f"{name}_ds{ds:02d}"


def finish_cell(logdir: Path, cfg: SweepConfig, data: PairData, out: CellOutput,
                ds: int) -> dict:
    """Evaluate one cell and write its TensorBoard run; returns its results.csv row."""
    pair = f"{data.db_season}-{data.query_season}"
    ev = evaluate_top_k(out.top_scores, out.top_indices, data.query_ids, data.db_ids,
                        cfg.tolerance, pr_convention=cfg.pr_convention)
    scalars = ev.scalars()
    timings = {"fit_seconds": out.fit_seconds, "encode_ms_per_image": out.encode_ms_per_image}
    fit = {"n_iter": out.n_iter, "converged": int(out.converged)}
    name = run_name(pair, out.method, out.removed_pcs, ds)
    staging = logdir / INCOMPLETE / name
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    write_cell_run(
        staging,
        scalars={**{f"metrics/{k}": v for k, v in scalars.items()},
                 **{f"timing/{k}": v for k, v in timings.items()},
                 **{f"fit/{k}": v for k, v in fit.items()}},
        hparams={"season_pair": pair, "method": out.method,
                 "removed_pcs": float(out.removed_pcs), "ds": float(ds)},
        trial_id=name,
        best_scores=ev.best_scores,
        best_correct=ev.best_correct,
        has_match=ev.has_match,
        n_thresholds=cfg.tb.pr_thresholds,
        pr_convention=cfg.pr_convention,
        examples=match_examples(data.query, data.db, data.query_ids, data.db_ids,
                                out.top_indices[:, 0], cfg.tb.n_match_examples),
        basis_images=out.basis_images,
        basis_tag=f"basis/{out.basis_name}",
    )
    np.savez(staging / "curve.npz", precision=ev.pr_precision, recall=ev.pr_recall)
    final = logdir / name
    final.parent.mkdir(parents=True, exist_ok=True)
    os.replace(staging, final)
    return {
        "season_pair": pair, "db_season": data.db_season, "query_season": data.query_season,
        "method": out.method, "removed_pcs": out.removed_pcs, "ds": ds,
        "n_train": len(data.train), "n_test": len(data.query), "tolerance": cfg.tolerance,
        **scalars, **timings, **fit,
        "seed": cfg.seed, "run": name,
    }


def save_cell(out_dir: Path, cfg: SweepConfig, data: PairData, cell: CellOutput,
              ds: int) -> dict:
    """Match a method's cell by sequences of ``ds`` frames (1: as it is), evaluate it, and
    write its TensorBoard run and results.csv row; returns the row."""
    pair = f"{data.db_season}-{data.query_season}"
    # A run left by a crash before its row was written is redone.
    shutil.rmtree(out_dir / run_name(pair, cell.method, cell.removed_pcs, ds), True)
    row = finish_cell(out_dir, cfg, data, with_sequence(cell, data, ds, cfg), ds)
    append_results(out_dir / "results.csv", [row])
    return row


def log_cell(log: RunLog, counter: str, row: dict, out: CellOutput,
             warning: str | None) -> None:
    k_text = f" k={out.removed_pcs}" if out.method in SWEEPS_REMOVED_PCS else ""
    k_text += f" ds={row['ds']}" if row["ds"] != 1 else ""
    iters = f"  {out.n_iter} iterations" if out.n_iter else ""
    log(
        f"{counter} {row['season_pair']} {out.method}{k_text}: recall@1 "
        f"{row['recall_at_1']:.3f}  auc_pr {row['auc_pr']:.3f}  "
        f"R@100P {row['recall_at_100_precision']:.3f}  "
        f"fit {row['fit_seconds']:.2f} s{iters}  {row['encode_ms_per_image']:.4f} ms/img"
    )
    if warning:
        log(f"warning: {row['season_pair']} {out.method}{k_text}: {warning}")


def write_summaries(logdir: Path) -> None:
    rows = read_results(logdir / "results.csv")
    if not rows:
        return
    atomic_write_text(logdir / "results.md", markdown_table(rows))
    figures = logdir / "figures"
    figures.mkdir(exist_ok=True)

    def load_curve(row):
        with np.load(logdir / row["run"] / "curve.npz") as z:
            return z["precision"], z["recall"]

    pr_curves_figure(rows, load_curve, figures / "pr_curves.png")
    correct_matches_figure(rows, figures / "correct_matches.png")
    if len({r["ds"] for r in rows}) > 1:
        recall_vs_ds_figure(rows, figures / "recall_vs_ds.png")


def run_cells(
    cfg: SweepConfig, log: RunLog, logdir: Path, pairs, route: Route, split: Split
) -> Path:
    """Start the devices, then fit, encode, match and evaluate every cell still to do,
    writing each one's run and results.csv row as it ends."""
    mesh = start_devices(cfg.mesh, log)
    if {"fae", "cae"} & set(cfg.methods):  # before anything is written, not mid-sweep
        check_batch_splits(cfg.train.batch_size, mesh)
    # With several processes all compute, process 0 writes the logdir; the others read it
    # (shared file system) to agree on what is left, and write to a folder they delete.
    primary = jax.process_index() == 0
    out = logdir if primary else Path(tempfile.mkdtemp(prefix="vpr_jax-replica-"))
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UserError(f"logdir {out} cannot be made ({err.strerror}): set logdir=PATH to a "
                        "folder you can write") from None
    try:
        return _cells(cfg, log, logdir, out, pairs, mesh, route, split)
    finally:
        if not primary:
            shutil.rmtree(out, ignore_errors=True)


def _cells(cfg: SweepConfig, log: RunLog, logdir: Path, out: Path, pairs, mesh: Mesh | None,
           route: Route, split: Split) -> Path:
    # Validation is over: from here on the logdir is written.
    atomic_write_text(out / "config.yaml", OmegaConf.to_yaml(to_dict(cfg)))
    log.open(out / "sweep.log")
    shutil.rmtree(out / INCOMPLETE, ignore_errors=True)
    log(f"sweep: {len(route)} frames per season, {len(split.train)} training and "
        f"{len(split.test)} test places per season, pairs {[f'{a}-{b}' for a, b in pairs]}, "
        f"methods {list(cfg.methods)}, logdir {logdir}")
    ks = {m: cfg.removed_pcs if m in SWEEPS_REMOVED_PCS else (0,) for m in cfg.methods}
    lengths = cfg.sequence_lengths
    write_experiment_config(
        out,
        {"season_pair": [f"{a}-{b}" for a, b in pairs], "method": list(cfg.methods),
         "removed_pcs": [float(k) for m in cfg.methods for k in ks[m]],
         "ds": [float(ds) for ds in lengths]},
        [f"metrics/{k}" for k in METRIC_KEYS] + [f"timing/{k}" for k in TIMING_KEYS],
    )

    done = {cell_key(r) for r in read_results(logdir / "results.csv")}
    cells = [(p, m, k, ds) for p in pairs for m in cfg.methods for k in ks[m] for ds in lengths]
    todo = {c for c in cells if (f"{c[0][0]}-{c[0][1]}", *c[1:]) not in done}
    if len(todo) < len(cells):
        log(f"resuming: {len(cells) - len(todo)} of {len(cells)} cells already in results.csv")
    finished = len(cells) - len(todo)
    with Bar(len(todo), "sweep cells") as bar:
        for db, query in pairs:
            pair = f"{db}-{query}"
            data = None  # built on first use; its PCA fit then serves PCA and ICA
            ctx = method_context(cfg, logdir, out, pair, log, mesh)
            for method in cfg.methods:
                # Counts with any ds still to do: their descriptors are computed again.
                pending = tuple(sorted({k for (p, m, k, _) in todo
                                        if p == (db, query) and m == method}))
                if not pending:
                    continue
                if data is None:
                    data = pair_data(route, split, db, query, cfg.split.database)
                for cell in METHODS[method](data, pending, cfg, ctx):
                    left = [ds for ds in lengths
                            if ((db, query), method, cell.removed_pcs, ds) in todo]
                    for i, ds in enumerate(left):
                        row = save_cell(out, cfg, data, cell, ds)
                        finished += 1
                        bar.advance()
                        # A warning about the descriptors goes with their first cell only.
                        log_cell(log, f"[{finished}/{len(cells)}]", row, cell,
                                 cell.warning if i == 0 else None)
    write_summaries(out)
    log(f"done: {logdir / 'results.md'}, figures in {logdir / 'figures'}; "
        f"view with: tensorboard --logdir {logdir}")
    return logdir
