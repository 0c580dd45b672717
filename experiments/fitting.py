"""One fit of one method on one pair: the same steps for every method, built-in or a user's.

``describe_fit`` gives the fit the resources its method ``uses`` (the pair's shared PCA
fit, the validation places, its training folder and log, the devices), times it, keeps its
state (``vpr_jax.encoders.saved``), then encodes the database, the queries and the
validation places (blocked, warm timing), checks the descriptors and yields them: once for
every cell of a method whose served values are feature suffixes (pca's counts, one matching
pass), once per cell otherwise. A user's method that raises, or whose encode gives other
than one finite row per image, stops the sweep with one line naming it.
"""

from __future__ import annotations

import functools
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from experiments.plan import Plan
from experiments.resolve import Fit, Served
from vpr_jax.data.pair import PairData
from vpr_jax.data.preprocess import describe_preprocessing
from vpr_jax.encoders.saved import save_fitted, suite_version
from vpr_jax.errors import UserError, first_line
from vpr_jax.method_table import MethodInfo
from vpr_jax.methods.contract import (
    NotScored,
    PCAFit,
    Report,
    Training,
    Validation,
    report_of,
    suffix_of,
)
from vpr_jax.methods.descriptors import (
    Descriptors,
    Part,
    as_images,
    degenerate_warning,
    encode_pair,
    encode_validation,
    timed,
)
from vpr_jax.outputs.tb import TrainingRun
from vpr_jax.progress import Log
from vpr_jax.sharding import to_host


class PairRun(NamedTuple):
    """What every fit of one pair shares."""

    plan: Plan
    data: PairData
    validate: Callable  # (val db, val queries, starts) -> (recall@1, margin) per start
    fitted_dir: Path  # the pair's folder of fitted states
    out: Path  # where this process writes TensorBoard runs
    log: Log
    mesh: Mesh | None
    shared: dict  # the pair's shared PCA fit, once made: {"pca_fit": PCAFit}


def _pca_fit(fit: Fit, run: PairRun) -> PCAFit | None:
    """The pair's shared PCA fit, or None for a fit whose method declares it needs no
    component (``pca_components``). The fit is made on first use, ``Plan.pca_components``
    components whichever methods use it, so each user gets what it would get alone."""
    method = fit.method.method
    if method.pca_components is not None:
        if method.pca_components(fit.settings, run.plan.training_sets[fit.method.name]) <= 0:
            return None
    declared, settings = run.plan.shared_fit
    if "pca_fit" not in run.shared:
        asked = run.plan.pca_components
        state, seconds = timed(
            lambda x: declared.fit(x, asked, settings, run.mesh, run.plan.cfg.seed),
            run.data.train,
        )
        held = len(state.components)
        if held < asked:
            run.log(
                f"note: {run.data.name}: the PCA fit holds {held} of the {asked} components "
                f"asked: {len(run.data.train)} training images of numerical rank {held} "
                "(repeated or constant frames); counts beyond it are left out "
                "(docs/methods.md#pca-on-any-training-set)"
            )
        run.shared["pca_fit"] = PCAFit(
            state=state, seconds=seconds, removed_pcs=run.plan.cfg.removed_pcs, asked=asked
        )
    return run.shared["pca_fit"]


def resources(fit: Fit, run: PairRun) -> dict[str, Any]:
    """What the fit's method ``uses``, by keyword."""
    uses, data = fit.method.method.uses, run.data
    out: dict[str, Any] = {}
    if "pca_fit" in uses:
        out["pca_fit"] = _pca_fit(fit, run)
    if "validation" in uses:
        out["validation"] = Validation(
            images=data.val,
            scores=lambda encode, starts=(0,): run.validate(
                *encode_validation(encode, data), tuple(starts)
            ),
        )
    if "training" in uses:
        out["training"] = _training(fit, run)
    if "mesh" in uses:
        out["mesh"] = run.mesh
    return out


def _training(fit: Fit, run: PairRun) -> Training:
    cfg, pair = run.plan.cfg, run.data.name
    return Training(
        folder=run.fitted_dir / fit.folder,
        log=lambda suffix: TrainingRun(run.out / pair / f"{fit.folder}{suffix}_training", run.log),
        identity={
            "data": run.plan.identity["data"],
            "split": run.plan.identity["split"],
            "seed": fit.seed,
            "season_pair": pair,
            "method": fit.method.name,
        },
        name=f"{pair} {fit.folder}",
        settings=cfg.train,
    )


def _fails(info: MethodInfo, step: str, err: Exception) -> UserError:
    return UserError(
        f"method {info.name} ({info.method}): {step} raised {first_line(err)}: fix it and "
        "rerun the same command, the finished cells are kept (the traceback is in sweep.log)",
        detail=traceback.format_exc(),
    )


def checked_encode(info: MethodInfo, encode: Callable) -> Callable:
    """A user's ``encode`` jitted, its output checked: one row per image, two dimensions,
    finite."""
    jitted = jax.jit(encode)

    def run(state, images):
        try:
            out = jitted(state, jnp.asarray(images))
        except Exception as err:  # the user's code
            raise _fails(info, "encode", err) from None
        shape = getattr(out, "shape", None)
        if shape is None or len(shape) != 2 or shape[0] != len(images):
            raise UserError(
                f"method {info.name} ({info.method}): encode gave shape {shape} for "
                f"{len(images)} images: return one row per image, (n, d)"
            )
        if not bool(jnp.isfinite(out).all()):
            raise UserError(
                f"method {info.name} ({info.method}): encode gave NaN or infinite descriptors "
                f"for {len(images)} images: check its state and its arithmetic"
            )
        return out

    return run


def _encoder(fit: Fit, state: Any, served: dict) -> Callable:
    """``images -> descriptors`` of the fit's state for one set of served values."""
    info, encode = fit.method.info, fit.method.method.encode
    if info.plugin:
        checked = checked_encode(info, functools.partial(encode, **served))
        return lambda x: checked(state, x)
    return lambda x: encode(state, x, **served)


def run_fit(fit: Fit, run: PairRun) -> tuple[Any, float, float]:
    """The fit's state, its seconds, and the seconds of the shared PCA fit it used."""
    info, method, data = fit.method.info, fit.method.method, run.data
    given = resources(fit, run)
    aligned = data.aligned_train if data.aligned_training else None
    key = jax.random.key(fit.seed)
    try:
        state, seconds = timed(lambda: method.fit(data.train, aligned, key, **fit.values, **given))
    except (UserError, NotScored):
        raise
    except Exception as err:
        if not info.plugin:
            raise
        raise _fails(info, "fit", err) from None
    shared = given.get("pca_fit")
    return state, seconds, shared.seconds if shared is not None else 0.0


def save_state(fit: Fit, state: Any, run: PairRun) -> None:
    """Keep what the method fitted, so ``vpr_jax.load_encoder`` gives it back (process 0;
    the pair's ``encoder.json`` follows with the report)."""
    state = jax.tree.map(to_host, state)  # on every process: it may gather
    if jax.process_index() != 0:
        return
    cfg, info = run.plan.cfg, fit.method.info
    serves: dict[str, list] = {}
    for served in fit.served:
        for name, value in served.values.items():
            serves.setdefault(name, []).append(value)
    description = {
        "method": info.method,
        "name": info.name,
        "objective": fit.objective,
        "pair": run.data.name,
        "settings": dict(fit.values),
        "serves": serves,
        "cells": [
            {"run": p.run, "setting": p.setting, "removed_pcs": p.removed_pcs, "served": p.values}
            for p in fit.served
        ],
        "seed": fit.seed,
        "preprocessing": describe_preprocessing(
            cfg.preprocess, cfg.patchnorm.size, cfg.patchnorm.rounded
        ),
        "suite_version": suite_version(),
    }
    save_fitted(run.fitted_dir / fit.folder, state, description)


def _left_out(fit: Fit, parts, err: NotScored, run: PairRun) -> None:
    """One note for cells this pair's training set cannot serve (``NotScored``)."""
    runs = ", ".join(p.run for p in parts)
    run.log(f"note: {run.data.name} {runs}: not scored: {err}")


def _scored_parts(fit: Fit, parts, state, run: PairRun) -> tuple[tuple, list[Report]]:
    """The parts the fitted state can serve, with their reports; a note for the others."""
    kept, reports = [], []
    for part in parts:
        try:
            reports.append(report_of(fit.method.method, state, {**fit.values, **part.values}))
        except NotScored as err:
            _left_out(fit, (part,), err, run)
            continue
        kept.append(part)
    return tuple(kept), reports


def describe_fit(fit: Fit, parts: tuple[Served, ...], run: PairRun) -> Iterator[Descriptors]:
    """Fit (timed), keep the state, then the descriptors of ``parts`` (cells of the fit):
    one encoding for all of them when their served values are feature suffixes. Cells the
    training set cannot serve (``NotScored``) are left out with a note."""
    try:
        state, *seconds = run_fit(fit, run)
    except NotScored as err:
        _left_out(fit, parts, err, run)
        return
    save_state(fit, state, run)
    parts, reports = _scored_parts(fit, parts, state, run)
    if not parts:
        return
    suffix = suffix_of(fit.method.method, fit.settings)
    if suffix:
        starts = tuple(int(p.values[suffix]) for p in parts)
        base = {**parts[0].values, suffix: 0}  # the whole descriptors: every suffix of them
        encode = _encoder(fit, state, base)
        yield _describe(fit, parts, reports, starts, encode, seconds, run)
        return
    for part, report in zip(parts, reports, strict=True):
        encode = _encoder(fit, state, part.values)
        yield _describe(fit, (part,), [report], (0,), encode, seconds, run)


def _describe(fit, parts, reports, starts, encode, seconds, run: PairRun) -> Descriptors:
    """Encode the pair with ``encode``; the degenerate-descriptor check. fit_seconds: the
    fit's (its own count where it keeps one: training over every session) and the shared
    PCA fit's it used."""
    data, cfg = run.data, run.plan.cfg
    first: Report = reports[0]
    db, query, ms = encode_pair(encode, data)
    warning = "; ".join(w for w in (first.warning, degenerate_warning(db, query)) if w) or None
    val_db, val_query = encode_validation(encode, data)
    shape, (own, shared) = data.train.shape[1:], seconds
    return Descriptors(
        method=fit.method.name,
        objective=fit.objective,
        seed=fit.seed,
        parts=tuple(Part(setting=p.setting, removed_pcs=p.removed_pcs, run=p.run) for p in parts),
        starts=starts,
        db=db,
        query=query,
        val_db=val_db,
        val_query=val_query,
        fit_seconds=(own if first.fit_seconds is None else first.fit_seconds) + shared,
        encode_ms_per_image=ms,
        n_iter=first.n_iter,
        converged=first.converged,
        stopped_early=first.stopped_early,
        basis=tuple(
            None
            if r.basis is None
            else as_images(np.asarray(r.basis)[: cfg.tb.n_basis_images], shape)
            for r in reports
        ),
        basis_name=first.basis_name,
        warning=warning,
    )
