"""The programs training runs, compiled once per architecture: the optimizer, the jitted
train step, an epoch's batch, the validation loss; which of them keep the platform's precision.

``train_step(params, opt_state, batch, key) -> (params, opt_state, metrics)`` augments the
batch (Table 2 of the paper: horizontal flip, width and height shift 0.2) and takes one
optimizer step on the objective's loss (``vpr_jax.encoders.objectives``). The loop that runs
them over epochs is ``vpr_jax.encoders.train``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P
from jaxtyping import Array, Float

from vpr_jax import config
from vpr_jax.config import TrainConfig
from vpr_jax.data.augment import PLACE, TABLE2, AugmentConfig
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import objectives
from vpr_jax.errors import UserError
from vpr_jax.precision import float32_products
from vpr_jax.sharding import AXIS

OPTIMIZERS = {name: getattr(optax, name) for name in config.OPTIMIZERS}


def make_optimizer(
    settings: TrainConfig, frozen: tuple[str, ...] = ()
) -> optax.GradientTransformation:
    """``settings``' optimizer; the params entries named in ``frozen`` get no steps."""
    return _optimizer(settings.optimizer, settings.learning_rate, frozen)


@functools.lru_cache(maxsize=32)  # the same object for the same settings: see make_train_step
def _optimizer(
    name: str, learning_rate: float, frozen: tuple[str, ...] = ()
) -> optax.GradientTransformation:
    if name not in OPTIMIZERS:
        raise ValueError(f"unknown optimizer {name!r}: use {', '.join(OPTIMIZERS)}")
    tx = OPTIMIZERS[name](learning_rate)
    if not frozen:
        return tx

    def labels(params):
        return {k: "frozen" if k in frozen else "trained" for k in params}

    return optax.multi_transform({"trained": tx, "frozen": optax.set_to_zero()}, labels)


# The programs whose products keep the platform's default precision (TF32 on recent NVIDIA
# GPUs), by name: the training step, whose rounding is noise next to SGD's, and the
# reconstructions training shows. Neither chooses anything: an epoch is kept by recall on
# codes made at float32 (``ae.make_encode``), or by the validation loss (``make_eval_loss``),
# also at float32. tests/test_precision.py holds every other program to float32.
PLATFORM_PRECISION = ("train_step", "reconstruct")


@functools.lru_cache(maxsize=32)  # per architecture: season pairs share compilations
def make_train_step(
    graphdef,
    tx: optax.GradientTransformation,
    augment: AugmentConfig | None,
    mesh: Mesh | None = None,
    objective: str = "reconstruct",
    temperature: float = 0.1,
    radius: int = 0,
    start_decay: float = 0.0,
):
    """The jitted step ``(params, opt_state, batch, key, places=None, anchor=None) ->
    (params, opt_state, metrics)`` for one architecture, optimizer and objective
    (``vpr_jax.encoders.objectives``: a batch of images, or of aligned pairs; ``places``: the
    batch's positions along the route, which the contrastive objective's ``radius`` reads);
    metrics: ``loss`` (the objective's) and the ``inputs`` it trained on (the batch after
    augmentation). Fixed arrays of the model (``ae.FIXED``: a removal's mean and
    components) are carried through, never trained. With ``start_decay`` > 0 the gradient
    also pulls the trainable weights towards ``anchor`` (their starting values):
    ``start_decay / 2 x ||params - anchor||^2`` (``start_penalty``).

    With a ``mesh`` the batch is split across its devices (data parallel): parameters and
    optimizer state are replicated and XLA all-reduces the gradients. Augmentation draws
    the same numbers either way (JAX's threefry keys are partitionable).
    """
    batch_sharding = None if mesh is None else NamedSharding(mesh, P(AXIS))

    def loss_fn(trainable, fixed, batch, places, anchor, key):
        params = {**trainable, **fixed}
        loss = objectives.loss(objective, graphdef, params, batch, temperature, places, radius, key)
        if not start_decay:
            return loss, loss
        return loss + start_decay * start_penalty(trainable, anchor), loss

    @jax.jit
    def train_step(
        params, opt_state, batch: Float[Array, "b ..."], key: jax.Array, places=None, anchor=None
    ):
        if batch_sharding is not None:
            batch = jax.lax.with_sharding_constraint(batch, batch_sharding)
        if augment is not None:
            batch = objectives.augment(key, batch, augment, objective)
        trainable, fixed = ae.split_fixed(params)
        grad_fn = jax.value_and_grad(loss_fn, has_aux=True)
        views_key = jax.random.fold_in(key, 7)  # the changes of conditions (augment_contrastive)
        (_, loss), grads = grad_fn(trainable, fixed, batch, places, anchor, views_key)
        updates, opt_state = tx.update(grads, opt_state, trainable)
        params = {**optax.apply_updates(trainable, updates), **fixed}
        # The augmented batch stays on the device unless the caller fetches it (TensorBoard
        # shows the first one); it is the same graph's output, so nothing compiles twice.
        return params, opt_state, {"loss": loss, "inputs": batch}

    return train_step


def augment_config(augment) -> AugmentConfig | None:
    """``train.augment``'s augmentation: the paper's (true), the place-keeping one (place:
    ``PLACE``) or none (false)."""
    if augment == "place":
        return PLACE
    return TABLE2 if augment is True else None


def start_penalty(trainable: dict, anchor: dict) -> Float[Array, ""]:
    """Half the squared distance of the trainable weights from ``anchor`` (their start)."""
    squares = jax.tree.map(lambda p, a: jnp.sum((p - a) ** 2), trainable, anchor)
    return 0.5 * sum(jax.tree.leaves(squares))


@functools.partial(jax.jit, static_argnums=3)
def take_batch(data: Array, order: Array, index: Array, batch_size: int) -> tuple[Array, Array]:
    """Batch ``index`` of an epoch: ``data[order[index * b : (index + 1) * b]]`` and those
    rows' positions (a training place's along the route), compiled once (a Python slice
    with a new start would compile a new program per step)."""
    picks = jax.lax.dynamic_slice_in_dim(order, index * batch_size, batch_size)
    return data[picks], picks


@functools.lru_cache(maxsize=32)  # per architecture: season pairs share compilations
def make_eval_loss(
    graphdef,
    batch_size: int,
    objective: str = "reconstruct",
    temperature: float = 0.1,
    radius: int = 0,
) -> Callable:
    """The objective's mean loss over any number of examples (in route order), in
    fixed-size batches (a contrastive batch's places are each other's wrong places, but
    for those within ``radius``)."""

    @jax.jit
    def per_example(params, batch, places):
        model = nnx.merge(graphdef, params)
        with float32_products():  # it selects epochs where nothing validates by recall
            return objectives.per_example_loss(objective, model, batch, temperature, places, radius)

    def eval_loss(params, examples: np.ndarray) -> float:
        losses = []
        for start in range(0, len(examples), batch_size):
            chunk = examples[start : start + batch_size]
            pad = batch_size - len(chunk)  # pad the tail: one compiled shape
            padded = np.concatenate([chunk, np.repeat(chunk[-1:], pad, axis=0)]) if pad else chunk
            places = np.minimum(np.arange(start, start + batch_size), len(examples) - 1)
            losses.append(np.asarray(per_example(params, padded, places))[: len(chunk)])
        return float(np.mean(np.concatenate(losses)))

    return eval_loss


def check_batch_splits(batch_size: int, devices: int, images_per_example: int = 1) -> None:
    """Data-parallel training splits every batch's examples evenly over the ``devices``
    (a cross_season example is a place's two images)."""
    step = devices * images_per_example
    if batch_size % step:
        raise UserError(
            f"train.batch_size={batch_size} does not split over {devices} devices: use a "
            f"multiple of {step}, or set mesh.devices"
        )
