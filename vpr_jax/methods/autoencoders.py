"""The auto-encoders as methods: train (or resume, or restore) one model per objective and
describe the pair with its code."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import jax
import numpy as np

from vpr_jax import sharding
from vpr_jax.config import SweepConfig, training_identity
from vpr_jax.data.pair import PairData
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import objectives
from vpr_jax.encoders.train import fit_autoencoder
from vpr_jax.files import lock_folder
from vpr_jax.method_table import model_name
from vpr_jax.methods.descriptors import (
    Descriptors,
    Fitted,
    MethodContext,
    as_images,
    describe,
    method_key,
)


def autoencoder_spec(method: str, cfg: SweepConfig) -> ae.Spec:
    if method == "fae":
        return ae.FAESpec(
            hidden=cfg.fae.hidden, centre=cfg.fae.input_centre, standardise=cfg.fae.standardise
        )
    c = cfg.cae
    return ae.CAESpec(
        channels=tuple(c.channels),
        kernel_sizes=tuple(c.kernel_sizes),
        code_channels=c.code_channels,
        space_to_depth=c.space_to_depth,
        standardise=c.standardise,
    )


def describe_fae(pair: PairData, cfg: SweepConfig, ctx: MethodContext) -> Iterator[Descriptors]:
    """The fundamental auto-encoder (one hidden layer): ``describe_autoencoder``."""
    return describe_autoencoder("fae", pair, cfg, ctx)


def describe_cae(pair: PairData, cfg: SweepConfig, ctx: MethodContext) -> Iterator[Descriptors]:
    """The convolutional auto-encoder: ``describe_autoencoder``."""
    return describe_autoencoder("cae", pair, cfg, ctx)


def describe_autoencoder(
    method: str, pair: PairData, cfg: SweepConfig, ctx: MethodContext
) -> Iterator[Descriptors]:
    """Train (or resume, or restore) the pair's auto-encoder for each objective still to do
    (``ctx.objectives``); its code is the descriptor.

    It trains on both seasons' training images and stops early on the validation places
    (``vpr_jax.data.splits``): the images themselves for ``reconstruct``, the aligned
    places' pairs for ``cross_season`` (``vpr_jax.encoders.objectives``). Every
    objective starts from the same initial weights. fit_seconds is the training time (of
    all sessions, when it was resumed); n_iter counts epochs; stopped_early says early
    stopping ended training before train.epochs.
    """
    spec = autoencoder_spec(method, cfg)
    epochs = getattr(cfg, method).epochs or cfg.train.epochs  # fae.epochs / cae.epochs first
    settings = dataclasses.replace(cfg.train, epochs=epochs)
    for objective in ctx.objectives:
        name = model_name(method, objective)
        if ctx.checkpoint_dir is not None and jax.process_index() == 0:
            # Logdirs of one name under different parents share this folder: one writer.
            lock_folder(
                ctx.checkpoint_dir / name,
                "checkpoint folder",
                "wait for it to finish, or give this logdir another name (or set "
                "train.checkpoint_dir)",
            )
        log = ctx.training_log(name) if ctx.training_log else None
        try:
            result = fit_autoencoder(
                spec,
                objectives.training_data(objective, pair.train),
                objectives.training_data(objective, pair.val),
                method_key(cfg.seed, method),
                settings,
                checkpoint_dir=ctx.checkpoint_dir / name if ctx.checkpoint_dir else None,
                identity={
                    **(ctx.identity or {}),
                    "train": training_identity(settings),
                    "season_pair": pair.name,
                    "method": method,
                },
                log=log,
                name=f"{pair.name} {name}",
                mesh=ctx.mesh,
                objective=objective,
            )
        finally:
            if log is not None:
                log.close()
        yield _autoencoder_descriptors(method, objective, result, pair, cfg)


def _autoencoder_descriptors(
    method: str, objective: str, result, pair: PairData, cfg: SweepConfig
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
        fit_seconds=result.train_seconds,
        n_iter=result.epochs,
        stopped_early=result.stopped_early,
        basis_name="hidden_units",
        fitted=Fitted(folder=model_name(method, objective), encode="autoencoder", state=None),
    )
