"""Running a validated sweep: start the devices, then every cell still to do, pair by pair.

Per pair and method the runner asks the method for descriptors (``vpr_jax.methods``), then
hands each removed-PC count and sequence length to ``experiments.cells``: matched, evaluated
and written once per cell, as each one ends. ``experiments.sweep`` validates everything it
can without JAX first and imports this module only then.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import jax
from jax.sharding import Mesh

from experiments.cells import INCOMPLETE, log_cell, match, save_cell, validation_recalls
from experiments.plan import Plan
from experiments.report import COMPARE, SUMMARY, write_report
from vpr_jax.config import MeshConfig, SweepConfig
from vpr_jax.data.pair import PairData, benchmark_pair, pair_data
from vpr_jax.data.preprocess import describe_preprocessing
from vpr_jax.encoders import objectives
from vpr_jax.encoders.saved import save_fitted, suite_version
from vpr_jax.encoders.train import check_batch_splits
from vpr_jax.errors import UserError, first_line
from vpr_jax.evaluation.metrics import SCALAR_NAMES
from vpr_jax.files import atomic_write_text
from vpr_jax.host_arrays import release_free_memory
from vpr_jax.method_table import MethodInfo, describe_function
from vpr_jax.methods import Descriptors, MethodContext, fit_pair_pca, uses_pca_fit
from vpr_jax.outputs.logdir import config_yaml, fitted_root, identity, lock_logdir
from vpr_jax.outputs.results import (
    TIMING_NAMES,
    CellKey,
    ResultRow,
    cell_key,
    read_results,
)
from vpr_jax.outputs.tb import TrainingRun, write_experiment_config
from vpr_jax.progress import Bar, Log, RunLog
from vpr_jax.sharding import make_mesh, mesh_size, to_host


def objectives_of(method: MethodInfo, cfg: SweepConfig) -> tuple[str, ...]:
    """The auto-encoders' objective axis (``fae.objective``, ``cae.objective``); one empty
    objective for the other methods."""
    return tuple(getattr(cfg, method.name).objective) if method.trained else ("",)


def start_devices(cfg: MeshConfig, log: Log) -> Mesh | None:
    """Join the other processes (``mesh.distributed``), then build the device mesh."""
    if cfg.distributed:
        # CPU devices of several processes talk through gloo; GPUs use NCCL regardless.
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        try:
            jax.distributed.initialize(cfg.coordinator, cfg.num_processes, cfg.process_id)
        except (RuntimeError, ValueError) as err:
            raise UserError(
                f"mesh.distributed=true could not join the other processes ({first_line(err)}): "
                "start "
                "one process per host under a launcher JAX detects (SLURM, Open MPI), or set "
                "mesh.coordinator=HOST:PORT, mesh.num_processes and mesh.process_id"
            ) from None
    try:
        mesh = make_mesh(cfg.devices)
    except ValueError as err:
        raise UserError(str(err)) from None
    if mesh is not None:
        devices = mesh.devices.flat
        log(
            f"mesh: {mesh_size(mesh)} {devices[0].platform} devices in "
            f"{jax.process_count()} process(es); PCA samples, matching database and "
            "training batches are split over them"
        )
    return mesh


def method_context(plan: Plan, out: Path, pair: str, log: Log, mesh: Mesh | None) -> MethodContext:
    """Checkpoints under <train.checkpoint_dir>/<logdir name>/<pair>/<method>/; a training
    run per auto-encoder next to its cell's run (under ``out``, where this process writes);
    the plan's outside descriptors."""
    ident = identity(plan.cfg)
    return MethodContext(
        checkpoint_dir=fitted_root(plan.cfg, plan.logdir) / pair,
        training_log=lambda method: TrainingRun(out / pair / f"{method}_training", log),
        identity={k: ident[k] for k in ("data", "split", "seed")},  # + training settings
        mesh=mesh,
        outside=plan.outside,
    )


def run_cells(plan: Plan, log: RunLog) -> Path:
    """Start the devices, then fit, encode, match and evaluate every cell still to do,
    writing each one's run and results.csv row as it ends."""
    cfg = plan.cfg
    mesh = start_devices(cfg.mesh, log)
    trained = [o for m in plan.methods if m.trained for o in objectives_of(m, cfg)]
    if trained:  # before anything is written, not mid-sweep
        check_batch_splits(
            cfg.train.batch_size, mesh, max(objectives.examples_per_image(o) for o in trained)
        )
    # With several processes all compute, process 0 writes the logdir; the others read it
    # (shared file system) to agree on what is left, and write to a folder they delete.
    primary = jax.process_index() == 0
    if primary:  # every check passed: from here on this process is the logdir's writer
        lock_logdir(plan.logdir)
    out = plan.logdir if primary else Path(tempfile.mkdtemp(prefix="vpr_jax-replica-"))
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UserError(
            f"logdir {out} cannot be made ({err.strerror}): set logdir=PATH to a "
            "folder you can write"
        ) from None
    try:
        return _run(plan, log, out, mesh)
    finally:
        if not primary:
            shutil.rmtree(out, ignore_errors=True)


def _cells_to_do(plan: Plan, log: Log) -> tuple[list[CellKey], set[CellKey]]:
    """Every cell of the sweep, in order, and those not yet in results.csv."""
    cfg = plan.cfg
    done = {cell_key(r) for r in read_results(plan.logdir / "results.csv")}
    cells = [
        CellKey(season_pair=f"{a}-{b}", method=m.name, objective=o, removed_pcs=k, ds=ds)
        for a, b in plan.pairs
        for m in plan.methods
        for o in objectives_of(m, cfg)
        for k in (cfg.removed_pcs if m.sweeps_removed_pcs else (0,))
        for ds in cfg.sequence_lengths
    ]
    todo = {c for c in cells if c not in done}
    if len(todo) < len(cells):
        log(f"resuming: {len(cells) - len(todo)} of {len(cells)} cells already in results.csv")
    return cells, todo


def _run(plan: Plan, log: RunLog, out: Path, mesh: Mesh | None) -> Path:
    cfg, logdir = plan.cfg, plan.logdir
    # Validation is over: from here on the logdir is written.
    atomic_write_text(out / "config.yaml", config_yaml(cfg))
    log.open(out / "sweep.log")
    shutil.rmtree(out / INCOMPLETE, ignore_errors=True)
    log(
        f"sweep: {plan.describe()}, pairs {[f'{a}-{b}' for a, b in plan.pairs]}, "
        f"methods {list(cfg.methods)}, logdir {logdir}"
    )
    cells, todo = _cells_to_do(plan, log)
    write_experiment_config(
        out,
        {
            "season_pair": [f"{a}-{b}" for a, b in plan.pairs],
            "method": [m.name for m in plan.methods],
            "objective": [c.objective for c in cells],
            "removed_pcs": [float(c.removed_pcs) for c in cells],
            "ds": [float(c.ds) for c in cells],
        },
        [f"metrics/{k}" for k in SCALAR_NAMES] + [f"timing/{k}" for k in TIMING_NAMES],
    )
    finished = len(cells) - len(todo)
    with Bar(len(todo), "sweep cells") as bar:
        for db, query in plan.pairs:
            for row, warning in _run_pair(plan, db, query, todo, log, out, mesh):
                finished += 1
                bar.advance()
                log_cell(log, f"[{finished}/{len(cells)}]", row, warning)
    write_report(out, cfg)
    shutil.rmtree(out / INCOMPLETE, ignore_errors=True)  # empty once every cell moved out
    log(
        f"done: {logdir / 'results.md'}, figures in {logdir / 'figures'}; compare the methods "
        f"with: tensorboard --logdir {logdir / COMPARE} (a run per pair: --logdir "
        f"{logdir / SUMMARY}; every cell: --logdir {logdir}); take results out with: python "
        f"-m experiments.export {logdir}"
    )
    return logdir


def _run_pair(
    plan: Plan,
    db: str,
    query: str,
    todo: set[CellKey],
    log: RunLog,
    out: Path,
    mesh: Mesh | None,
) -> Iterator[tuple[ResultRow, str | None]]:
    """Every method of one pair with cells still to do: its descriptors, its fitted state
    kept, its cells saved as they end (yielded with the descriptors' warning)."""
    cfg, pair = plan.cfg, f"{db}-{query}"
    data, ctx = None, method_context(plan, out, pair, log, mesh)
    saved: set[str] = set()  # fitted folders written in this run
    for method in plan.methods:
        # Objectives and counts with any cell still to do: their descriptors are computed
        # again.
        left = [
            (c.objective, c.removed_pcs)
            for c in todo
            if (c.season_pair, c.method) == (pair, method.name)
        ]
        if not left:
            continue
        if data is None:  # built on first use
            data = load_pair(plan, db, query)
            ctx = ctx._replace(validate=validation_recalls(data, cfg, mesh))
        if uses_pca_fit(method, cfg) and ctx.pca_fit is None:  # one fit per pair
            ctx = ctx._replace(pca_fit=fit_pair_pca(data, cfg, mesh))
        todo_ctx = ctx._replace(
            objectives=tuple(o for o in objectives_of(method, cfg) if o in {o for o, _ in left}),
            removed_pcs=tuple(sorted({k for _, k in left})),
        )
        for desc in describe_function(method)(data, cfg, todo_ctx):
            if desc.fitted is not None and desc.fitted.folder not in saved:
                saved.add(desc.fitted.folder)  # pca.output=pixels: one fit, a desc per count
                _save_fitted(method, desc, ctx.checkpoint_dir, cfg, pair)
            yield from _save_descriptors(out, cfg, data, desc, todo, mesh)
            # The cells are saved: drop the descriptors before the generator fits and
            # encodes the next (a 35,768-frame database's are 0.3 GiB).
            del desc
            release_free_memory()


def _save_fitted(
    method: MethodInfo, desc: Descriptors, folder: Path, cfg: SweepConfig, pair: str
) -> None:
    """Keep what the method fitted, so ``vpr_jax.load_encoder`` gives it back (process 0;
    the pair's ``encoder.json`` follows with the report)."""
    fitted = desc.fitted
    state = jax.tree.map(to_host, fitted.state)  # on every process: it may gather
    if jax.process_index() != 0:
        return
    description = {
        "method": method.plugin or method.name,
        "name": method.name,
        "objective": desc.objective,
        "pair": pair,
        "counts": [int(k) for k in fitted.counts],
        "preprocessing": describe_preprocessing(
            cfg.preprocess, cfg.patchnorm.size, cfg.patchnorm.rounded
        ),
        "seed": cfg.seed,
        "suite_version": suite_version(),
    }
    save_fitted(folder / fitted.folder, fitted.encode, state, description)


def load_pair(plan: Plan, db: str, query: str) -> PairData:
    """The images and ground truth of one pair: of the route, or the benchmark's."""
    cfg = plan.cfg
    if plan.benchmark is not None:
        return benchmark_pair(plan.benchmark, plan.route, plan.split, cfg)
    return pair_data(plan.route, plan.split, db, query, cfg.split.database, cfg.tolerance)


def _save_descriptors(
    out: Path,
    cfg: SweepConfig,
    data: PairData,
    desc: Descriptors,
    todo: set[CellKey],
    mesh: Mesh | None,
) -> Iterator[tuple[ResultRow, str | None]]:
    """Match, evaluate and save every cell of these descriptors still to do, count by count
    and ds by ds; yields (row, the descriptors' warning with their first cell only)."""
    single = {}  # per part, ds = 1 matches of every count, from one pass
    warning = desc.warning

    def matches(k: int, ds: int, part: str):
        if part == "val" and desc.val_db is None:  # outside descriptors of route places
            return None
        if ds > 1:
            return match(desc, data, ds, (k,), cfg, mesh, part)[0]
        if part not in single:
            single[part] = dict(
                zip(
                    desc.removed_pcs,
                    match(desc, data, 1, desc.removed_pcs, cfg, mesh, part),
                    strict=True,
                )
            )
        return single[part][k]

    for k in desc.removed_pcs:
        for ds in cfg.sequence_lengths:
            cell = CellKey(
                season_pair=data.name,
                method=desc.method,
                objective=desc.objective,
                removed_pcs=k,
                ds=ds,
            )
            if cell not in todo:
                continue
            row = save_cell(
                out, cfg, data, desc, k, ds, matches(k, ds, "test"), matches(k, ds, "val")
            )
            yield row, warning
            warning = None
