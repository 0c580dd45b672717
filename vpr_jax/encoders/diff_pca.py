"""Supervised change removal (Lowry & Milford): remove the directions in which aligned places
differ between seasons.

PCA change removal (``vpr_jax.encoders.pca``) guesses that the leading principal components
of the images carry the seasonal change. The training places of a season pair are aligned,
so the change can be measured instead: the differences ``a_i - b_i`` of place i's two images
span it. The principal directions of those differences (eigenvectors of their second moment
``E[d d^T]``, not centred, so the mean seasonal shift counts as change too) are the
components; the descriptor for a removed count k is the centred image minus its projection
on the first k of them. Everything outside their span is kept, however few training places
there are.

For the sweep's one matching pass over every k, ``suffix_descriptors`` writes an image as
``[c_1 .. c_K, r]``: its coefficients on the K components and the residual after all K.
The dot product of two such vectors over features ``[k:]`` is that of their k-removed
descriptors (the coefficients are on orthonormal directions, the residual is orthogonal to
them), and so are the norms, so the cosine on the suffix ``[k:]`` is exactly the cosine of
``encode(state, images, k)``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from jaxtyping import Array, Float, Int

from vpr_jax.encoders import pca


class DiffPCAState(NamedTuple):
    mean: Float[Array, " d"]  # training mean of both seasons' images: centres every image
    components: Float[Array, "c d"]  # directions of seasonal change, largest first
    explained_variance: Float[Array, " c"]  # the differences' second moment along each


def difference_rank(n_places: int, n_pixels: int) -> int:
    """How many change directions ``n_places`` aligned differences can span."""
    return min(n_places, n_pixels)


def fit_diff_pca(
    train_a: Float[Array, "n ..."],
    train_b: Float[Array, "n ..."],
    n_components: int | None = None,
    *,
    solver: pca.Solver = "auto",
    mesh: Mesh | None = None,
) -> DiffPCAState:
    """Fit on aligned training images: row i of ``train_a`` and of ``train_b`` show the same
    place in two seasons. ``n_components`` (the largest count to remove) defaults to every
    direction the differences can span, ``difference_rank``: the sweep fits them all, so
    the shapes, and so the compiled programs, do not depend on the removed-PC counts."""
    a = np.asarray(train_a, np.float32).reshape(len(train_a), -1)
    b = np.asarray(train_b, np.float32).reshape(len(train_b), -1)
    if a.shape != b.shape:
        raise ValueError(f"aligned training sets differ in shape: {a.shape} and {b.shape}")
    rank = difference_rank(*a.shape)
    n_components = rank if n_components is None else n_components
    if not 1 <= n_components <= rank:
        raise ValueError(
            f"n_components={n_components} outside 1..{rank} for {len(a)} aligned "
            f"places of {a.shape[1]} pixels"
        )
    diff = a - b
    # PCA of the differences and their negatives: the mean is exactly zero, so the
    # covariance it diagonalises is the second moment of the differences.
    moments = pca.fit_pca(np.concatenate([diff, -diff]), n_components, solver, mesh=mesh)
    scale = (2 * len(diff) - 1) / (2 * len(diff))  # ddof=1 of 2n samples -> mean of d d^T
    mean = jnp.mean(jnp.concatenate([jnp.asarray(a), jnp.asarray(b)]), axis=0)
    return DiffPCAState(mean, moments.components, moments.explained_variance * scale)


def encode(
    state: DiffPCAState, images: Float[Array, "n ..."], removed_pcs: int | Int[Array, ""]
) -> Float[Array, "n d"]:
    """Centred images minus their projection on the first ``removed_pcs`` change directions
    (at most ``len(state.components)``; a traced count works, so ``vmap`` over counts does):
    PCA change removal's pixel form, on these directions."""
    return pca.encode(state, images, removed_pcs, "pixels")


def suffix_descriptors(
    state: DiffPCAState, images: Float[Array, "n ..."]
) -> Float[Array, "n c_plus_d"]:
    """``[coefficients on every component, residual after all of them]``
    (``pca.suffix_descriptors``): cosine on the features ``[k:]`` equals cosine of
    ``encode(state, images, k)`` for every k."""
    return pca.suffix_descriptors(state, images)
