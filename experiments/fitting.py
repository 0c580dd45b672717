"""One fit of one method on one pair: the same steps for every method, built-in or a user's.

``describe_fit`` gives the fit the resources its method ``uses`` (the pair's shared PCA
fit, the validation places, its training folder and log, the devices), times it, keeps its
state (``vpr_jax.encoders.saved``), then encodes the database, the queries and the
validation places (blocked, warm timing), checks the descriptors and yields them: once for
every cell of a method whose served values are feature suffixes (pca's counts, one matching
pass), once per cell otherwise. A user's method that raises, or whose encode gives other
than one finite row per image, stops the sweep with one line naming it. ``load_pair``
makes the pair's data that every fit of it reads.
"""

from __future__ import annotations

import dataclasses
import functools
import traceback
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from experiments.cells import validation_scores
from experiments.plan import Plan
from experiments.resolve import Fit, Served
from experiments.saving import save_state
from vpr_jax.data.pair import PairData, benchmark_pair, pair_data, with_train_places
from vpr_jax.encoders import inputs
from vpr_jax.encoders import pca as pca_math
from vpr_jax.errors import UserError, first_line
from vpr_jax.evaluation.protocol import describe_protocol, fingerprint, protocol_record
from vpr_jax.host_arrays import release_free_memory
from vpr_jax.method_table import MethodInfo
from vpr_jax.methods import pca
from vpr_jax.methods.contract import (
    SERVED,
    SUFFIX,
    NotScored,
    PCAFit,
    Report,
    Training,
    Validation,
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
from vpr_jax.methods.inputs import PIXELS, input_of
from vpr_jax.methods.precomputed import Outside
from vpr_jax.methods.settings import as_dict
from vpr_jax.outputs.tb import TrainingRun
from vpr_jax.precision import with_float32_products
from vpr_jax.progress import Log, RunLog


class PairRun(NamedTuple):
    """What every fit of one pair shares."""

    plan: Plan
    data: PairData
    validate: Callable  # (val db, val queries, starts) -> (recall@1, margin) per start
    fitted_dir: Path  # the pair's folder of fitted states
    out: Path  # where this process writes TensorBoard runs
    log: Log
    mesh: Mesh | None
    made: dict  # the pair's shared PCA fits, once made, by settings and training places;
    # and the pair thinned to each ``split.train_places`` value, once made


def pair_run(
    plan: Plan, data: PairData, fitted_dir: Path, out: Path, log: Log, mesh, made=None
) -> PairRun:
    """A pair's shared part, its validation scorer made for ``mesh``; ``made``: what a
    fit would otherwise make again (the cluster's shared PCA fit)."""
    return PairRun(
        plan=plan,
        data=data,
        validate=validation_scores(data, plan.cfg, mesh),
        fitted_dir=fitted_dir,
        out=out,
        log=log,
        mesh=mesh,
        made={} if made is None else made,
    )


def _shared_pca_settings(fit: Fit, plan: Plan) -> Any:
    """The settings of the shared PCA fit ``fit`` uses: pca's own cells theirs, every other
    method pca's first, of the fit's own input (a PCA fit of what the method sees)."""
    if fit.method.info == plan.pca.info:
        return fit.settings
    return dataclasses.replace(plan.pca.combinations[0].settings, input=seen_input(fit))


def seen_input(fit: Fit) -> str:
    """The input the fit's method sees (``vpr_jax.methods.inputs``): what a method given
    ``with_input`` names when it needs the input's options; pixels otherwise (an
    auto-encoder's own ``input`` is not one)."""
    if "input_options" in fit.method.method.needs(fit.settings):
        return input_of(fit.settings)
    return PIXELS


def input_options(cfg) -> inputs.Options:
    """The options of the inputs' parts that have them (``gradients.*``, ``patchnorm.*``)."""
    g, p = cfg.gradients, cfg.patchnorm
    return inputs.Options(
        cell=g.cell, bins=g.bins, block=g.block, norm=g.norm, patch=p.size, rounded=p.rounded
    )


def _as_seen(settings: Any, train, cfg):
    """The training images as the input of ``settings`` shows them (pixels: as they are)."""
    name = input_of(settings)
    if name == PIXELS:
        return train
    return inputs.apply(inputs.fit(name, train, input_options(cfg)), train)


def pca_fit_key(fit: Fit, plan: Plan) -> tuple | None:
    """Which of the pair's shared PCA fits ``fit`` uses (None: none), by the settings that
    decide it and the training places."""
    if "pca_fit" not in fit.method.method.needs(fit.settings):
        return None
    return fit_key(plan.pca.method, _shared_pca_settings(fit, plan)), fit.train_places


def pca_fit(fit: Fit, run: PairRun) -> PCAFit:
    """The pair's shared PCA fit: made on first use and kept per ``pca_fit_key``, whichever
    methods use it, so each user gets what it would get alone."""
    key, settings = pca_fit_key(fit, run.plan), _shared_pca_settings(fit, run.plan)
    if key not in run.made:
        train = _as_seen(settings, fitted_on(fit, run).train, run.plan.cfg)
        n_images, n_pixels = len(train), int(np.prod(train.shape[1:]))
        asked = pca.shared_components(settings, n_images, n_pixels)
        state, seconds = timed(
            lambda x: pca.shared_fit(x, asked, settings, run.mesh, run.plan.cfg.seed), train
        )
        held = len(state.components)
        if held < asked:
            floor = pca_math.rank_tolerance(n_images, n_pixels)
            run.log(
                f"note: {run.data.name}: the PCA fit holds {held} of the {asked} components "
                f"asked: the other {asked - held} carry less than {floor:.1e} of the largest "
                f"variance, below what float32 resolves in sums over {n_images} training "
                "images (repeated or constant frames have such components, and so has a "
                "spectrum that falls that far); counts beyond them are left out "
                "(docs/methods.md#pca-on-any-training-set)"
            )
        run.made[key] = PCAFit(state=state, seconds=seconds)
    return run.made[key]


def fitted_on(fit: Fit, run: PairRun) -> PairData:
    """The pair as the fit sees it: its training places thinned to ``split.train_places``
    (the validation and test places as they are), made once per value (None: the pair
    itself)."""
    key = ("train_places", fit.train_places)
    if key not in run.made:
        run.made[key] = with_train_places(run.data, fit.train_places)
    return run.made[key]


def fit_key(method, settings: Any) -> str:
    """What decides a method's fit among its settings: all but those one fit serves."""
    served = {n for n, kind in method.axes(settings).items() if kind in (SERVED, SUFFIX)}
    values = as_dict(settings)
    return repr(sorted((n, v) for n, v in values.items() if n not in served))


def resources(fit: Fit, run: PairRun) -> dict[str, Any]:
    """What the fit's method needs from the runner, by keyword."""
    needs, data = fit.method.method.needs(fit.settings), run.data
    out: dict[str, Any] = {}
    if "pca_fit" in needs:
        out["pca_fit"] = pca_fit(fit, run)
    if "validation" in needs:
        out["validation"] = Validation(
            images=data.val,
            scores=lambda encode, starts=(0,): run.validate(
                *encode_validation(encode, data), tuple(starts)
            ),
        )
    if "training" in needs:
        out["training"] = _training(fit, run)
    if "mesh" in needs:
        out["mesh"] = run.mesh
    if "outside" in needs:
        out["outside"] = Outside(sides=run.plan.outside[fit.method.name], pair=data)
    if "input_options" in needs:
        out["input_options"] = input_options(run.plan.cfg)
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
            "train_places": fit.train_places,
        },
        name=f"{pair} {fit.folder}",
        checkpoint_every_s=cfg.train.checkpoint_every_s,
    )


def _fails(info: MethodInfo, step: str, err: Exception) -> UserError:
    fix = (
        "fix it and rerun the same command, the finished cells are kept"
        if info.plugin
        else "a fault of the suite: please report it; the finished cells are kept"
    )
    return UserError(
        f"method {info.name} ({info.method}): {step} raised {first_line(err)}: {fix} (the "
        "traceback is in sweep.log)",
        detail=traceback.format_exc(),
    )


@jax.jit
def _all_finite(descriptors) -> jax.Array:
    """Whether every value is finite: one program per shape (as eager ``isfinite`` and
    ``all``, it was two, each compiled for every shape an encoder returns)."""
    return jnp.isfinite(descriptors).all()


def checked_encode(info: MethodInfo, encode: Callable, jit: bool = True) -> Callable:
    """A method's ``encode`` (jitted for a user's: the contract asks for a jittable one,
    traced with float32 products where it states none, as ``load_encoder`` hands it out),
    its output checked: one row per image, two dimensions, at least one feature, finite.
    The same for every method, built-in or a user's."""
    call = jax.jit(with_float32_products(encode)) if jit else encode

    def run(state, images):
        try:
            out = call(state, jnp.asarray(images))
        except UserError:
            raise
        except Exception as err:  # the method's code
            if isinstance(err, OSError) and not info.plugin:
                raise
            raise _fails(info, "encode", err) from None
        shape = getattr(out, "shape", None)
        if shape is None or len(shape) != 2 or shape[0] != len(images) or shape[1] < 1:
            raise UserError(
                f"method {info.name} ({info.method}): encode gave shape {shape} for "
                f"{len(images)} images: return one row per image, (n, d) with d >= 1"
            )
        if not bool(_all_finite(out)):
            raise UserError(
                f"method {info.name} ({info.method}): encode gave NaN or infinite descriptors "
                f"for {len(images)} images: check its state and its arithmetic"
            )
        return out

    return run


def _encoder(fit: Fit, state: Any, served: dict) -> Callable:
    """``images -> descriptors`` of the fit's state for one set of served values."""
    info, encode = fit.method.info, fit.method.method.encode
    checked = checked_encode(info, functools.partial(encode, **served), jit=info.plugin)
    return lambda x: checked(state, x)


def run_fit(fit: Fit, run: PairRun) -> tuple[Any, float, float]:
    """The fit's state, its seconds, and the seconds of the shared PCA fit it used."""
    info, method, data = fit.method.info, fit.method.method, fitted_on(fit, run)
    given = resources(fit, run)
    aligned = data.aligned_train if data.aligned_training else None
    key = jax.random.key(fit.seed)
    # A user's fit computes its products at float32 unless it states otherwise, as every
    # built-in's are stated (vpr_jax.precision): the same numbers on any device.
    fit_fn = with_float32_products(method.fit) if info.plugin else method.fit
    try:
        state, seconds = timed(lambda: fit_fn(data.train, aligned, key, **fit.values, **given))
    except (UserError, NotScored):
        raise
    except Exception as err:  # the method's code, a built-in's or a user's
        if isinstance(err, OSError) and not info.plugin:
            raise  # the disk's fault, not the method's: sweep.main says which
        raise _fails(info, "fit", err) from None
    shared = given.get("pca_fit")
    return state, seconds, shared.seconds if shared is not None else 0.0


def _left_out(fit: Fit, parts, err: NotScored, run: PairRun) -> None:
    """One note for cells this pair's training set cannot serve (``NotScored``)."""
    runs = ", ".join(p.run for p in parts)
    run.log(f"note: {run.data.name} {runs}: not scored: {err}")


def _scored_parts(fit: Fit, parts, state, run: PairRun) -> tuple[tuple, list[Report]]:
    """The parts the fitted state can serve, with their reports; a note for the others."""
    kept, reports = [], []
    for part in parts:
        try:
            reports.append(fit.method.method.reported(state, {**fit.values, **part.values}))
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
    save_state(fit, state, run.plan.cfg, run.data.name, run.fitted_dir)
    parts, reports = _scored_parts(fit, parts, state, run)
    if not parts:
        return
    kinds = fit.method.method.axes(fit.settings)
    suffix = next((n for n, kind in kinds.items() if kind == SUFFIX), "")
    if suffix:
        starts = tuple(int(p.values[suffix]) for p in parts)
        base = {**parts[0].values, suffix: 0}  # the whole descriptors: every suffix of them
        encode = _encoder(fit, state, base)
        yield _describe(fit, parts, reports, starts, encode, seconds, run)
        return
    for part, report in zip(parts, reports, strict=True):
        encode = _encoder(fit, state, part.values)
        desc = _describe(fit, (part,), [report], (0,), encode, seconds, run)
        if report.start_state is not None:  # a trained model that left its start
            start_db, start_query, _ = encode_pair(
                _encoder(fit, report.start_state, part.values), run.data
            )
            desc = desc._replace(start_db=start_db, start_query=start_query)
        yield desc


def _describe(fit, parts, reports, starts, encode, seconds, run: PairRun) -> Descriptors:
    """Encode the pair with ``encode``; the degenerate-descriptor check. fit_seconds: the
    fit's (its own count where it keeps one: training over every session) and the shared
    PCA fit's it used."""
    data, cfg = run.data, run.plan.cfg
    first: Report = reports[0]
    db, query, ms = encode_pair(encode, data)
    warning = "; ".join(w for w in (first.warning, degenerate_warning(db, query)) if w) or None
    val_db, val_query = encode_validation(encode, data) if first.validation else (None, None)
    release_free_memory()  # the encoder's temporaries, before the matcher takes its own
    shape, (own, shared) = data.train.shape[1:], seconds
    n_train = len(fitted_on(fit, run).train)
    return Descriptors(
        method=fit.method.name,
        objective=fit.objective,
        seed=fit.seed,
        parts=tuple(Part(swept=p.swept, run=p.run) for p in parts),
        starts=starts,
        db=db,
        query=query,
        val_db=val_db,
        val_query=val_query,
        fit_seconds=(own if first.fit_seconds is None else first.fit_seconds) + shared,
        encode_ms_per_image=ms,
        report=first,
        n_train=n_train,
        basis=tuple(
            None
            if r.basis is None
            else as_images(np.asarray(r.basis)[: cfg.tb.n_basis_images], shape)
            for r in reports
        ),
        warning=warning,
    )


def load_pair(plan: Plan, db: str, query: str) -> PairData:
    """The images and ground truth of one pair, of the route or the benchmark, with the
    fingerprint of its protocol."""
    cfg = plan.cfg
    if plan.benchmark is not None:
        data = benchmark_pair(plan.benchmark, plan.route, plan.split, cfg)
    else:
        data = pair_data(plan.route, plan.split, db, query, cfg.split.database, cfg.tolerance)
    return data._replace(protocol=fingerprint(protocol_record(data, plan.benchmark is not None)))


def log_protocol(plan: Plan, data: PairData, log: RunLog) -> None:
    """One line for a pair loaded to be run: its protocol's fingerprint and what it is."""
    what = describe_protocol(data, plan.benchmark is not None)
    log(f"protocol {data.name} {data.protocol}: {what}")
