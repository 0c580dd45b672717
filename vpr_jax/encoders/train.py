"""Training an auto-encoder: epochs of the compiled programs (raw optax, a jitted train
step: ``vpr_jax.encoders.train_programs``), early stopping, resumable.

``fit_autoencoder`` is a short loop over named steps on one ``TrainState``:
``init_or_restore`` (a fresh state, or the checkpoint's), then per epoch ``train_epoch``
(a shuffled pass over the training set), ``score_epoch`` (the validation loss, and the
score that selects: the validation places' recall@1 when the caller gives a ``validate``,
else minus the loss) and ``end_epoch`` (keep the best-scoring parameters; stop after
``patience`` epochs without a better score), and a checkpoint when one is due. The
starting weights are scored too (epoch 0): training is kept only where it improves.

Selecting by recognition, not by the loss: an auto-encoder's validation loss keeps falling
while its code learns more of the season and the light, which recognition must ignore; on
real frames the epoch of least loss is rarely the epoch of best recall.

Every random draw comes from ``(key, epoch, step)``, so a run resumed from an epoch's
checkpoint continues exactly as the uninterrupted run would have.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from jaxtyping import Array

from vpr_jax import sharding
from vpr_jax.config import TrainConfig, plain
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import checkpoints, objectives
from vpr_jax.encoders.train_programs import (
    augment_config,
    check_batch_splits,
    make_eval_loss,
    make_optimizer,
    make_train_step,
    take_batch,
)
from vpr_jax.errors import UserError
from vpr_jax.files import lock_folder
from vpr_jax.progress import Bar

SELECT_RECALL, SELECT_LOSS = "validation recall@1", "validation loss"
# validate(encode) -> the validation places' recall@1 of a model's encode(images) -> codes
Validate = Callable[[Callable[[np.ndarray], Array]], float]
Start = Callable[[Any, dict], dict]  # (graphdef, drawn params) -> the starting params


class TrainState(NamedTuple):
    """Everything training needs to go on, saved as one checkpoint item per saved epoch."""

    params: dict  # the current parameters
    opt_state: Any  # the optimizer's state (optax)
    best_params: dict  # the parameters of the best-scoring epoch so far
    best_score: float  # their score (validation recall@1, or minus the loss); -inf at first
    best_val: float  # their validation loss
    best_epoch: int  # the epoch they are from (0: the starting weights)
    bad_epochs: int  # epochs since the best one: early stopping's counter
    epoch: int  # epochs finished
    step: int  # optimizer steps taken
    seconds: float  # training time, summed over every session so far


class TrainResult(NamedTuple):
    graphdef: object  # the architecture: ae.make_encode(graphdef)(params, images)
    params: dict  # the best parameters (highest score: see selected_by)
    epochs: int  # epochs trained in total (before any interruption too)
    steps: int
    best_val_loss: float  # the validation loss of the best parameters
    best_score: float  # their score: validation recall@1, or minus the validation loss
    best_epoch: int  # the epoch they are from (0: the starting weights)
    selected_by: str  # SELECT_RECALL or SELECT_LOSS
    stopped_early: bool
    restored: bool  # a finished model was restored from its checkpoint, not trained
    resumed_epoch: int  # epoch training resumed after (0: from scratch)
    train_seconds: float  # training time, summed over every session that trained it
    start_params: dict | None = None  # the starting weights (epoch 0), untouched by training


class TrainingLog(Protocol):
    """Where training reports: TensorBoard and the run log in the sweep."""

    def begin(self, step: int) -> None: ...
    def scalar(self, tag: str, value: float, step: int) -> None: ...
    def images(self, tag: str, images: np.ndarray, step: int) -> None: ...
    def line(self, text: str) -> None: ...
    def close(self) -> None: ...


class NoLog:
    """A training log that keeps nothing: training without a sweep around it."""

    def begin(self, step: int) -> None:
        pass

    def scalar(self, tag: str, value: float, step: int) -> None:
        pass

    def images(self, tag: str, images: np.ndarray, step: int) -> None:
        pass

    def line(self, text: str) -> None:
        pass

    def close(self) -> None:
        pass


class TrainingData(NamedTuple):
    """What a model learns from: an objective's examples (``objectives.training_data``)."""

    train: np.ndarray  # the training places' examples
    val: np.ndarray  # the validation places' examples: their loss, and the images shown


class TrainOptions(NamedTuple):
    """How one model trains, beside its spec and data."""

    key: jax.Array  # every random draw: the initial weights, the order, the augmentation
    settings: TrainConfig = TrainConfig()
    objective: str = "reconstruct"  # vpr_jax.encoders.objectives
    validate: Validate | None = None  # the validation places' recall@1 of an encode; None:
    # the validation loss selects
    checkpoint_dir: Path | None = None  # where epochs are committed; None: nothing saved
    identity: dict | None = None  # what must match a checkpoint to resume it
    log: TrainingLog = NoLog()
    name: str = "auto-encoder"  # how progress lines call the model
    mesh: Mesh | None = None  # devices each batch is split over
    fixed: dict | None = None  # a removal's arrays (ae.with_removal)
    start: Start | None = None  # other starting weights (ae.pca_start; name it in identity)


def _examples(images: np.ndarray, n: int) -> np.ndarray:
    picks = np.linspace(0, len(images) - 1, min(n, len(images))).round().astype(int)
    return images[picks]


class Trainer(NamedTuple):
    """One model's compiled steps and the settings it trains with."""

    graphdef: Any  # the architecture: ae.make_encode(graphdef)(params, images)
    objective: str  # vpr_jax.encoders.objectives: what the model learns to output
    train_step: Callable  # (params, opt_state, batch, key) -> (params, opt_state, metrics)
    eval_loss: Callable  # (params, examples) -> the objective's mean loss
    reconstruct: Callable  # (params, images) -> images
    settings: TrainConfig
    anchor: dict | None  # the starting trainable weights train.start_decay pulls towards
    batch_size: int  # examples per step: images, or places for cross_season
    steps_per_epoch: int  # the tail that fills no batch is dropped: one compiled shape


def make_trainer(
    spec: ae.Spec,
    image_shape: tuple[int, int],
    n_train: int,
    key: jax.Array,
    settings: TrainConfig,
    mesh: Mesh | None = None,
    objective: str = "reconstruct",
    fixed: dict | None = None,
    start: Start | None = None,
) -> tuple[Trainer, TrainState]:
    """The model's compiled steps and its initial state (weights drawn from ``key``; the
    model's fixed arrays from ``fixed``: ``ae.with_removal``; then ``start(graphdef,
    params)``, e.g. ``ae.pca_start``). ``n_train`` counts examples; a step sees
    ``train.batch_size`` images, so a paired step takes half as many places."""
    graphdef, params = ae.build(spec, jax.random.fold_in(key, 0), image_shape)
    if spec.removed:
        if fixed is None:
            raise ValueError(f"a model that removes {spec.removed} components needs them")
        params = ae.with_removal(params, fixed["removal_mean"], fixed["removal_basis"])
    if start is not None:
        params = start(graphdef, params)
    tx = make_optimizer(settings, ae.frozen(spec))
    per_step = max(1, settings.batch_size // objectives.examples_per_image(objective))
    batch_size = min(per_step, n_train)
    augment = augment_config(settings.augment)
    temperature, radius = settings.temperature, settings.contrastive_radius
    anchor = None  # train.start_decay's: the starting weights, where the steps run
    if settings.start_decay:
        anchor = ae.split_fixed(params)[0]
        anchor = anchor if mesh is None else sharding.replicate(anchor, mesh)
    step = make_train_step(
        graphdef, tx, augment, mesh, objective, temperature, radius, settings.start_decay
    )
    trainer = Trainer(
        graphdef=graphdef,
        objective=objective,
        train_step=step,
        eval_loss=make_eval_loss(graphdef, batch_size, objective, temperature, radius),
        reconstruct=ae.make_reconstruct(graphdef),
        settings=settings,
        anchor=anchor,
        batch_size=batch_size,
        steps_per_epoch=n_train // batch_size,
    )
    fresh = TrainState(
        params=params,
        opt_state=tx.init(ae.split_fixed(params)[0]),
        best_params=params,
        best_score=-math.inf,
        best_val=math.inf,
        best_epoch=0,
        bad_epochs=0,
        epoch=0,
        step=0,
        seconds=0.0,
    )
    return trainer, fresh


def checkpoint_meta(
    spec: ae.Spec,
    image_shape: tuple[int, int],
    identity: dict | None,
    objective: str = "reconstruct",
    selected_by: str = SELECT_LOSS,
) -> dict:
    """What a checkpoint must hold to be reused: the same model, image shape, objective,
    selection and identity (a checkpoint whose best parameters were chosen by another rule
    is refused, not resumed)."""
    return {
        "spec": ae.spec_to_json(spec),
        "image_shape": list(image_shape),
        "objective": objective,
        "selected_by": selected_by,
        "identity": plain(identity or {}),
    }


def init_or_restore(
    fresh: TrainState,
    checkpoint_dir: Path | None,
    meta: dict,
    log: TrainingLog,
    name: str,
) -> tuple[TrainState, dict | None]:
    """The checkpoint's newest state and its metadata (``done`` says whether training
    finished), or ``fresh`` and None when there is none. A checkpoint of another model, data
    or settings (``meta`` differs) is refused."""
    if checkpoint_dir is None or not checkpoints.has_checkpoint(checkpoint_dir):
        return fresh, None
    saved = checkpoints.read_meta(checkpoint_dir)
    if any(saved.get(k) != v for k, v in meta.items()):
        raise UserError(
            f"{checkpoint_dir} holds a model trained on other data or settings: "
            "delete that folder, or set train.checkpoint_dir=PATH to keep both"
        )
    state, saved = checkpoints.restore(checkpoint_dir, fresh)
    log.line(
        f"{name}: restored the trained model from {checkpoint_dir}"
        if saved["done"]
        else f"{name}: resuming after epoch {state.epoch} (step {state.step})"
    )
    return state, saved


def train_epoch(
    trainer: Trainer,
    state: TrainState,
    train_dev: Array,
    key: jax.Array,
    log: TrainingLog,
    name: str,
) -> tuple[TrainState, np.ndarray]:
    """One shuffled pass over the training set; returns the state and each step's loss."""
    epoch = state.epoch + 1
    epoch_key = jax.random.fold_in(key, epoch)
    order = jax.random.permutation(jax.random.fold_in(epoch_key, 0), len(train_dev))
    params, opt_state, losses = state.params, state.opt_state, []
    with Bar(trainer.steps_per_epoch, f"{name} epoch {epoch}/{trainer.settings.epochs}") as bar:
        for s in range(trainer.steps_per_epoch):
            batch, places = take_batch(train_dev, order, s, trainer.batch_size)
            params, opt_state, metrics = trainer.train_step(
                params,
                opt_state,
                batch,
                jax.random.fold_in(epoch_key, s + 1),
                places,
                trainer.anchor,
            )
            losses.append(metrics["loss"])  # on the device until the epoch ends: no waits
            if epoch == 1 and s == 0 and trainer.settings.augment:
                shown, _ = objectives.inputs_and_targets(
                    trainer.objective, sharding.to_host(metrics["inputs"])
                )
                log.images("inputs/augmented", _examples(np.asarray(shown), 8), state.step + 1)
            bar.advance()
    losses = np.asarray(jnp.stack(losses)) if losses else np.zeros(0)
    for i, loss in enumerate(losses):
        log.scalar("loss/train", float(loss), state.step + 1 + i)
    state = state._replace(
        params=params, opt_state=opt_state, epoch=epoch, step=state.step + len(losses)
    )
    return state, losses


class EpochScore(NamedTuple):
    """How one epoch's parameters do on the validation places."""

    val_loss: float  # the objective's loss
    recall_at_1: float  # their recall@1 (NaN without a validate)
    score: float  # what selects: recall_at_1, or minus val_loss without a validate


def score_epoch(
    trainer: Trainer,
    params: dict,
    val_images: np.ndarray,
    validate: Validate | None,
    mesh: Mesh | None,
) -> EpochScore:
    """The validation loss of ``params`` and the score that selects among epochs."""
    val_loss = trainer.eval_loss(params, val_images)
    if validate is None:
        return EpochScore(val_loss, math.nan, -val_loss)
    if mesh is not None:  # encode on one device, as the sweep encodes the chosen model
        params = jax.tree.map(sharding.to_host, params)
    encode = ae.make_encode(trainer.graphdef)
    recall = float(validate(lambda images: encode(params, images)))
    return EpochScore(val_loss, recall, recall)


def end_epoch(
    state: TrainState, scored: EpochScore, settings: TrainConfig
) -> tuple[TrainState, bool, bool]:
    """Keep the best-scoring parameters (the earlier epoch on a tie) and count epochs
    without a better score: (state, stopped early, done)."""
    if scored.score > state.best_score:
        state = state._replace(
            best_params=state.params,
            best_score=scored.score,
            best_val=scored.val_loss,
            best_epoch=state.epoch,
            bad_epochs=0,
        )
    else:
        state = state._replace(bad_epochs=state.bad_epochs + 1)
    stopped_early = state.bad_epochs >= settings.patience and state.epoch < settings.epochs
    return state, stopped_early, stopped_early or state.epoch == settings.epochs


def log_epoch(
    trainer: Trainer,
    state: TrainState,
    losses: np.ndarray,
    scored: EpochScore,
    val_examples: np.ndarray,
    log: TrainingLog,
    name: str,
) -> None:
    """The validation loss and recall@1 (the two curves), six validation examples in rows of
    input | target | output (reconstruct: the images over their reconstructions;
    cross_season: both seasons, their mean, the output for each season; none for the
    contrastive objective, which has no decoder to show), one line."""
    log.scalar("loss/validation", scored.val_loss, state.step)
    if not math.isnan(scored.recall_at_1):
        log.scalar("validation/recall_at_1", scored.recall_at_1, state.step)
    if trainer.objective not in objectives.CODE_ONLY:
        shown = _examples(val_examples, 6)
        inputs, targets = (
            np.asarray(x) for x in objectives.inputs_and_targets(trainer.objective, shown)
        )
        outputs = np.asarray(trainer.reconstruct(state.params, inputs))
        rows = (
            [inputs, outputs]
            if trainer.objective == "reconstruct"
            else [inputs, targets[: len(shown)], outputs]
        )
        log.images("reconstructions/validation", np.concatenate(rows), state.step)
    train_loss = f"{float(np.mean(losses)):.5f}" if len(losses) else "-"
    recall = "" if math.isnan(scored.recall_at_1) else f"  recall@1 {scored.recall_at_1:.3f}"
    best = "  (best)" if state.bad_epochs == 0 else ""
    log.line(
        f"{name} epoch {state.epoch}/{trainer.settings.epochs}: train loss {train_loss}  "
        f"validation loss {scored.val_loss:.5f}{recall}{best}"
    )


def score_start(
    trainer: Trainer,
    state: TrainState,
    val_images: np.ndarray,
    validate: Validate | None,
    mesh: Mesh | None,
    log: TrainingLog,
    name: str,
) -> TrainState:
    """Score the starting weights as epoch 0: the best so far until an epoch beats them."""
    scored = score_epoch(trainer, state.params, val_images, validate, mesh)
    state, _, _ = end_epoch(state, scored, trainer.settings)
    log_epoch(trainer, state, np.zeros(0), scored, val_images, log, name)
    return state


def _on_devices(train_images: np.ndarray, state: TrainState, mesh: Mesh | None):
    """The training set and the state where the steps run: with a mesh every device holds
    the training set (each step splits its batch) and a replica of the model."""
    if mesh is None:
        return jnp.asarray(train_images), state
    params, opt_state, best = sharding.replicate(
        (state.params, state.opt_state, state.best_params), mesh
    )
    return sharding.replicate(train_images, mesh), state._replace(
        params=params, opt_state=opt_state, best_params=best
    )


def save_epoch(
    checkpoint_dir: Path, state: TrainState, meta: dict, *, done: bool, stopped_early: bool
) -> None:
    """Commit the epoch's state, with the model's metadata and a readable summary."""
    summary = {
        "epoch": state.epoch,
        "step": state.step,
        "best_epoch": state.best_epoch,
        "best_score": state.best_score,
        "best_val_loss": state.best_val,
        "bad_epochs": state.bad_epochs,
        "done": done,
        "stopped_early": stopped_early,
        "train_seconds": state.seconds,
    }
    checkpoints.save(checkpoint_dir, state.epoch, state, {**meta, **summary})


def fit_autoencoder(spec: ae.Spec, data: TrainingData, options: TrainOptions) -> TrainResult:
    """Train (or resume, or restore) one auto-encoder; returns its best parameters.

    ``options.validate(encode)`` scores a model by what it is for (the validation places'
    recall@1 of its codes); the best epoch (0: the starting weights) is kept and early
    stopping counts epochs without a better one; without it the validation loss selects.
    With a ``checkpoint_dir`` an epoch is committed once ``checkpoint_every_s`` passed, the
    last always: a finished model is restored, an unfinished one resumes; ``identity`` must
    match the checkpoint's. With a ``mesh`` each batch is split across its devices."""
    began = time.perf_counter()
    o, settings = options, options.settings
    if o.checkpoint_dir is not None and jax.process_index() == 0:
        # Logdirs of one name under different parents share a folder: one writer.
        lock_folder(
            o.checkpoint_dir,
            "checkpoint folder",
            "wait for it to finish, or give this logdir another name (or set train.checkpoint_dir)",
        )
    train_images, val_images = (np.asarray(x, np.float32) for x in data)
    shape = _image_shape(train_images, o.objective)
    trainer, fresh = make_trainer(
        spec, shape, len(train_images), o.key, settings, o.mesh, o.objective, o.fixed, o.start
    )
    selected_by = SELECT_LOSS if o.validate is None else SELECT_RECALL
    meta = checkpoint_meta(spec, shape, o.identity, o.objective, selected_by)
    state, saved = init_or_restore(fresh, o.checkpoint_dir, meta, o.log, o.name)
    if saved is not None and saved["done"]:
        return _result(
            trainer, state, selected_by, saved["stopped_early"], restored=True, start=fresh.params
        )
    resumed_epoch, spent = state.epoch, state.seconds
    check_batch_splits(trainer.batch_size, sharding.mesh_size(o.mesh))
    train_dev, state = _on_devices(train_images, state, o.mesh)
    o.log.begin(state.step)
    if state.epoch == 0:  # the starting weights compete too
        state = score_start(trainer, state, val_images, o.validate, o.mesh, o.log, o.name)
    stopped_early, last_save = False, time.perf_counter()
    while state.epoch < settings.epochs:
        state, losses = train_epoch(trainer, state, train_dev, o.key, o.log, o.name)
        scored = score_epoch(trainer, state.params, val_images, o.validate, o.mesh)
        state, stopped_early, done = end_epoch(state, scored, settings)
        log_epoch(trainer, state, losses, scored, val_images, o.log, o.name)
        state = state._replace(seconds=spent + time.perf_counter() - began)
        if o.checkpoint_dir is not None and (done or _due(last_save, settings)):
            save_epoch(o.checkpoint_dir, state, meta, done=done, stopped_early=stopped_early)
            last_save = time.perf_counter()
        if done:
            break
    return _result(
        trainer,
        state,
        selected_by,
        stopped_early,
        resumed_epoch=resumed_epoch,
        start=fresh.params,
    )


def _image_shape(examples: np.ndarray, objective: str) -> tuple[int, int]:
    """(height, width) of an objective's examples: images, or pairs of them."""
    return examples.shape[2:4] if objective in objectives.PAIRED else examples.shape[1:3]


def _due(last_save: float, settings: TrainConfig) -> bool:
    return time.perf_counter() - last_save >= settings.checkpoint_every_s


def _result(
    trainer: Trainer,
    state: TrainState,
    selected_by: str,
    stopped_early: bool,
    *,
    restored: bool = False,
    resumed_epoch: int | None = None,
    start: dict | None = None,
) -> TrainResult:
    """What training gives back: the best parameters and the counters of ``state``; a
    restored model resumed after its last epoch; ``start``: the starting weights."""
    return TrainResult(
        graphdef=trainer.graphdef,
        params=state.best_params,
        epochs=state.epoch,
        steps=state.step,
        best_val_loss=state.best_val,
        best_score=state.best_score,
        best_epoch=state.best_epoch,
        selected_by=selected_by,
        stopped_early=stopped_early,
        restored=restored,
        resumed_epoch=state.epoch if resumed_epoch is None else resumed_epoch,
        train_seconds=state.seconds,
        start_params=start,
    )
