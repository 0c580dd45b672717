"""How an auto-encoder method trains: from the runner's resources (its validation places, a
training folder and log, the devices, the pair's PCA fit for a residual input) and its own
settings to ``vpr_jax.encoders.train.fit_autoencoder``, and back to a ``ModelState`` the
method's encode reads. The model keeps the epoch whose code scores the best recall@1 on the
validation places; a finished checkpoint is restored, an unfinished one resumed."""

from __future__ import annotations

import dataclasses
import zlib
from collections.abc import Callable
from typing import NamedTuple

import jax
import numpy as np

from vpr_jax import sharding
from vpr_jax.config import TrainConfig, plain, training_identity
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import objectives
from vpr_jax.encoders.train import Start, TrainingData, TrainOptions, TrainResult, fit_autoencoder
from vpr_jax.methods.contract import PCAFit, Training, Validation


def training_values(values: dict) -> dict:
    """The ``train.*`` settings among a fit's values (an auto-encoder has each as its own)."""
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    return {k: v for k, v in values.items() if k in names}


# What the model sees (<method>.input), steps applied in this order: the residual after the
# pair's leading residual_pcs components (residual inputs), then each image standardised
# (zero mean, std 1/4: standardised, residual) or not (pixels, residual_pixels: the FAE
# centres them at fae.input_centre, the CAE takes them as they are). The linear methods'
# other inputs (gradients, patchnorm, combinations) are no images a decoder reconstructs.
INPUTS = ("standardised", "pixels", "residual", "residual_pixels")


def is_residual(input: str) -> bool:
    """Whether the input removes the pair's leading components first."""
    return input in ("residual", "residual_pixels")


def is_standardised(input: str) -> bool:
    """Whether each image is standardised before the model (else the FAE centres it and
    the CAE takes it as it is)."""
    return input in ("standardised", "residual")


def recorded_as_before(values: dict) -> dict:
    """A fit's values as checkpoints have always recorded them in their identity: the input
    as ``pixels`` or ``residual`` and ``standardise`` beside it, so a model trained before
    the two became one input resumes."""
    return {
        **values,
        "input": "residual" if is_residual(values["input"]) else "pixels",
        "standardise": is_standardised(values["input"]),
    }


class Model(NamedTuple):
    """What tells one auto-encoder from the other: its architecture and its start."""

    spec: Callable[[int], ae.Spec]  # removed components -> the architecture
    start: Start | None  # other starting weights than the drawn ones (the FAE's linear start)


class Fit(NamedTuple):
    """One fit of an auto-encoder method."""

    name: str  # the method's: folds into the key, so fae and cae start from other draws
    model: Model
    values: dict  # every setting of the fit (its objective, epochs...): part of the
    # checkpoint's identity


def fit_model(
    fit: Fit,
    train: np.ndarray,
    key: jax.Array,
    *,
    validation: Validation,
    training: Training,
    mesh,
    pca_fit: PCAFit | None,
) -> ae.ModelState:
    """Train (or resume, or restore) the fit's model and keep its best epoch."""
    k = fit.values["residual_pcs"] if is_residual(fit.values["input"]) else 0
    removal = None
    if k:
        state = pca_fit.state
        removal = {"removal_mean": state.mean, "removal_basis": state.components[:k]}
    spec = fit.model.spec(k)
    settings = dataclasses.replace(
        TrainConfig(**training_values(fit.values)),
        checkpoint_every_s=training.checkpoint_every_s,
    )
    key = jax.random.fold_in(key, zlib.crc32(fit.name.encode()))
    objective = fit.values["objective"]
    data = TrainingData(
        objectives.training_data(objective, train),
        objectives.training_data(objective, validation.images),
    )
    result = _train(fit, spec, settings, data, key, removal, validation, training, mesh)
    return ae.ModelState(
        params=jax.tree.map(sharding.to_host, result.params),  # encoded on one device
        epochs=np.int32(result.epochs),
        stopped_early=np.bool_(result.stopped_early),
        train_seconds=np.float32(result.train_seconds),
        spec=spec,
        image_shape=tuple(int(s) for s in train.shape[1:3]),
        kept_epoch=np.int32(result.best_epoch),
        start_params=None
        if result.best_epoch == 0 or result.start_params is None
        else jax.tree.map(sharding.to_host, result.start_params),
    )


def _train(
    fit: Fit,
    spec: ae.Spec,
    settings: TrainConfig,
    data: TrainingData,
    key: jax.Array,
    removal: dict | None,
    validation: Validation,
    training: Training,
    mesh,
) -> TrainResult:
    """One model: trained, resumed or restored in its checkpoint folder."""
    folder = training.folder / "training" if training.folder is not None else None
    log = training.log("")
    if removal is not None:
        log.line(
            f"{training.name}: input residual, {len(removal['removal_basis'])} leading "
            "components of the pair's PCA fit removed"
        )
    options = TrainOptions(
        key=key,
        settings=settings,
        objective=fit.values["objective"],
        validate=lambda encode: validation.recall_at_1(encode)[0],
        checkpoint_dir=folder,
        identity={
            **training.identity,
            "model": plain(recorded_as_before(fit.values)),
            "train": training_identity(settings),
        },
        log=log,
        name=training.name,
        mesh=mesh,
        fixed=removal,
        start=fit.model.start,
    )
    try:
        return fit_autoencoder(spec, data, options)
    finally:
        log.close()
