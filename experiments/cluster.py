"""A sweep's fits spread over a Ray cluster (``cluster.address``; docs/scaling.md, "Many
machines").

The unit of work is a fit with all its cells, as ``experiments.run`` groups them: a Ray task
(``_fit_task``, a plain function of its arguments) receives the plan without its route and
devices, the pair's data through Ray's object store (put once per pair), the pair's shared
PCA fit where its method uses one (made once per pair and settings by a task of its own,
``_shared_task``, which Ray runs before the fits that take its result), the fit and its
cells still to do, and what the driver holds of the fit's folder (an auto-encoder's training
checkpoints, so a resumed fit goes on from them). It fits and scores in a folder of its own
and returns what it made: the rows, the files of its TensorBoard runs and curves, the
fitted folder, the lines it logged and the node it ran on. This process (the driver) stays
the only writer of the logdir and the checkpoint folder: it writes each fit's files as the
fit arrives, then its rows, so no shared file system is needed and an interrupted sweep
resumes like any other. A worker that dies costs a retry (Ray's), never a row. The numbers
are those of one process: the same code runs, on the same data.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NamedTuple

from experiments import cluster_worker
from vpr_jax.compute_config import ClusterConfig
from vpr_jax.errors import UserError, first_line
from vpr_jax.files import replace_folder
from vpr_jax.progress import Bar, Log

INSTALL = 'pip install -e ".[cluster]"'
CONNECT_S = 5  # seconds an address has to answer
RETRIES = 3  # tries of a fit after the first, when its worker or node dies
SKIPPED = ("results.csv", ".incomplete", "sweep.log")  # of a task's logdir: the driver's own


class FitOutput(NamedTuple):
    """What a fit's task made, for the driver to write."""

    rows: list  # ResultRow, one per cell, in the order they ended
    warnings: list  # the descriptors' warning beside each row (None: none)
    logdir_files: dict[str, bytes]  # path under the logdir -> content: runs and curves
    fitted_files: dict[str, bytes]  # path under the fit's folder -> content
    lines: list[str]  # what the fit logged (notes, training epochs)
    node: str  # the host it ran on
    cores: tuple[int, ...]  # the cores its worker was held to there (): not pinned
    seconds: float  # the task's wall time there: the fit, its encodings and its cells


def connect(cluster: ClusterConfig, log: Log) -> None:
    """Join (or, for ``local``, start) the Ray cluster ``cluster`` names. Ray missing or a
    cluster that cannot be reached: UserError naming the fix, before anything is written."""
    # Ray reports usage to its makers by default; a sweep sends nothing off the cluster
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    try:
        import ray
    except ImportError:
        raise UserError(
            f"cluster.address={cluster.address} needs Ray, which is not installed: {INSTALL}, "
            "or leave cluster.address unset to run in this process"
        ) from None
    quiet = {"logging_level": logging.WARNING, "log_to_driver": False}
    unreachable = _unreachable(cluster.address)
    ours = signal.getsignal(signal.SIGTERM)  # Ray's core installs its own, which aborts
    try:
        if unreachable:
            raise ConnectionError(unreachable)
        if cluster.address == "local":
            ray.init(
                num_cpus=cluster.workers, include_dashboard=False, **quiet, **_worker_env(cluster)
            )
        else:
            ray.init(address=cluster.address, **quiet, **_worker_env(cluster))
    except (ConnectionError, RuntimeError, ValueError, TimeoutError) as err:
        raise UserError(
            f"cluster.address={cluster.address}: no Ray cluster could be reached "
            f"({first_line(err)[:200]}): start one (ray start --head) and give its address "
            "(auto, HOST:PORT or ray://HOST:PORT), use cluster.address=local, or leave it unset"
        ) from None
    finally:
        if ours is not None:  # SIGTERM stops the sweep as Ctrl-C does (experiments.sweep)
            signal.signal(signal.SIGTERM, ours)
    resources = ray.cluster_resources()
    log(
        f"cluster: {cluster.address}, {len(ray.nodes())} node(s), "
        f"{resources.get('CPU', 0):g} CPUs, {resources.get('GPU', 0):g} GPUs"
    )


def _worker_env(cluster: ClusterConfig) -> dict:
    """What every worker of this sweep starts with (``experiments.cluster_worker``): the
    cores each holds to, and with ``threads=share`` the setup hook that holds it there
    before JAX starts (sent by value: a worker cannot import the suite from the driver's
    folder before the hook runs). Fits that ask for GPUs: neither (untried: no GPU here)."""
    if cluster.gpus_per_fit > 0:
        return {}
    share = "" if cluster.cores_per_worker is None else str(cluster.cores_per_worker)
    runtime: dict = {"env_vars": {cluster_worker.SHARE_ENV: share}}
    if cluster.threads == "share":
        from ray import cloudpickle

        cloudpickle.register_pickle_by_value(cluster_worker)
        runtime["worker_process_setup_hook"] = cluster_worker.start_on_share
    return {"runtime_env": runtime}


def _unreachable(address: str) -> str | None:
    """Why nothing answers at ``HOST:PORT`` (``ray://`` too) within ``CONNECT_S`` seconds,
    or None (it answers; ``local`` and ``auto`` are Ray's to find): Ray itself retries a
    silent address for minutes."""
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if address in ("local", "auto") or not host or not port.isdigit():
        return None
    try:
        socket.create_connection((host, int(port)), timeout=CONNECT_S).close()
    except OSError as err:
        return f"{host}:{port}: {err.strerror or err}"
    return None


def disconnect() -> None:
    """Leave the cluster (a ``local`` one stops with it)."""
    import ray

    if ray.is_initialized():
        ray.shutdown()


def _pack(folder: Path, skipped: tuple[str, ...] = ()) -> dict[str, bytes]:
    """Every file under ``folder`` by its path there, with its bytes (none: ``{}``)."""
    if not folder.is_dir():
        return {}
    return {
        path.relative_to(folder).as_posix(): path.read_bytes()
        for path in sorted(folder.rglob("*"))
        if path.is_file() and path.relative_to(folder).parts[0] not in skipped
    }


def _unpack(files: dict[str, bytes], folder: Path) -> None:
    for name, content in files.items():
        path = folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(content)


def _shared_task(plan, data, fit) -> tuple[tuple, Any, list[str]]:
    """The pair's shared PCA fit that ``fit`` uses, made once for every fit of the pair
    that uses it: (its key, the fit, what it logged)."""
    from experiments.fitting import pair_run, pca_fit, pca_fit_key
    from vpr_jax import compile_cache

    cluster_worker.start()
    lines: list[str] = []
    compile_cache.use(plan.cfg.compile_cache, lines.append)
    run = pair_run(plan, data, Path("."), Path("."), lines.append, None)
    return pca_fit_key(fit, plan), pca_fit(fit, run), lines


def _fit_task(
    plan, data, fit, parts: tuple, todo: frozenset, held: dict[str, bytes], shared
) -> FitOutput:
    """One fit and its cells, run in a folder of this worker's own (see the module's
    docstring), with the pair's ``shared`` PCA fit where it uses one (``_shared_task``'s
    output, or None); what it made comes back."""
    from experiments.cells import save_descriptors
    from experiments.fitting import describe_fit, pair_run
    from vpr_jax import compile_cache

    began = time.perf_counter()
    cluster_worker.start()
    lines: list[str] = [] if shared is None else list(shared[2])
    compile_cache.use(plan.cfg.compile_cache, lines.append)
    made = {} if shared is None else {shared[0]: shared[1]}
    with tempfile.TemporaryDirectory(prefix="vpr_jax-fit-") as tmp:
        out, fitted = Path(tmp) / "logdir", Path(tmp) / "fitted"
        out.mkdir()
        _unpack(held, fitted / fit.folder)
        run = pair_run(plan, data, fitted, out, lines.append, None, made)
        cells = [
            found
            for desc in describe_fit(fit, parts, run)
            for found in save_descriptors(out, plan.cfg, data, desc, set(todo), None)
        ]
        return FitOutput(
            rows=[row for row, _ in cells],
            warnings=[warning for _, warning in cells],
            logdir_files=_pack(out, SKIPPED),
            fitted_files=_pack(fitted / fit.folder),
            lines=lines,
            node=socket.gethostname(),
            cores=cluster_worker.cores(),
            seconds=time.perf_counter() - began,
        )


def _write_back(output: FitOutput, out: Path, fit_folder: Path) -> None:
    """A fit's files in the logdir and its folder in the checkpoint folder, each run and the
    folder whole (aside, then moved into place); the rows follow (``run_fits``)."""
    if output.fitted_files:
        staging = Path(tempfile.mkdtemp(prefix=f".{fit_folder.name}.", dir=_made(fit_folder)))
        _unpack(output.fitted_files, staging)
        replace_folder(staging, fit_folder)
    runs: dict[Path, dict[str, bytes]] = {}
    for name, content in output.logdir_files.items():
        pair, run, *rest = Path(name).parts
        runs.setdefault(Path(pair) / run, {})[Path(*rest).as_posix()] = content
    for run, files in runs.items():
        staging = Path(tempfile.mkdtemp(prefix=f".{run.name}.", dir=_made(out / run)))
        _unpack(files, staging)
        replace_folder(staging, out / run)


def _made(path: Path) -> Path:
    """``path``'s folder, made if need be."""
    path.parent.mkdir(parents=True, exist_ok=True)
    return path.parent


def run_fits(plan, todo: set[str], log: Log, out: Path) -> Iterator[tuple[Any, str | None]]:
    """Every fit with cells still to do, as Ray tasks on the cluster ``connect`` joined;
    yields (row, warning) per cell as each fit's files are written, in order of arrival."""
    import ray

    from experiments.cells import parts_left
    from experiments.fitting import load_pair, log_protocol, pca_fit_key
    from vpr_jax.outputs.logdir import fitted_root

    cfg = plan.cfg
    task = ray.remote(max_retries=RETRIES, retry_exceptions=False)(_fit_task)
    shared_task = ray.remote(max_retries=RETRIES, retry_exceptions=False)(_shared_task)
    lite = ray.put(plan._replace(route=None, mesh=None, benchmark=None))
    pending: dict = {}
    for db, query in plan.pairs:
        pair = f"{db}-{query}"
        fits = []
        for fit in plan.fits:
            parts = parts_left(fit.served, pair, todo, cfg.sequence_lengths)
            if parts:
                fits.append((fit, parts))
        if not fits:
            continue
        data = load_pair(plan, db, query)
        log_protocol(plan, data, log)
        data_ref = ray.put(data)
        shared = {}  # the pair's shared PCA fits, each a task of its own, made once
        for fit, parts in fits:
            key = pca_fit_key(fit, plan)
            if key is not None and key not in shared:
                shared[key] = shared_task.options(num_cpus=1).remote(lite, data_ref, fit)
            folder = fitted_root(cfg, plan.logdir) / pair / fit.folder
            trains = "training" in fit.method.method.needs(fit.settings)
            options = {"num_cpus": 1, "num_gpus": cfg.cluster.gpus_per_fit if trains else 0}
            ref = task.options(**options).remote(
                lite, data_ref, fit, parts, frozenset(todo), _pack(folder), shared.get(key)
            )
            pending[ref] = (pair, fit, folder)
    log(f"cluster: {len(pending)} fit(s) queued")
    with Bar(len(pending), _fits_label(0, len(pending))) as bar:
        yield from _arrivals(pending, out, log, bar)


def _fits_label(done: int, left: int) -> str:
    """The bar's label: fits done, running (as many as the cluster has CPUs for), queued."""
    import ray

    running = min(left, int(ray.cluster_resources().get("CPU", 0)) or left)
    return f"fits: {done} done, {running} running, {left - running} queued"


def _arrivals(pending: dict, out: Path, log: Log, bar: Bar):
    """Each fit's output as it arrives: logged, written, its rows yielded."""
    import ray

    from vpr_jax.outputs.results import append_results

    done, logged = 0, set()
    while pending:
        (ready,), _ = ray.wait(list(pending), num_returns=1)
        pair, fit, folder = pending.pop(ready)
        output = _result(ready, pair, fit)
        for line in output.lines:
            if line not in logged:  # a shared fit's note comes with each fit that used it
                log(line)
                logged.add(line)
        _write_back(output, out, folder)
        log(
            f"{pair} {fit.folder}: fitted on node {output.node}{_cores_text(output.cores)} "
            f"in {output.seconds:.1f} s "
            f"({len(pending)} fit(s) left)"
        )
        append_results(out / "results.csv", output.rows)  # after the runs: a row means done
        done += 1
        bar.advance(description=_fits_label(done, len(pending)))
        yield from zip(output.rows, output.warnings, strict=True)


def _cores_text(cores: tuple[int, ...]) -> str:
    return f" (cores {','.join(map(str, cores))})" if cores else " (not pinned)"


def _result(ref, pair: str, fit) -> FitOutput:
    """The task's output; a method's refusal as the one line it is; a fit that kept
    failing (its worker or node lost every try): one line naming it."""
    import ray

    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as err:
        cause = err.cause
        if isinstance(cause, UserError):
            raise cause from None
        raise UserError(
            f"fit {pair} {fit.folder} failed on node {err.ip} (process {err.pid}): "
            f"{first_line(cause)}: a fault of the suite or the method; the finished cells "
            "are kept, rerun the same command"
        ) from None
    except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError) as err:
        raise UserError(
            f"fit {pair} {fit.folder} kept failing: its worker or node was lost on all "
            f"{RETRIES + 1} tries ({first_line(err)[:200]}): check the cluster's nodes "
            "(ray status), then rerun the same command; the finished cells are kept"
        ) from None
