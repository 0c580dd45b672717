"""Within-place whitening (a linear discriminant): shrink the directions in which one place's
images vary between seasons, inside the leading principal components.

The training places of a season pair are aligned: place i has an image ``a_i`` in one season
and ``b_i`` in the other. In the coordinates z of the leading ``n_components`` principal
components (the pair's PCA fit of both seasons' images), the within-place scatter is

    S_w = mean_i [(z_ai - m_i)(z_ai - m_i)^T + (z_bi - m_i)(z_bi - m_i)^T] / 2
        = mean_i (z_ai - z_bi)(z_ai - z_bi)^T / 4,        m_i = (z_ai + z_bi) / 2,

the scatter of each place about its own mean. Whitening it (z -> S^(-1/2) z) makes every
direction vary equally within a place, so directions along which seasons move a place are
scaled down and directions that tell places apart, relative to that, up: cosine matching of
the whitened coordinates is matching by a learnt Mahalanobis metric, the within-class half
of Fisher's discriminant.

Regularised: with few places the smallest eigenvalues of S_w are noise, and whitening would
blow them up, so S_w is shrunk towards a scaled identity (Ledoit & Wolf's target):
S = (1 - shrinkage) S_w + shrinkage (trace(S_w) / m) I. ``shrinkage`` = 0 is plain
whitening; 1 leaves the PCA coordinates as they are (up to a rotation and a common scale).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from vpr_jax.encoders import pca
from vpr_jax.precision import f32_matmul


class LDAState(NamedTuple):
    mean: Float[Array, " d"]  # training mean of both seasons' images
    transform: Float[Array, "m d"]  # rows: whitened directions, least within-place spread first
    within_variance: Float[Array, " m"]  # eigenvalues of the regularised within-place scatter


def within_place_scatter(za: Float[Array, "n m"], zb: Float[Array, "n m"]) -> Float[Array, "m m"]:
    """Each place's scatter about its own mean, averaged over places (two images a place)."""
    diff = za - zb
    return f32_matmul(diff.T, diff) / (4 * za.shape[0])


@functools.partial(jax.jit, static_argnames=("n_components",))
def fit_lda(
    pca_state: pca.PCAState,
    train_a: Float[Array, "n ..."],
    train_b: Float[Array, "n ..."],
    n_components: int,
    shrinkage: float | Float[Array, ""] = 0.1,
) -> LDAState:
    """Fit on aligned training images (row i of ``train_a`` and ``train_b``: one place) in
    the leading ``n_components`` components of ``pca_state``, a PCA fit of both seasons'
    training images."""
    basis = pca_state.components[:n_components]
    za = f32_matmul(pca.flatten(train_a) - pca_state.mean, basis.T)
    zb = f32_matmul(pca.flatten(train_b) - pca_state.mean, basis.T)
    scatter = within_place_scatter(za, zb)
    m = scatter.shape[0]
    target = jnp.trace(scatter) / m * jnp.eye(m, dtype=scatter.dtype)
    regularised = (1.0 - shrinkage) * scatter + shrinkage * target
    eigvals, eigvecs = jnp.linalg.eigh(regularised)  # ascending: least within-place spread
    eigvals = jnp.maximum(eigvals, jnp.finfo(eigvals.dtype).tiny)
    # Rows in pixel space: whitening of the PCA coordinates folded into one matrix, with
    # scikit-learn's sign convention (largest-magnitude entry of each eigenvector positive).
    rotation = pca.flip_signs(eigvecs.T)
    transform = f32_matmul(rotation / jnp.sqrt(eigvals)[:, None], basis)
    return LDAState(pca_state.mean, transform, eigvals)


@jax.jit
def encode(state: LDAState, images: Float[Array, "n ..."]) -> Float[Array, "n m"]:
    """Whitened coordinates of images centred with the training mean."""
    return f32_matmul(pca.flatten(images) - state.mean, state.transform.T)
