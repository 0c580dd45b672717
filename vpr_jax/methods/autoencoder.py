"""What the two auto-encoders (``fae``, ``cae``) share as methods: their settings' checks,
their starts, and the method a model's architecture makes; a fit trains one model
(``vpr_jax.methods.training``) and its state is the model (``ae.ModelState``).

The model learns from both seasons' training images: the images themselves for
``reconstruct``, the aligned places' pairs for the paired objectives
(``vpr_jax.encoders.objectives``); each objective is rows of its own. What it sees is
its ``input`` (``training.INPUTS``): with a residual input it first removes the leading
``residual_pcs`` components of the pair's PCA fit, then standardises each image
(``residual``) or not (``residual_pixels``). Its training settings (``TrainingSettings``:
learning rate, augmentation, temperature...) are its own, each ``train.*``'s value unless
given, and a list for one is a sweep axis like any other (``train.augment=auto``:
``augment=[true,false]``). Every objective starts from the same initial weights (the key of
the seed and the method's name).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import numpy as np

from vpr_jax.config import TrainConfig
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import objectives
from vpr_jax.encoders.train import Start
from vpr_jax.errors import UserError
from vpr_jax.methods.contract import (
    ROWS,
    Method,
    PCAFit,
    Report,
    Training,
    TrainingSet,
    Validation,
)
from vpr_jax.methods.training import INPUTS, Fit, Model, fit_model, is_residual

# How the weights start (<method>.init): drawn, or at a linear solution of the model's own
# inputs (``ae.pca_start``, ``ae.lda_start``): each direction a unit beside its negative.
INITS = ("random", "pca", "whitened_pca", "lda")
LDA_SHRINKAGE = 0.1  # init=lda regularises as the lda method does by default


@dataclasses.dataclass(frozen=True)
class TrainingSettings:
    """The training settings an auto-encoder has of its own: ``train.*``'s meaning, and
    ``train.*``'s value where not given (the sweep fills them in)."""

    epochs: int | None = None  # at most; early stopping may end sooner
    batch_size: int | None = None
    learning_rate: float | None = None
    optimizer: str | None = None  # adam | adamw | sgd
    patience: int | None = None  # epochs without a better validation recall@1
    augment: Any = None  # true (the paper's), false, place (train.augment=auto: the axis)
    temperature: float | None = None  # the contrastive objective's
    contrastive_radius: int | None = None  # the contrastive objective's route mask
    start_decay: float | None = None  # the pull towards the starting weights (L2-SP)

    def training(self) -> TrainConfig:
        """These settings as ``train.*`` (checked there); None where not yet filled in."""
        return TrainConfig(**{k: v for k, v in _training_values(self).items() if v is not None})


TRAINING_FIELDS = tuple(f.name for f in dataclasses.fields(TrainingSettings))


def _training_values(settings: Any) -> dict:
    return {k: getattr(settings, k) for k in TRAINING_FIELDS}


def start_of(init: str, train: np.ndarray, aligned) -> Start | None:
    """The start ``init`` names, from the training images (both seasons) or, for ``lda``,
    their aligned places; None for drawn weights."""
    if init == "lda":
        a, b = aligned
        return functools.partial(ae.lda_start, images_a=a, images_b=b, shrinkage=LDA_SHRINKAGE)
    if init in ("pca", "whitened_pca"):
        return functools.partial(ae.pca_start, images=train, whiten=init == "whitened_pca")
    return None


def check_common(group: str, settings: Any) -> None:
    """The settings both auto-encoders have: objectives, input, start, training."""
    chosen = list(settings.objective)
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
        (
            settings.input in INPUTS,
            f"{group}.input={settings.input} is not one of the auto-encoders' inputs: use "
            f"{', '.join(INPUTS)} (gradients, patchnorm and combinations are the linear "
            "methods': an auto-encoder reconstructs images)",
        ),
        (
            settings.init in INITS,
            f"{group}.init={settings.init} is unknown: use {', '.join(INITS)}",
        ),
        (
            settings.residual_pcs >= 1,
            f"{group}.residual_pcs={settings.residual_pcs} must be >= 1 (pixels remove none)",
        ),
    )
    for ok, message in checks:
        if not ok:
            raise UserError(message)
    try:
        settings.training()
    except UserError as err:  # train.*'s checks, named for this method
        raise UserError(str(err).replace("train.", f"{group}.", 1)) from None


def without_aligned_places(group: str, settings: Any, training: TrainingSet, log) -> Any:
    """On data without aligned training places the paired objectives give way (the paper's
    ``reconstruct`` stays) and the lda start gives way to the whitened PCA start (the
    nearest that needs no alignment, with a note); asked for by name, they are refused."""
    if training.aligned:
        return settings
    if settings.init == "lda":
        if "init" in training.given:
            raise UserError(
                f"{group}.init=lda needs aligned training places, which the data do not have: "
                "set data.train_source and data.train_root to an aligned route to learn from, "
                f"or use {group}.init=whitened_pca"
            )
        log(f"note: {group}.init=lda needs aligned training places: {group} starts at whitened_pca")
        settings = dataclasses.replace(settings, init="whitened_pca")
    paired = [o for o in settings.objective if o in objectives.PAIRED]
    if paired and "objective" in training.given:
        raise UserError(
            f"{group}.objective={','.join(paired)} needs aligned training places, which the "
            "data do not have: set data.train_source and data.train_root to an aligned route "
            "to learn from (e.g. Nordland's training places), or leave them out"
        )
    kept = tuple(o for o in settings.objective if o not in paired) or ("reconstruct",)
    return dataclasses.replace(settings, objective=kept)


def check(group: str, settings: Any, training: TrainingSet, log) -> Any:
    """What the data and the devices allow: the paired objectives and the lda start need
    aligned places; a residual input needs its components in the shared PCA fit; each
    batch splits its examples evenly over the devices (a paired example is a place's two
    images)."""
    settings = without_aligned_places(group, settings, training, log)
    if is_residual(settings.input):
        k, limit = settings.residual_pcs, training.pca_limit
        if k >= limit:
            raise UserError(
                f"{group}.residual_pcs={k} leaves no component: PCA of {training.n_images} "
                f"training images has {limit}, so use a smaller count"
            )
        training.check_pca_components(group, k)
    per_example = max(objectives.examples_per_image(o) for o in settings.objective)
    step = training.devices * per_example
    if settings.batch_size % step:
        raise UserError(
            f"{group}.batch_size={settings.batch_size} (train.batch_size unless set) does not "
            f"split over {training.devices} devices: use a multiple of {step}, or set "
            "mesh.devices"
        )
    return settings


def needs(settings: Any) -> tuple[str, ...]:
    """The validation places, a training folder and the devices; a residual input the
    pair's PCA fit too."""
    return ("validation", "training", "mesh") + (
        ("pca_fit",) if settings is not None and is_residual(settings.input) else ()
    )


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
        axes={"objective": ROWS},
        needs=needs,
        random=True,
        check=lambda s, training, log: check(name, s, training, log),
        report=report,
    )


def start_name(init: str, units: int) -> str:
    """What a model's weights start from, in words: "lda in 256 directions"."""
    if init == "random":
        return "drawn weights"
    return f"{init} in {units // 2} directions"


def report(
    state: ae.ModelState, settings: dict, basis: np.ndarray | None = None, units: int = 0
) -> Report:
    """Epochs, early stopping, the training time (over every session) of a fit, the epoch
    it kept and what it started from (``units``: the units a linear start sets)."""
    kept = None if state.kept_epoch is None else int(state.kept_epoch)
    return Report(
        n_iter=int(state.epochs),
        stopped_early=bool(state.stopped_early),
        fit_seconds=float(state.train_seconds),
        basis=basis,
        basis_name="hidden_units",
        kept_epoch=kept,
        start=start_name(settings["init"], units),
        start_state=None
        if state.start_params is None
        else dataclasses.replace(
            state, params=state.start_params, start_params=None, kept_epoch=np.int32(0)
        ),
    )
