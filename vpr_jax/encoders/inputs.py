"""What a method sees (its ``input`` setting): a pure jittable function of the images, fitted
on the training images and saved with the method's state.

Parts (``PARTS``):

- ``pixels``: the image as it is;
- ``standardised``: each image to zero mean and standard deviation 1/4
  (``autoencoders.standardise``: a season's global brightness and contrast gone);
- ``patchnorm``: SeqSLAM's patch normalisation (``vpr_jax.data.preprocess``), in JAX;
- ``gradients``: histograms of gradient orientations (``vpr_jax.encoders.gradients``).

A combination joins parts with ``+`` (``standardised+gradients``): their values side by side,
each part scaled so that its total variance over the training images (the sum of its
features' variances) is 1, so no part wins by its units; the scales are the fitted state.
A single part is left as it is, unscaled: ``pixels`` gives back the images themselves.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from vpr_jax.data.preprocess import patch_normalize_jax
from vpr_jax.encoders import gradients
from vpr_jax.encoders.input_parts import PARTS, parts_of


class Options(NamedTuple):
    """How the parts that have settings compute (``gradients.*``, ``patchnorm.*``)."""

    cell: int = 4  # gradients: pixels per cell side
    bins: int = 9  # gradients: orientation bins over 0-180 degrees
    block: int = 3  # gradients: cells per block side
    norm: str = "L2"  # gradients: block normalisation
    patch: int = 8  # patchnorm: patch side
    rounded: bool = False  # patchnorm: openSeqSLAM's integer z-scores


DEFAULTS = Options()
MAX_SIDE, MAX_BINS = 64, 360  # a cell, block or patch side in pixels or cells; bins


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class InputState:
    """A fitted input: its parts and options (static) and each part's scale."""

    scales: Float[Array, " p"]  # one per part: 1 / sqrt(its total training variance)
    parts: tuple[str, ...] = dataclasses.field(metadata={"static": True})
    options: Options = dataclasses.field(metadata={"static": True})

    def __post_init__(self):
        """A saved folder's claims checked before anything computes with them (a file is
        data): known parts, and options in the ranges a 32x64 image allows, so no file
        makes the histograms loop or allocate without bound. ValueError otherwise."""
        parts_of("+".join(self.parts))
        o = self.options
        if not (
            1 <= o.cell <= MAX_SIDE
            and 2 <= o.bins <= MAX_BINS
            and 1 <= o.block <= MAX_SIDE
            and o.norm in gradients.NORMS
            and 1 <= o.patch <= MAX_SIDE
        ):
            raise ValueError(f"input options {tuple(o)} are outside what an image allows")


@functools.partial(jax.jit, static_argnums=(0, 2))
def part(name: str, images: Float[Array, "n h w"], options: Options) -> Float[Array, "n ..."]:
    """One part of the input of ``images``: (n, h, w) for an image part, (n, f) else."""
    if name == "pixels":
        return images
    if name == "standardised":
        # the auto-encoders' own; imported here: flax is no cost of a sweep without them
        from vpr_jax.encoders.autoencoders import standardise

        return standardise(images)
    if name == "patchnorm":
        return patch_normalize_jax(images, options.patch, options.rounded)
    if name == "gradients":
        return gradients.gradient_histograms(
            images, options.cell, options.bins, options.block, options.norm
        )
    raise ValueError(f"input part {name!r} is not one of {PARTS}")


def fit(name: str, train: Float[Array, "n h w"], options: Options = DEFAULTS) -> InputState:
    """The input ``name`` fitted on ``train``: each part's scale (1 for a single part)."""
    parts = parts_of(name)
    if len(parts) == 1:
        return InputState(jnp.ones(1, jnp.float32), parts, options)
    scales = [1.0 / jnp.sqrt(total_variance(_flat(part(p, train, options))) + 1e-12) for p in parts]
    return InputState(jnp.stack(scales).astype(jnp.float32), parts, options)


@jax.jit
def total_variance(x: Float[Array, "n f"]) -> Float[Array, ""]:
    """The sum of the features' variances over the rows (each centred with its mean)."""
    centred = x - jnp.mean(x, axis=0)
    return jnp.sum(centred * centred) / x.shape[0]


@jax.jit
def apply(state: InputState, images: Float[Array, "n h w"]) -> Float[Array, "n ..."]:
    """The input of ``images``: a single part's own shape; a combination (n, f), its parts'
    scaled values side by side."""
    images = jnp.asarray(images, jnp.float32)
    if len(state.parts) == 1:
        return part(state.parts[0], images, state.options)
    return jnp.concatenate(
        [
            _flat(part(p, images, state.options)) * state.scales[i]
            for i, p in enumerate(state.parts)
        ],
        axis=1,
    )


def _flat(x):
    return jnp.reshape(x, (x.shape[0], -1))


def n_values(name: str, image_shape: tuple[int, int], options: Options = DEFAULTS) -> int:
    """How many values the input ``name`` gives an image of ``image_shape``."""
    h, w = image_shape
    sizes = {
        "gradients": gradients.n_features(h, w, options.cell, options.bins, options.block),
    }
    return sum(sizes.get(p, h * w) for p in parts_of(name))
