"""Training an auto-encoder: raw optax, a jitted train step, early stopping, resumable.

``train_step(params, opt_state, batch, key) -> (params, opt_state, metrics)`` augments the
batch (Table 2 of the seed: horizontal flip, width and height shift 0.2), reconstructs it
and takes one optimizer step on the mean squared error.

``fit_autoencoder`` is a short loop over named steps on one ``TrainState``:
``init_or_restore`` (a fresh state, or the checkpoint's), then per epoch ``train_epoch``
(a shuffled pass over the training set), ``validation_loss`` and
``end_epoch`` (keep the best parameters; stop after ``patience`` epochs without
improvement), and a checkpoint when one is due. Every random draw comes from
``(key, epoch, step)``, so a run resumed from an epoch's checkpoint continues exactly as the
uninterrupted run would have.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P
from jaxtyping import Array, Float

from vpr_jax import sharding
from vpr_jax.config import TrainConfig, plain
from vpr_jax.data.augment import AugmentConfig
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import checkpoints, objectives
from vpr_jax.errors import UserError
from vpr_jax.progress import Bar
from vpr_jax.sharding import AXIS

OPTIMIZERS = {"adam": optax.adam, "adamw": optax.adamw, "sgd": optax.sgd}  # config's names


class TrainState(NamedTuple):
    """Everything training needs to go on, saved as one checkpoint item per saved epoch."""

    params: dict  # the current parameters
    opt_state: Any  # the optimizer's state (optax)
    best_params: dict  # the parameters of the best validation epoch so far
    best_val: float  # their validation loss (inf before the first epoch)
    bad_epochs: int  # epochs since the best one: early stopping's counter
    epoch: int  # epochs finished
    step: int  # optimizer steps taken
    seconds: float  # training time, summed over every session so far


class TrainResult(NamedTuple):
    graphdef: object  # the architecture: ae.make_encode(graphdef)(params, images)
    params: dict  # the best parameters (lowest validation loss)
    epochs: int  # epochs trained in total (before any interruption too)
    steps: int
    best_val_loss: float
    stopped_early: bool
    restored: bool  # a finished model was restored from its checkpoint, not trained
    resumed_epoch: int  # epoch training resumed after (0: from scratch)
    train_seconds: float  # training time, summed over every session that trained it


class TrainingLog(Protocol):
    """Where training reports: TensorBoard and the run log in the sweep; may be None."""

    def begin(self, step: int) -> None: ...
    def scalar(self, tag: str, value: float, step: int) -> None: ...
    def images(self, tag: str, images: np.ndarray, step: int) -> None: ...
    def line(self, text: str) -> None: ...
    def close(self) -> None: ...


def make_optimizer(settings: TrainConfig) -> optax.GradientTransformation:
    return _optimizer(settings.optimizer, settings.learning_rate)


@functools.lru_cache(maxsize=32)  # the same object for the same settings: see make_train_step
def _optimizer(name: str, learning_rate: float) -> optax.GradientTransformation:
    if name not in OPTIMIZERS:
        raise ValueError(f"unknown optimizer {name!r}: use {', '.join(OPTIMIZERS)}")
    return OPTIMIZERS[name](learning_rate)


@functools.lru_cache(maxsize=32)  # per architecture: season pairs share compilations
def make_train_step(
    graphdef,
    tx: optax.GradientTransformation,
    augment: AugmentConfig | None,
    mesh: Mesh | None = None,
    objective: str = "reconstruct",
):
    """The jitted step ``(params, opt_state, batch, key) -> (params, opt_state, metrics)``
    for one architecture, optimizer and objective (``vpr_jax.encoders.objectives``: a batch
    of images, or of aligned pairs); metrics: ``loss`` and the ``inputs`` it trained on (the
    batch after augmentation).

    With a ``mesh`` the batch is split across its devices (data parallel): parameters and
    optimizer state are replicated and XLA all-reduces the gradients. Augmentation draws
    the same numbers either way (JAX's threefry keys are partitionable).
    """
    batch_sharding = None if mesh is None else NamedSharding(mesh, P(AXIS))

    def loss_fn(params, batch):
        return objectives.loss(objective, graphdef, params, batch)

    @jax.jit
    def train_step(params, opt_state, batch: Float[Array, "b ..."], key: jax.Array):
        if batch_sharding is not None:
            batch = jax.lax.with_sharding_constraint(batch, batch_sharding)
        if augment is not None:
            batch = objectives.augment(key, batch, augment, objective)
        loss, grads = jax.value_and_grad(loss_fn)(params, batch)
        updates, opt_state = tx.update(grads, opt_state, params)
        # The augmented batch stays on the device unless the caller fetches it (TensorBoard
        # shows the first one); it is the same graph's output, so nothing compiles twice.
        return optax.apply_updates(params, updates), opt_state, {"loss": loss, "inputs": batch}

    return train_step


@functools.partial(jax.jit, static_argnums=3)
def take_batch(data: Array, order: Array, index: Array, batch_size: int) -> Array:
    """Batch ``index`` of an epoch: ``data[order[index * b : (index + 1) * b]]``, compiled
    once (a Python slice with a new start would compile a new program per step)."""
    picks = jax.lax.dynamic_slice_in_dim(order, index * batch_size, batch_size)
    return data[picks]


@functools.lru_cache(maxsize=32)  # per architecture: season pairs share compilations
def make_eval_loss(graphdef, batch_size: int, objective: str = "reconstruct") -> Callable:
    """The objective's mean loss over any number of examples, in fixed-size batches."""

    @jax.jit
    def per_example(params, batch):
        return objectives.per_example_loss(objective, nnx.merge(graphdef, params), batch)

    def eval_loss(params, examples: np.ndarray) -> float:
        losses = []
        for start in range(0, len(examples), batch_size):
            chunk = examples[start : start + batch_size]
            pad = batch_size - len(chunk)  # pad the tail: one compiled shape
            padded = np.concatenate([chunk, np.repeat(chunk[-1:], pad, axis=0)]) if pad else chunk
            losses.append(np.asarray(per_example(params, padded))[: len(chunk)])
        return float(np.mean(np.concatenate(losses)))

    return eval_loss


def check_batch_splits(batch_size: int, mesh: Mesh | None, images_per_example: int = 1) -> None:
    """Data-parallel training splits every batch's examples evenly over the mesh's devices
    (a cross_season example is a place's two images)."""
    step = sharding.mesh_size(mesh) * images_per_example
    if batch_size % step:
        raise UserError(
            f"train.batch_size={batch_size} does not split over "
            f"{sharding.mesh_size(mesh)} devices: use a multiple of {step}, or "
            "set mesh.devices"
        )


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
) -> tuple[Trainer, TrainState]:
    """The model's compiled steps and its initial state (weights drawn from ``key``).
    ``n_train`` counts examples; a step sees ``train.batch_size`` images, so a cross_season
    step takes half as many places."""
    graphdef, params = ae.build(spec, jax.random.fold_in(key, 0), image_shape)
    tx = make_optimizer(settings)
    per_step = max(1, settings.batch_size // objectives.examples_per_image(objective))
    batch_size = min(per_step, n_train)
    augment = AugmentConfig() if settings.augment else None
    trainer = Trainer(
        graphdef=graphdef,
        objective=objective,
        train_step=make_train_step(graphdef, tx, augment, mesh, objective),
        eval_loss=make_eval_loss(graphdef, batch_size, objective),
        reconstruct=ae.make_reconstruct(graphdef),
        settings=settings,
        batch_size=batch_size,
        steps_per_epoch=n_train // batch_size,
    )
    fresh = TrainState(
        params=params,
        opt_state=tx.init(params),
        best_params=params,
        best_val=math.inf,
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
) -> dict:
    """What a checkpoint must hold to be reused: the same model, image shape, objective and
    identity."""
    return {
        "spec": ae.spec_to_json(spec),
        "image_shape": list(image_shape),
        "objective": objective,
        "identity": plain(identity or {}),
    }


def init_or_restore(
    fresh: TrainState,
    checkpoint_dir: Path | None,
    meta: dict,
    log: TrainingLog | None,
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
    if log is not None:
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
    log: TrainingLog | None,
    name: str,
) -> tuple[TrainState, np.ndarray]:
    """One shuffled pass over the training set; returns the state and each step's loss."""
    epoch = state.epoch + 1
    epoch_key = jax.random.fold_in(key, epoch)
    order = jax.random.permutation(jax.random.fold_in(epoch_key, 0), len(train_dev))
    params, opt_state, losses = state.params, state.opt_state, []
    with Bar(trainer.steps_per_epoch, f"{name} epoch {epoch}/{trainer.settings.epochs}") as bar:
        for s in range(trainer.steps_per_epoch):
            batch = take_batch(train_dev, order, s, trainer.batch_size)
            params, opt_state, metrics = trainer.train_step(
                params, opt_state, batch, jax.random.fold_in(epoch_key, s + 1)
            )
            losses.append(metrics["loss"])  # on the device until the epoch ends: no waits
            if log is not None and epoch == 1 and s == 0 and trainer.settings.augment:
                shown, _ = objectives.inputs_and_targets(
                    trainer.objective, sharding.to_host(metrics["inputs"])
                )
                log.images("inputs/augmented", _examples(np.asarray(shown), 8), state.step + 1)
            bar.advance()
    losses = np.asarray(jnp.stack(losses)) if losses else np.zeros(0)
    if log is not None:
        for i, loss in enumerate(losses):
            log.scalar("loss/train", float(loss), state.step + 1 + i)
    state = state._replace(
        params=params, opt_state=opt_state, epoch=epoch, step=state.step + len(losses)
    )
    return state, losses


def validation_loss(trainer: Trainer, state: TrainState, val_images: np.ndarray) -> float:
    """The validation loss of the current parameters (what early stopping watches)."""
    return trainer.eval_loss(state.params, val_images)


def end_epoch(
    state: TrainState, val_loss: float, settings: TrainConfig
) -> tuple[TrainState, bool, bool]:
    """Keep the best parameters and count epochs without improvement: (state, stopped
    early, done)."""
    if val_loss < state.best_val:
        state = state._replace(best_params=state.params, best_val=val_loss, bad_epochs=0)
    else:
        state = state._replace(bad_epochs=state.bad_epochs + 1)
    stopped_early = state.bad_epochs >= settings.patience and state.epoch < settings.epochs
    return state, stopped_early, stopped_early or state.epoch == settings.epochs


def log_epoch(
    trainer: Trainer,
    state: TrainState,
    losses: np.ndarray,
    val_loss: float,
    val_examples: np.ndarray,
    log: TrainingLog,
    name: str,
) -> None:
    """The validation loss, six validation examples in rows of input | target | output
    (reconstruct: the images over their reconstructions; cross_season: both seasons, their
    mean, the output for each season), one line."""
    log.scalar("loss/validation", val_loss, state.step)
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
    train_loss = float(np.mean(losses)) if len(losses) else math.nan
    best = "  (best)" if state.bad_epochs == 0 else ""
    log.line(
        f"{name} epoch {state.epoch}/{trainer.settings.epochs}: train loss "
        f"{train_loss:.5f}  validation loss {val_loss:.5f}{best}"
    )


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
        "best_val_loss": state.best_val,
        "bad_epochs": state.bad_epochs,
        "done": done,
        "stopped_early": stopped_early,
        "train_seconds": state.seconds,
    }
    checkpoints.save(checkpoint_dir, state.epoch, state, {**meta, **summary})


def fit_autoencoder(
    spec: ae.Spec,
    train_images: np.ndarray,
    val_images: np.ndarray,
    key: jax.Array,
    settings: TrainConfig | None = None,
    *,
    checkpoint_dir: Path | None = None,
    identity: dict | None = None,
    log: TrainingLog | None = None,
    name: str = "auto-encoder",
    mesh: Mesh | None = None,
    objective: str = "reconstruct",
) -> TrainResult:
    """Train (or resume, or restore) one auto-encoder; returns its best parameters.

    ``train_images`` and ``val_images`` are the ``objective``'s examples (images, or aligned
    pairs ``(n, 2, h, w)``: ``objectives.training_data``). With ``checkpoint_dir`` an epoch
    is committed once ``checkpoint_every_s`` seconds passed since the last save, and the
    last epoch always is: a finished model is restored, an unfinished one resumes after its
    last saved epoch. ``identity`` must match the checkpoint's, so a model of other data or
    settings is never reused. With a ``mesh`` each batch is split across its devices.
    """
    start = time.perf_counter()
    settings = settings or TrainConfig()
    train_images = np.asarray(train_images, np.float32)
    val_images = np.asarray(val_images, np.float32)
    shape = train_images.shape[2:4] if objective == "cross_season" else train_images.shape[1:3]
    trainer, fresh = make_trainer(spec, shape, len(train_images), key, settings, mesh, objective)
    meta = checkpoint_meta(spec, shape, identity, objective)
    state, saved = init_or_restore(fresh, checkpoint_dir, meta, log, name)
    if saved is not None and saved["done"]:
        return _result(trainer, state, stopped_early=saved["stopped_early"], restored=True)
    resumed_epoch, spent = state.epoch, state.seconds
    check_batch_splits(trainer.batch_size, mesh)
    train_dev, state = _on_devices(train_images, state, mesh)
    if log is not None:
        log.begin(state.step)
    stopped_early, last_save = False, time.perf_counter()
    while state.epoch < settings.epochs:
        state, losses = train_epoch(trainer, state, train_dev, key, log, name)
        val_loss = validation_loss(trainer, state, val_images)
        state, stopped_early, done = end_epoch(state, val_loss, settings)
        if log is not None:
            log_epoch(trainer, state, losses, val_loss, val_images, log, name)
        state = state._replace(seconds=spent + time.perf_counter() - start)
        due = time.perf_counter() - last_save >= settings.checkpoint_every_s
        if checkpoint_dir is not None and (due or done):
            save_epoch(checkpoint_dir, state, meta, done=done, stopped_early=stopped_early)
            last_save = time.perf_counter()
        if done:
            break
    return _result(trainer, state, stopped_early=stopped_early, resumed_epoch=resumed_epoch)


def _result(
    trainer: Trainer,
    state: TrainState,
    *,
    stopped_early: bool,
    restored: bool = False,
    resumed_epoch: int | None = None,
) -> TrainResult:
    """What training gives back: the best parameters and the counters of ``state``; a
    restored model resumed after its last epoch."""
    return TrainResult(
        graphdef=trainer.graphdef,
        params=state.best_params,
        epochs=state.epoch,
        steps=state.step,
        best_val_loss=state.best_val,
        stopped_early=stopped_early,
        restored=restored,
        resumed_epoch=state.epoch if resumed_epoch is None else resumed_epoch,
        train_seconds=state.seconds,
    )
