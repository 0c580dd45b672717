"""Running a validated sweep: every cell still to do, pair by pair, on the plan's devices.

Per pair, each fit of each method (``experiments.resolve``) with a cell still to do is
fitted, kept and encoded the same way for every method (``experiments.fitting``); its cells
(served values x sequence lengths) go to ``experiments.cells``: matched, evaluated and
written once per cell, as each one ends. With ``cluster.address`` each fit is a task on a
Ray cluster instead, and this process writes what it made (``experiments.cluster``).
``experiments.sweep`` validates everything it can first and imports this module only then.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import jax
from jax.sharding import Mesh

from experiments.cells import (
    INCOMPLETE,
    log_cell,
    parts_left,
    run_name,
    save_descriptors,
)
from experiments.fitting import PairRun, describe_fit, load_pair, log_protocol
from experiments.fitting import pair_run as make_pair_run
from experiments.plan import Plan
from experiments.report import COMPARE, SUMMARY, run_steps, write_report
from experiments.resolve import Fit, Served
from experiments.saving import describe_saved
from vpr_jax.errors import UserError
from vpr_jax.evaluation.metrics import SCALAR_NAMES
from vpr_jax.files import atomic_write_text
from vpr_jax.host_arrays import release_free_memory
from vpr_jax.outputs.logdir import ENCODERS_CSV, config_yaml, fitted_root, lock_logdir
from vpr_jax.outputs.results import (
    SWEEP_KEYS,
    TIMING_NAMES,
    ResultRow,
    cell_key,
    read_results,
    swept_hparams,
)
from vpr_jax.outputs.tb import write_experiment_config
from vpr_jax.progress import Bar, Log, RunLog


def run_cells(plan: Plan, log: RunLog) -> Path:
    """Fit, encode, match and evaluate every cell still to do on the plan's devices,
    writing each one's run and results.csv row as it ends."""
    mesh = plan.mesh
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


class Cell(NamedTuple):
    """A cell of the plan: its run (what identifies it in results.csv) and what the
    experiment's HParams config lists of it."""

    run: str  # summer-fall/pca_k005, summer-fall/fae_cross_season_ds10
    season_pair: str
    method: str
    objective: str
    swept: dict  # every swept value, by name
    ds: int
    seed: int


def all_cells(plan: Plan) -> list[Cell]:
    """Every cell of the sweep, in the order it runs."""
    cfg, out = plan.cfg, []
    for a, b in plan.pairs:
        for fit in plan.fits:
            out += [
                cell_of(f"{a}-{b}", fit, part, ds)
                for part in fit.served
                for ds in cfg.sequence_lengths
            ]
    return out


def cell_of(pair: str, fit: Fit, part: Served, ds: int) -> Cell:
    """The cell of one served part of a fit at one sequence length."""
    return Cell(
        run=run_name(pair, part.run, ds),
        season_pair=pair,
        method=fit.method.name,
        objective=fit.objective,
        swept=part.swept,
        ds=ds,
        seed=fit.seed,
    )


def _cells_to_do(plan: Plan, log: Log) -> tuple[list[Cell], set[str]]:
    """Every cell of the sweep, in order, and the runs of those not yet in results.csv."""
    done = {cell_key(r) for r in read_results(plan.logdir / "results.csv")}
    cells = all_cells(plan)
    todo = {c.run for c in cells if c.run not in done}
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
        f"methods {list(cfg.methods)}"
        + (f", outside descriptors {list(cfg.precomputed)}" if cfg.precomputed else "")
        + f", logdir {logdir}"
    )
    cells, todo = _cells_to_do(plan, log)
    hparams = [swept_hparams(c.swept) for c in cells]
    write_experiment_config(
        out,
        {
            "season_pair": [f"{a}-{b}" for a, b in plan.pairs],
            "method": [c.method for c in cells],
            "objective": [c.objective for c in cells],
            **{name: [h[name] for h in hparams] for name in ("setting", *SWEEP_KEYS)},
            "ds": [float(c.ds) for c in cells],
            "seed": [float(c.seed) for c in cells],
        },
        [f"metrics/{k}" for k in SCALAR_NAMES] + [f"timing/{k}" for k in TIMING_NAMES],
    )
    finished = len(cells) - len(todo)
    if cfg.cluster.address is not None:  # each fit a task on the cluster, written here
        from experiments.cluster import run_fits

        rows = run_fits(plan, todo, log, out)
    else:
        rows = (
            found
            for db, query in plan.pairs
            for found in _run_pair(plan, db, query, todo, log, out, mesh)
        )
    # On a cluster the bar is over fits (experiments.cluster): one bar on a terminal at a time
    with Bar(len(todo) if cfg.cluster.address is None else 0, "sweep cells") as bar:
        for row, warning in rows:
            finished += 1
            bar.advance()
            log_cell(log, f"[{finished}/{len(cells)}]", row, warning, cfg.seed)
    failed = write_report(out, cfg, log)
    failed += run_steps({ENCODERS_CSV: lambda: describe_saved(out, cfg)}, log)
    shutil.rmtree(out / INCOMPLETE, ignore_errors=True)  # empty once every cell moved out
    log(
        ("done, but not written: " + ", ".join(failed) + "; " if failed else "done: ")
        + f"{logdir / 'results.md'}, figures in {logdir / 'figures'}; compare the methods "
        f"with: tensorboard --logdir {logdir / COMPARE} (a run per pair: --logdir "
        f"{logdir / SUMMARY}; every cell: --logdir {logdir}); take results out with: python "
        f"-m experiments.export {logdir}"
    )
    return logdir


def _run_pair(
    plan: Plan,
    db: str,
    query: str,
    todo: set[str],
    log: RunLog,
    out: Path,
    mesh: Mesh | None,
) -> Iterator[tuple[ResultRow, str | None]]:
    """Every fit of one pair with cells still to do (the sets of outside descriptors last):
    its cells saved as they end (yielded with the descriptors' warning)."""
    cfg, pair = plan.cfg, f"{db}-{query}"
    run = None

    def pair_run() -> PairRun:  # built on first use
        nonlocal run
        if run is None:
            data = load_pair(plan, db, query)
            log_protocol(plan, data, log)  # before the pair's first cell
            run = make_pair_run(plan, data, fitted_root(cfg, plan.logdir) / pair, out, log, mesh)
        return run

    for fit in plan.fits:
        parts = parts_left(fit.served, pair, todo, cfg.sequence_lengths)
        if parts:
            for desc in describe_fit(fit, parts, pair_run()):
                yield from save_descriptors(out, cfg, pair_run().data, desc, todo, mesh)
                # The cells are saved: drop the descriptors before the next fit and
                # encoding, so two methods' descriptors are never held at once.
                del desc
                release_free_memory()
