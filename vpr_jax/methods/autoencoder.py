"""What the two auto-encoders (``fae``, ``cae``) share as methods: a fit trains one model
(or resumes it, or restores it from its checkpoint) and keeps the epoch whose code scores the
best recall@1 on the validation places; its state is the model (``ae.ModelState``).

The model learns from both seasons' training images: the images themselves for
``reconstruct``, the aligned places' pairs for the paired objectives
(``vpr_jax.encoders.objectives``). With ``input=residual`` it first removes the leading
components of the pair's PCA fit, as many as PCA change removal picks on the validation
places (``residual_input``); with ``train.augment=auto`` a model is trained with and one
without augmentation and the better on validation is kept. Every objective starts from the
same initial weights (the key of the seed and the method's name).
"""

from __future__ import annotations

import dataclasses
import functools
import zlib
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import numpy as np

from vpr_jax import sharding
from vpr_jax.config import TrainConfig, plain, training_identity
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import objectives, pca
from vpr_jax.encoders.train import (
    Start,
    TrainingData,
    TrainOptions,
    TrainResult,
    check_batch_splits,
    fit_autoencoder,
)
from vpr_jax.errors import UserError
from vpr_jax.files import lock_folder
from vpr_jax.methods.contract import Method, PCAFit, Report, Training, TrainingSet, Validation

INPUTS = ("pixels", "residual")  # what the model sees: <method>.input
# How the weights start (<method>.init): drawn, or at a linear solution of the model's own
# inputs (``ae.pca_start``, ``ae.lda_start``): each direction a unit beside its negative.
INITS = ("random", "pca", "whitened_pca", "lda")
LDA_SHRINKAGE = 0.1  # init=lda regularises as the lda method does by default


def start_of(init: str, train: np.ndarray, aligned) -> Start | None:
    """The start ``init`` names, from the training images (both seasons) or, for ``lda``,
    their aligned places; None for drawn weights."""
    if init == "lda":
        a, b = aligned
        return functools.partial(ae.lda_start, images_a=a, images_b=b, shrinkage=LDA_SHRINKAGE)
    if init in ("pca", "whitened_pca"):
        return functools.partial(ae.pca_start, images=train, whiten=init == "whitened_pca")
    return None


def check_common(
    group: str, objective: tuple[str, ...], input: str, epochs, init: str = "random"
) -> None:
    """The settings both auto-encoders have: objectives, input, epochs, start."""
    chosen = list(objective)
    unknown = [o for o in chosen if o not in objectives.OBJECTIVES]
    checks = (
        (len(chosen) > 0, f"{group}.objective is empty: e.g. {group}.objective=cross_season"),
        (
            not unknown,
            f"{group}.objective={chosen} names unknown {unknown}: choose from "
            f"{', '.join(objectives.OBJECTIVES)}",
        ),
        (
            len(set(chosen)) == len(chosen),
            f"{group}.objective={chosen} repeats one: name each once",
        ),
        (input in INPUTS, f"{group}.input={input} is unknown: use {' or '.join(INPUTS)}"),
        (epochs is None or epochs >= 1, f"{group}.epochs={epochs} must be >= 1"),
        (init in INITS, f"{group}.init={init} is unknown: use {', '.join(INITS)}"),
    )
    for ok, message in checks:
        if not ok:
            raise UserError(message)


def without_aligned_places(group: str, settings: Any, training: TrainingSet, log) -> Any:
    """On data without aligned training places the paired objectives give way (the seed's
    ``reconstruct`` stays) and the lda start gives way to the whitened PCA start (the
    nearest that needs no alignment, with a note); asked for by name, they are refused."""
    if training.aligned:
        return settings
    if settings.init == "lda":
        if "init" in training.asked:
            raise UserError(
                f"{group}.init=lda needs aligned training places, which the data do not have: "
                "set data.train_source and data.train_root to an aligned route to learn from, "
                f"or use {group}.init=whitened_pca"
            )
        log(f"note: {group}.init=lda needs aligned training places: {group} starts at whitened_pca")
        settings = dataclasses.replace(settings, init="whitened_pca")
    paired = [o for o in settings.objective if o in objectives.PAIRED]
    if paired and "objective" in training.asked:
        raise UserError(
            f"{group}.objective={','.join(paired)} needs aligned training places, which the "
            "data do not have: set data.train_source and data.train_root to an aligned route "
            "to learn from (e.g. Nordland's training places), or leave them out"
        )
    kept = tuple(o for o in settings.objective if o not in paired) or ("reconstruct",)
    return dataclasses.replace(settings, objective=kept)


def check_devices(settings: Any, train: TrainConfig, mesh) -> None:
    """Data-parallel training splits each batch's examples evenly over the devices (a
    paired example is a place's two images)."""
    per_example = max(objectives.examples_per_image(o) for o in settings.objective)
    check_batch_splits(train.batch_size, mesh, per_example)


def pca_components(settings: Any, training: TrainingSet) -> int:
    """A residual input removes up to the largest removed count of the pair's PCA fit."""
    return max(training.removed_pcs) if settings.input == "residual" else 0


class ResidualInput(NamedTuple):
    """What a residual-input model takes out of every image: PCA's validation-selected
    count of the pair's leading components."""

    k: int
    val_recall_at_1: float  # PCA's, with k removed
    fixed: dict | None  # ae.with_removal's arrays (None when k = 0: the images themselves)


def residual_input(pca_fit: PCAFit, validation: Validation) -> ResidualInput:
    """The count PCA change removal chooses on the validation places, by the sweep's rule:
    the best validation recall@1 among the sweep's removed counts, then margin, then the
    fewest."""
    state = pca_fit.state
    counts = sorted(k for k in pca_fit.removed_pcs if k <= state.components.shape[0])
    scores = validation.scores(lambda x: pca.suffix_descriptors(state, x), tuple(counts))
    best = max(range(len(counts)), key=lambda i: scores[i])  # the first of equals
    k = counts[best]
    fixed = {"removal_mean": state.mean, "removal_basis": state.components[:k]} if k else None
    return ResidualInput(k, float(scores[best][0]), fixed)


def augment_variants(settings: TrainConfig) -> tuple[tuple[str, TrainConfig], ...]:
    """(folder suffix, settings) of each model ``train.augment`` asks for: one, or with
    ``auto`` the model with augmentation and the one without."""
    if settings.augment != "auto":
        return (("", settings),)
    return (
        ("_augmented", dataclasses.replace(settings, augment=True)),
        ("_plain", dataclasses.replace(settings, augment=False)),
    )


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
    """Train (or resume, or restore) the fit's model and keep its best epoch; with
    ``train.augment=auto`` the better of two models on validation (the first on a tie)."""
    removal = residual_input(pca_fit, validation) if pca_fit is not None else None
    spec = fit.model.spec(removal.k if removal else 0)
    epochs = fit.values["epochs"] or training.settings.epochs  # <method>.epochs overrides
    settings = dataclasses.replace(training.settings, epochs=epochs)
    key = jax.random.fold_in(key, zlib.crc32(fit.name.encode()))
    objective = fit.values["objective"]
    data = TrainingData(
        objectives.training_data(objective, train),
        objectives.training_data(objective, validation.images),
    )
    trained = [
        _train(fit, suffix, spec, variant, data, key, removal, validation, training, mesh)
        for suffix, variant in augment_variants(settings)
    ]
    chosen = better_model(trained)
    best = trained[chosen]
    if len(trained) > 1:
        variants = augment_variants(settings)
        kept = variants[chosen][0]
        scores = ", ".join(
            f"{suffix.strip('_')} {r.best_score:.3f}"
            for (suffix, _), r in zip(variants, trained, strict=True)
        )
        training.log(kept).line(
            f"{training.name}{kept}: kept, the better on the validation places (recall@1 {scores})"
        )
    return ae.ModelState(
        params=jax.tree.map(sharding.to_host, best.params),  # encoded on one device
        epochs=np.int32(best.epochs),
        stopped_early=np.bool_(best.stopped_early),
        train_seconds=np.float32(sum(r.train_seconds for r in trained)),
        spec=spec,
        image_shape=tuple(int(s) for s in train.shape[1:3]),
    )


def better_model(trained: list[TrainResult]) -> int:
    """Which of the models ``train.augment=auto`` trained is kept: the best validation
    score, the first on a tie. By position: models hold arrays, so they do not compare."""
    return max(range(len(trained)), key=lambda i: trained[i].best_score)


def _train(
    fit: Fit,
    suffix: str,
    spec: ae.Spec,
    settings: TrainConfig,
    data: TrainingData,
    key: jax.Array,
    removal: ResidualInput | None,
    validation: Validation,
    training: Training,
    mesh,
) -> TrainResult:
    """One model: trained, resumed or restored in its checkpoint folder."""
    folder = training.folder / f"training{suffix}" if training.folder is not None else None
    if folder is not None and jax.process_index() == 0:
        # Logdirs of one name under different parents share this folder: one writer.
        lock_folder(
            folder,
            "checkpoint folder",
            "wait for it to finish, or give this logdir another name (or set train.checkpoint_dir)",
        )
    log = training.log(suffix)
    name = training.name + suffix
    if removal is not None:
        log.line(
            f"{name}: input residual, {removal.k} leading components removed (PCA's "
            f"validation-selected count, validation recall@1 {removal.val_recall_at_1:.3f})"
        )
    options = TrainOptions(
        key=key,
        settings=settings,
        objective=fit.values["objective"],
        validate=lambda encode: validation.recall_at_1(encode)[0],
        checkpoint_dir=folder,
        identity={
            **training.identity,
            "model": plain(fit.values),
            "train": training_identity(settings),
        },
        log=log,
        name=name,
        mesh=mesh,
        fixed=removal.fixed if removal else None,
        start=fit.model.start,
    )
    try:
        return fit_autoencoder(spec, data, options)
    finally:
        log.close()


def autoencoder_method(
    name: str, model_of: Callable[[np.ndarray, Any, dict], Model], settings: type, report: Callable
) -> Method:
    """An auto-encoder as a method: ``model_of(train, aligned, settings)`` its architecture
    and start; trained from the runner's validation places, training folder, devices and
    (with a residual input) the pair's PCA fit; once per seed and per objective, each
    objective its own rows."""

    def fit(
        train,
        aligned,
        key,
        *,
        validation: Validation,
        training: Training,
        mesh,
        pca_fit: PCAFit | None = None,
        **values,
    ) -> ae.ModelState:
        return fit_model(
            Fit(name=name, model=model_of(train, aligned, values), values=values),
            train,
            key,
            validation=validation,
            training=training,
            mesh=mesh,
            pca_fit=pca_fit,
        )

    return Method(
        fit=fit,
        encode=ae.encode_state,
        settings=settings,
        uses=("validation", "training", "mesh", "pca_fit"),
        random=True,
        variants="objective",
        check=lambda s, training, log: without_aligned_places(name, s, training, log),
        check_devices=check_devices,
        pca_components=pca_components,
        report=report,
    )


def report(state: ae.ModelState, settings: dict, basis: np.ndarray | None = None) -> Report:
    """Epochs, early stopping and the training time (over every session) of a fit."""
    return Report(
        n_iter=int(state.epochs),
        stopped_early=bool(state.stopped_early),
        fit_seconds=float(state.train_seconds),
        basis=basis,
        basis_name="hidden_units",
    )
