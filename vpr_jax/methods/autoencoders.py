"""The auto-encoders as methods: train (or resume, or restore) one model per objective and
describe the pair with its code."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Iterator
from typing import NamedTuple

import jax
import numpy as np

from vpr_jax import sharding
from vpr_jax.config import SweepConfig, TrainConfig, training_identity
from vpr_jax.data.pair import PairData
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import objectives, pca
from vpr_jax.encoders.train import TrainResult, fit_autoencoder
from vpr_jax.files import lock_folder
from vpr_jax.method_table import model_name
from vpr_jax.methods.descriptors import (
    Descriptors,
    Fitted,
    MethodContext,
    as_images,
    describe,
    encode_validation,
    method_key,
)


def autoencoder_spec(method: str, cfg: SweepConfig, removed: int = 0) -> ae.Spec:
    """The model ``fae.*`` / ``cae.*`` describe, removing ``removed`` components first."""
    if method == "fae":
        return ae.FAESpec(
            hidden=cfg.fae.hidden,
            centre=cfg.fae.input_centre,
            standardise=cfg.fae.standardise,
            removed=removed,
        )
    c = cfg.cae
    return ae.CAESpec(
        channels=tuple(c.channels),
        kernel_sizes=tuple(c.kernel_sizes),
        code_channels=c.code_channels,
        space_to_depth=c.space_to_depth,
        standardise=c.standardise,
        removed=removed,
    )


def describe_fae(pair: PairData, cfg: SweepConfig, ctx: MethodContext) -> Iterator[Descriptors]:
    """The fundamental auto-encoder (one hidden layer): ``describe_autoencoder``."""
    return describe_autoencoder("fae", pair, cfg, ctx)


def describe_cae(pair: PairData, cfg: SweepConfig, ctx: MethodContext) -> Iterator[Descriptors]:
    """The convolutional auto-encoder: ``describe_autoencoder``."""
    return describe_autoencoder("cae", pair, cfg, ctx)


class ResidualInput(NamedTuple):
    """What a residual-input model takes out of every image: PCA's validation-selected count
    of the pair's leading components (``fae.input=residual``)."""

    k: int
    val_recall_at_1: float  # PCA's, with k removed
    fixed: dict | None  # ae.with_removal's arrays (None when k = 0: the images themselves)


def pca_removal(pair: PairData, cfg: SweepConfig, ctx: MethodContext) -> ResidualInput:
    """The count PCA change removal chooses on the validation places (the best validation
    recall@1 among ``removed_pcs``, the fewest on a tie), from the pair's PCA fit."""
    if ctx.pca_fit is None or ctx.validate is None:
        raise ValueError("input=residual needs the pair's PCA fit and ctx.validate (the runner's)")
    state = ctx.pca_fit.state
    counts = sorted(k for k in cfg.removed_pcs if k <= state.components.shape[0])
    recalls = ctx.validate(
        *encode_validation(lambda x: pca.suffix_descriptors(state, x), pair), tuple(counts)
    )
    best = int(np.argmax(recalls))  # the first of equals: the fewest components
    k = counts[best]
    fixed = None
    if k:
        fixed = {"removal_mean": state.mean, "removal_basis": state.components[:k]}
    return ResidualInput(k, float(recalls[best]), fixed)


def augment_variants(settings: TrainConfig) -> tuple[tuple[str, TrainConfig], ...]:
    """(folder suffix, settings) of each model ``train.augment`` asks for: one, or with
    ``auto`` the model with augmentation and the one without."""
    if settings.augment != "auto":
        return (("", settings),)
    return (
        ("_augmented", dataclasses.replace(settings, augment=True)),
        ("_plain", dataclasses.replace(settings, augment=False)),
    )


def describe_autoencoder(
    method: str, pair: PairData, cfg: SweepConfig, ctx: MethodContext
) -> Iterator[Descriptors]:
    """Train (or resume, or restore) the pair's auto-encoder for each objective still to do
    (``ctx.objectives``); its code is the descriptor.

    It trains on both seasons' training images, and each epoch is scored by what the code
    is for: the validation places' recall@1 (``vpr_jax.data.splits``; ``ctx.validate``).
    The best epoch is kept and early stopping counts epochs without a better one. The
    training examples are the images themselves for ``reconstruct``, the aligned places'
    pairs for the paired objectives (``vpr_jax.encoders.objectives``). With
    ``<method>.input=residual`` the model removes PCA's validation-selected components
    first (``pca_removal``); with ``train.augment=auto`` a model is trained with and one
    without augmentation and the better on validation is kept. Every objective starts from
    the same initial weights. fit_seconds is the training time (of every model trained,
    all sessions); n_iter counts epochs; stopped_early says early stopping ended training
    before train.epochs.
    """
    group = getattr(cfg, method)
    removal = pca_removal(pair, cfg, ctx) if group.input == "residual" else None
    spec = autoencoder_spec(method, cfg, removal.k if removal else 0)
    settings = dataclasses.replace(cfg.train, epochs=group.epochs or cfg.train.epochs)
    for objective in ctx.objectives:
        trained = [
            (
                model_name(method, objective) + suffix,
                _train(method, objective, suffix, spec, variant, removal, pair, cfg, ctx),
            )
            for suffix, variant in augment_variants(settings)
        ]
        folder, result = max(trained, key=lambda t: t[1].best_score)  # the first on a tie
        seconds = sum(r.train_seconds for _, r in trained)
        yield _autoencoder_descriptors(method, objective, folder, result, seconds, pair, cfg)


def _train(
    method: str,
    objective: str,
    suffix: str,
    spec: ae.Spec,
    settings: TrainConfig,
    removal: ResidualInput | None,
    pair: PairData,
    cfg: SweepConfig,
    ctx: MethodContext,
) -> TrainResult:
    """One model: trained, resumed or restored in its checkpoint folder."""
    name = model_name(method, objective) + suffix
    if ctx.checkpoint_dir is not None and jax.process_index() == 0:
        # Logdirs of one name under different parents share this folder: one writer.
        lock_folder(
            ctx.checkpoint_dir / name,
            "checkpoint folder",
            "wait for it to finish, or give this logdir another name (or set train.checkpoint_dir)",
        )
    log = ctx.training_log(name) if ctx.training_log else None
    if log is not None and removal is not None:
        log.line(
            f"{pair.name} {name}: input residual, {removal.k} leading components removed "
            f"(PCA's validation-selected count, validation recall@1 {removal.val_recall_at_1:.3f})"
        )
    start, identity = None, {**(ctx.identity or {}), "input": getattr(cfg, method).input}
    if method == "fae" and cfg.fae.init != "random":
        whiten = cfg.fae.init == "whitened_pca"
        start = functools.partial(ae.pca_start, images=pair.train, whiten=whiten)
        identity["init"] = cfg.fae.init
    validate = None
    if ctx.validate is not None:
        validate = lambda encode: ctx.validate(*encode_validation(encode, pair), (0,))[0]  # noqa: E731
    try:
        return fit_autoencoder(
            spec,
            objectives.training_data(objective, pair.train),
            objectives.training_data(objective, pair.val),
            method_key(cfg.seed, method),
            settings,
            checkpoint_dir=ctx.checkpoint_dir / name if ctx.checkpoint_dir else None,
            identity={
                **identity,
                "train": training_identity(settings),
                "season_pair": pair.name,
                "method": method,
            },
            log=log,
            name=f"{pair.name} {name}",
            mesh=ctx.mesh,
            objective=objective,
            validate=validate,
            fixed=removal.fixed if removal else None,
            start=start,
        )
    finally:
        if log is not None:
            log.close()


def _autoencoder_descriptors(
    method: str,
    objective: str,
    folder: str,
    result: TrainResult,
    seconds: float,
    pair: PairData,
    cfg: SweepConfig,
) -> Descriptors:
    encode = ae.make_encode(result.graphdef)
    # Encoding runs on one device: a mesh-replicated model would encode on every device.
    params = jax.tree.map(sharding.to_host, result.params)
    basis = None
    if method == "fae":  # what each hidden unit looks for: its weights as an image
        weights = np.asarray(params["encoder"]["kernel"]).T[: cfg.tb.n_basis_images]
        basis = as_images(weights, pair)
    return describe(
        method,
        lambda x: encode(params, x),
        pair,
        basis=(basis,),
        objective=objective,
        fit_seconds=seconds,
        n_iter=result.epochs,
        stopped_early=result.stopped_early,
        basis_name="hidden_units",
        fitted=Fitted(folder=folder, encode="autoencoder", state=None),
    )
