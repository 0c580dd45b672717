"""Training an auto-encoder: raw optax, a jitted train step, early stopping, resumable.

``train_step(params, opt_state, batch, key) -> (params, opt_state, metrics)`` augments the
batch (Table 2 of the seed: horizontal flip, width and height shift 0.2), reconstructs it
and takes one optimizer step on the mean squared error.

``fit_autoencoder`` runs epochs over a shuffled training set, scores a held-out validation
set after each, keeps the best parameters, and stops after ``patience`` epochs without
improvement. Every random draw comes from ``(key, epoch, step)``, so a run resumed from an
epoch's checkpoint continues exactly as the uninterrupted run would have.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple, Protocol

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P
from jaxtyping import Array, Float

from vpr_jax import checkpoints, sharding
from vpr_jax.config import TrainConfig
from vpr_jax.data.augment import AugmentConfig, augment_batch
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.errors import UserError
from vpr_jax.progress import Bar
from vpr_jax.sharding import AXIS

OPTIMIZERS = {"adam": optax.adam, "adamw": optax.adamw, "sgd": optax.sgd}  # config's names


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
):
    """The jitted step ``(params, opt_state, batch, key) -> (params, opt_state, metrics)``
    for one architecture and optimizer; metrics: ``loss`` and the ``inputs`` it trained on
    (the batch after augmentation).

    With a ``mesh`` the batch is split across its devices (data parallel): parameters and
    optimizer state are replicated and XLA all-reduces the gradients. Augmentation draws
    the same numbers either way (JAX's threefry keys are partitionable).
    """
    batch_sharding = None if mesh is None else NamedSharding(mesh, P(AXIS))

    def loss_fn(params, batch):
        return ae.reconstruction_loss(graphdef, params, batch)

    @jax.jit
    def train_step(params, opt_state, batch: Float[Array, "b h w ..."], key: jax.Array):
        if batch_sharding is not None:
            batch = jax.lax.with_sharding_constraint(batch, batch_sharding)
        if augment is not None:
            batch = augment_batch(key, batch, augment)
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
def make_eval_loss(graphdef, batch_size: int) -> Callable:
    """Mean reconstruction loss over any number of images, in fixed-size batches."""

    @jax.jit
    def per_image(params, batch):
        recon = nnx.merge(graphdef, params)(batch)
        return jnp.mean((recon - batch) ** 2, axis=tuple(range(1, batch.ndim)))

    def eval_loss(params, images: np.ndarray) -> float:
        losses = []
        for start in range(0, len(images), batch_size):
            chunk = images[start : start + batch_size]
            pad = batch_size - len(chunk)  # pad the tail: one compiled shape
            padded = np.concatenate([chunk, np.repeat(chunk[-1:], pad, axis=0)]) if pad else chunk
            losses.append(np.asarray(per_image(params, padded))[: len(chunk)])
        return float(np.mean(np.concatenate(losses)))

    return eval_loss


def check_batch_splits(batch_size: int, mesh: Mesh | None) -> None:
    """Data-parallel training splits every batch evenly over the mesh's devices."""
    n_devices = sharding.mesh_size(mesh)
    if batch_size % n_devices:
        raise UserError(f"train.batch_size={batch_size} does not split over {n_devices} "
                        f"devices: use a multiple of {n_devices}, or set mesh.devices")


def split_validation(
    images: np.ndarray, n_groups: int, fraction: float
) -> tuple[np.ndarray, np.ndarray]:
    """Hold out the last ``fraction`` of each of ``n_groups`` equal consecutive groups.

    The sweep's training images are two seasons' training stretches back to back; the tail of
    each stretch is validation, so no validation place sits between training places.
    """
    groups = np.split(np.asarray(images), n_groups)
    n_val = max(1, int(round(len(groups[0]) * fraction)))
    if len(groups[0]) - n_val < 1:
        raise UserError(f"train.val_fraction={fraction} leaves no training image: lower it")
    train = np.concatenate([g[:-n_val] for g in groups])
    val = np.concatenate([g[-n_val:] for g in groups])
    return train, val


def _json(value):
    """A value as it comes back from JSON (tuples become lists)."""
    if isinstance(value, dict):
        return {k: _json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json(v) for v in value]
    return value


def _examples(images: np.ndarray, n: int) -> np.ndarray:
    picks = np.linspace(0, len(images) - 1, min(n, len(images))).round().astype(int)
    return images[picks]


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
) -> TrainResult:
    """Train (or resume, or restore) one auto-encoder; returns its best parameters.

    With ``checkpoint_dir``, an epoch is committed there once ``checkpoint_every_s`` seconds
    passed since the last save, and the last epoch always is: a finished model is restored,
    an unfinished one resumes after its last saved epoch. ``identity`` (JSON data) must
    match the checkpoint's, so a model of other data or settings is never reused. With a
    ``mesh`` each batch is split across its devices (see ``make_train_step``).
    """
    start = time.perf_counter()
    settings = settings or TrainConfig()
    train_images = np.asarray(train_images, np.float32)
    val_images = np.asarray(val_images, np.float32)
    graphdef, params = ae.build(spec, jax.random.fold_in(key, 0), train_images.shape[1:3])
    tx = make_optimizer(settings)
    opt_state = tx.init(params)
    best_params, best_val, bad_epochs, epoch, step, spent = params, math.inf, 0, 0, 0, 0.0
    meta_base = {
        "spec": {"kind": type(spec).__name__, **spec._asdict()},
        "image_shape": list(train_images.shape[1:3]),
        "identity": identity or {},
    }

    if checkpoint_dir is not None and checkpoints.has_checkpoint(checkpoint_dir):
        meta = checkpoints.read_meta(checkpoint_dir)
        if any(meta.get(k) != _json(v) for k, v in meta_base.items()):
            raise UserError(
                f"{checkpoint_dir} holds a model trained on other data or settings: delete "
                "that folder, or set train.checkpoint_dir=PATH to keep both"
            )
        restored = checkpoints.restore(
            checkpoint_dir, params, {"params": params, "opt_state": opt_state}
        )
        meta = restored.meta
        best_params, best_val = restored.model, meta["best_val_loss"]
        epoch, step, bad_epochs = meta["epoch"], meta["step"], meta["bad_epochs"]
        spent = meta["train_seconds"]
        if meta["done"]:
            if log is not None:
                log.line(f"{name}: restored the trained model from {checkpoint_dir}")
            return TrainResult(graphdef, best_params, epoch, step, best_val,
                               meta["stopped_early"], True, epoch, spent)  # fmt: skip
        params, opt_state = restored.train["params"], restored.train["opt_state"]
        if log is not None:
            log.line(f"{name}: resuming after epoch {epoch} (step {step})")
    resumed_epoch = epoch

    n = len(train_images)
    batch_size = min(settings.batch_size, n)
    steps_per_epoch = n // batch_size  # the tail is dropped: one compiled batch shape
    check_batch_splits(batch_size, mesh)
    augment = AugmentConfig() if settings.augment else None
    train_step = make_train_step(graphdef, tx, augment, mesh)
    eval_loss = make_eval_loss(graphdef, batch_size)
    reconstruct = ae.make_reconstruct(graphdef)
    if mesh is None:
        train_dev = jnp.asarray(train_images)
    else:  # every device holds the training set; each step splits its batch
        train_dev = sharding.replicate(train_images, mesh)
        params, opt_state, best_params = sharding.replicate((params, opt_state, best_params), mesh)
    if log is not None:
        log.begin(step)

    stopped_early, last_save = False, time.perf_counter()
    for epoch in range(resumed_epoch + 1, settings.epochs + 1):
        epoch_key = jax.random.fold_in(key, epoch)
        order = jax.random.permutation(jax.random.fold_in(epoch_key, 0), n)
        losses = []  # on the device until the epoch ends: no wait between steps
        with Bar(steps_per_epoch, f"{name} epoch {epoch}/{settings.epochs}") as bar:
            for s in range(steps_per_epoch):
                batch = take_batch(train_dev, order, s, batch_size)
                params, opt_state, metrics = train_step(
                    params, opt_state, batch, jax.random.fold_in(epoch_key, s + 1)
                )
                losses.append(metrics["loss"])
                if log is not None and epoch == 1 and s == 0 and settings.augment:
                    shown = sharding.to_host(metrics["inputs"])
                    log.images("inputs/augmented", _examples(shown, 8), step + 1)
                bar.advance()
        losses = np.asarray(jnp.stack(losses)) if losses else np.zeros(0)
        if log is not None:
            for i, loss in enumerate(losses):
                log.scalar("loss/train", float(loss), step + 1 + i)
        step += len(losses)
        val = eval_loss(params, val_images)
        if val < best_val:
            best_params, best_val, bad_epochs = params, val, 0
        else:
            bad_epochs += 1
        stopped_early = bad_epochs >= settings.patience and epoch < settings.epochs
        done = stopped_early or epoch == settings.epochs
        train_loss = float(np.mean(losses)) if len(losses) else math.nan
        if log is not None:
            log.scalar("loss/validation", val, step)
            shown = _examples(val_images, 6)
            recon = np.asarray(reconstruct(params, shown))
            log.images("reconstructions/validation", np.concatenate([shown, recon]), step)
            best = "  (best)" if bad_epochs == 0 else ""
            log.line(f"{name} epoch {epoch}/{settings.epochs}: train loss {train_loss:.5f}  "
                     f"validation loss {val:.5f}{best}")  # fmt: skip
        seconds = spent + time.perf_counter() - start
        due = time.perf_counter() - last_save >= settings.checkpoint_every_s
        if checkpoint_dir is not None and (due or done):
            meta = {**meta_base, "epoch": epoch, "step": step, "best_val_loss": best_val,
                    "bad_epochs": bad_epochs, "done": done, "stopped_early": stopped_early,
                    "train_seconds": seconds}  # fmt: skip
            checkpoints.save(checkpoint_dir, epoch, {"params": params, "opt_state": opt_state},
                             best_params, meta)  # fmt: skip
            last_save = time.perf_counter()
        if done:
            break
    return TrainResult(graphdef, best_params, epoch, step, best_val, stopped_early, False,
                       resumed_epoch, seconds)  # fmt: skip


def load_encoder(checkpoint_dir: str | Path):
    """``(encode_fn, params)`` of a trained auto-encoder checkpoint folder.

    ``encode_fn(params, images) -> (n, code)`` is jitted and pure: use it inside your own
    jitted functions, vmap it, differentiate through it.
    """
    checkpoint_dir = Path(checkpoint_dir)
    meta = checkpoints.read_meta(checkpoint_dir)
    fields = dict(meta["spec"])
    kind = fields.pop("kind")
    if kind == "FAESpec":
        fields.setdefault("centre", 0.0)  # written before the FAE centred its input
        spec = ae.FAESpec(**fields)
    elif kind == "CAESpec":
        spec = ae.CAESpec(**{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()})
    else:
        raise UserError(f"{checkpoint_dir} holds an unknown model kind {kind!r}")
    graphdef, like = ae.build(spec, jax.random.key(0), tuple(meta["image_shape"]))
    params = checkpoints.restore(checkpoint_dir, like).model
    return ae.make_encode(graphdef), params
