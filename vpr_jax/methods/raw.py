"""raw: the pixels, centred with the training mean; cosine does the L2 normalisation. The
reference every other method improves on."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from vpr_jax.encoders import pca
from vpr_jax.methods.contract import Method


def fit(train: Float[Array, "n h w"], aligned, key) -> dict:
    return {"mean": jnp.mean(pca.device_rows(train), axis=0)}


@jax.jit
def encode(state: dict, images: Float[Array, "n h w"]) -> Float[Array, "n d"]:
    return pca.flatten(images) - state["mean"]


method = Method(fit=fit, encode=encode, random=False)
