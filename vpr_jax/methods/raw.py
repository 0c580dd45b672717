"""raw: the pixels (or another ``input``), centred with the training mean; cosine does the L2
normalisation. The reference every other method improves on; ``raw.input=gradients`` is the
training-free gradient-histogram baseline."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from vpr_jax.encoders import pca
from vpr_jax.methods.contract import Method
from vpr_jax.methods.inputs import check_input, with_input


@dataclasses.dataclass(frozen=True)
class Settings:
    """``raw.*``."""

    # what the method sees (vpr_jax.methods.inputs): pixels, standardised, patchnorm,
    # gradients, or parts joined by + (a list: an axis)
    input: str = "pixels"

    def __post_init__(self):
        check_input(self, "raw")


def fit(train: Float[Array, "n h w"], aligned, key) -> dict:
    return {"mean": jnp.mean(pca.device_rows(train), axis=0)}


@jax.jit
def encode(state: dict, images: Float[Array, "n h w"]) -> Float[Array, "n d"]:
    return pca.flatten(images) - state["mean"]


method = with_input(Method(fit=fit, encode=encode, settings=Settings, random=False))
