"""What an auto-encoder learns to do: the training objectives, as per-example losses.

- ``reconstruct`` (the paper's): an image -> itself. Training data: images ``(n, h, w)``.
- ``cross_season``: either season's image of a place -> the place's season mean
  ``(a_i + b_i) / 2``. Training data: the aligned pairs of the training places, ``(n, 2, h,
  w)`` (row i holds place i in both seasons). The output may not depend on the season, so a
  code that carries the season buys the decoder nothing, and the code of a place becomes
  the same for its two seasons wherever the decoder needs it. Asking each season's image
  for the other's (a swap) would do the opposite: the code would have to carry the season
  to know which image to produce.
- ``contrastive``: no decoder; the codes of a batch's places are compared by cosine, and
  each place's code in one season is pulled towards its code in the other and pushed from
  the batch's other places (InfoNCE, symmetric over the two seasons, at ``temperature``).
  It learns what recognition needs directly: the one signal the aligned places give.
  Training data: aligned pairs, as for cross_season.
- ``augment_contrastive``: InfoNCE as ``contrastive``, for data without aligned places: the
  positive pair of an image is two changes of conditions of it (``vpr_jax.data.augment.
  condition_views``: brightness, contrast, gamma, blur, a shadow band, noise, small shifts),
  drawn anew at every step; the batch's other images are its wrong places. Training data:
  the images, as for reconstruct.

The first two are mean squared errors per example (an image, or a place: the mean of its
two seasons' errors; a model that removes components reproduces its residual image,
``FAE.residual``); the contrastive loss is per place, against the other places of its
batch. Training means them over a batch and validation over the held-out tail the same
way. Augmentation draws one transform per example: a place's two images and
its target move together.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jaxtyping import Array, Float, Int, PRNGKeyArray

from vpr_jax.data.augment import AugmentConfig, augment_batch, condition_views
from vpr_jax.encoders import autoencoders as ae

OBJECTIVES = ("reconstruct", "cross_season", "contrastive", "augment_contrastive")
PAIRED = ("cross_season", "contrastive")  # objectives that train on aligned places' pairs
VIEWS = ("augment_contrastive",)  # objectives that make their pairs from one image
CODE_ONLY = ("contrastive", "augment_contrastive")  # no decoder output to train or show
# The fixed key of the changes of conditions a validation loss is measured on.
VALIDATION_VIEWS_SEED = 0


def _check(objective: str) -> None:
    if objective not in OBJECTIVES:
        raise ValueError(f"unknown objective {objective!r}: use one of {', '.join(OBJECTIVES)}")


def training_data(objective: str, images: np.ndarray, n_seasons: int = 2) -> np.ndarray:
    """What an objective trains on, from the sweep's training images (``n_seasons`` aligned
    stretches back to back): the images themselves, or the places' pairs ``(n, 2, h, w)``."""
    _check(objective)
    if objective not in PAIRED:
        return np.asarray(images, np.float32)
    if n_seasons != 2 or len(images) % 2:
        raise ValueError(f"{objective} needs the aligned training places of two seasons")
    first, second = np.split(np.asarray(images, np.float32), 2)
    return np.stack([first, second], axis=1)


def examples_per_image(objective: str) -> int:
    """Images one training example holds: a batch of b images takes b / this examples."""
    _check(objective)
    return 2 if objective in (*PAIRED, *VIEWS) else 1


def augment(key: PRNGKeyArray, batch: Array, cfg: AugmentConfig, objective: str) -> Array:
    """One random transform per example; a pair's two images share theirs."""
    if objective not in PAIRED:
        return augment_batch(key, batch, cfg)
    pairs_last = jnp.moveaxis(batch, 1, -1)  # (b, h, w, 2): the pair as channels
    return jnp.moveaxis(augment_batch(key, pairs_last, cfg), -1, 1)


def inputs_and_targets(objective: str, batch: Array) -> tuple[Array, Array]:
    """(images the model sees, what it should output for each), both ``(m, h, w ...)``."""
    if objective not in PAIRED:
        return batch, batch
    a, b = batch[:, 0], batch[:, 1]
    mean = (a + b) / 2
    return jnp.concatenate([a, b]), jnp.concatenate([mean, mean])


def contrastive_loss(
    codes_a: Float[Array, "b d"],
    codes_b: Float[Array, "b d"],
    temperature: float,
    places: Int[Array, " b"] | None = None,
    radius: int = 0,
) -> Float[Array, " b"]:
    """Symmetric InfoNCE per place: row i of ``codes_a`` and of ``codes_b`` are one place in
    two seasons; every other row of the batch is a wrong place. Cosine similarities over
    ``temperature``, cross-entropy of the right place in both directions, averaged.

    On a route, neighbouring places look alike and count as correct matches: with
    ``places`` (each row's position along the route) and ``radius`` > 0, rows within
    ``radius`` positions of row i (other than i) are left out of its wrong places."""
    a = codes_a / (jnp.linalg.norm(codes_a, axis=1, keepdims=True) + 1e-8)
    b = codes_b / (jnp.linalg.norm(codes_b, axis=1, keepdims=True) + 1e-8)
    logits = a @ b.T / temperature
    right = jnp.diagonal(logits)
    if places is not None and radius > 0:
        near = jnp.abs(places[:, None] - places[None, :]) <= radius
        logits = jnp.where(near & ~jnp.eye(len(places), dtype=bool), -jnp.inf, logits)
    a_to_b = jax.nn.logsumexp(logits, axis=1) - right
    b_to_a = jax.nn.logsumexp(logits, axis=0) - right
    return (a_to_b + b_to_a) / 2


def per_example_loss(
    objective: str,
    model: nnx.Module,
    batch: Array,
    temperature: float = 0.1,
    places: Int[Array, " n"] | None = None,
    radius: int = 0,
    key: PRNGKeyArray | None = None,
) -> Float[Array, " n"]:
    """The loss of ``model`` (an auto-encoder module) per example of ``batch``: mean squared
    error of its output (reconstruct, cross_season) or InfoNCE of its code (contrastive,
    its wrong places leaving out those within ``radius`` of ``places``; augment_contrastive,
    the two views ``key`` draws of each image: the validation's fixed key without one)."""
    if objective in VIEWS:
        key = jax.random.key(VALIDATION_VIEWS_SEED) if key is None else key
        views = condition_views(key, batch)
        codes = model.encode(jnp.concatenate([views[:, 0], views[:, 1]]))
        return contrastive_loss(codes[: len(batch)], codes[len(batch) :], temperature)
    if objective == "contrastive":
        codes = model.encode(jnp.concatenate([batch[:, 0], batch[:, 1]]))
        n = len(batch)
        return contrastive_loss(codes[:n], codes[n:], temperature, places, radius)
    inputs, targets = inputs_and_targets(objective, batch)
    targets = model.residual(targets)  # what a model that removes components reproduces
    errors = jnp.mean((model(inputs) - targets) ** 2, axis=tuple(range(1, inputs.ndim)))
    if objective == "reconstruct":
        return errors
    return (errors[: len(batch)] + errors[len(batch) :]) / 2  # a place: both seasons


def loss(
    objective: str,
    graphdef,
    params,
    batch: Array,
    temperature: float = 0.1,
    places: Int[Array, " n"] | None = None,
    radius: int = 0,
    key: PRNGKeyArray | None = None,
) -> Float[Array, ""]:
    """The training loss of a batch: the mean of its per-example losses (``key``: the
    changes of conditions of augment_contrastive's views)."""
    if objective == "reconstruct":  # the same mean, summed as the paper's loss always was
        return ae.reconstruction_loss(graphdef, params, batch)
    model = nnx.merge(graphdef, params)
    return jnp.mean(per_example_loss(objective, model, batch, temperature, places, radius, key))
