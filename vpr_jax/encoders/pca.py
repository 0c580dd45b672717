"""PCA change removal (Lowry & Milford): fit PCA on training images of both seasons, drop the
first principal components, which carry most of the appearance change between seasons.

The fit uses ``jnp.linalg.eigh`` of whichever symmetric matrix is smaller: the (D, D)
covariance when samples outnumber pixels, else the (N, N) Gram matrix of the centred data.

Removing the first k components can be expressed two ways and both are supported:
- ``output="coefficients"``: the coefficients on components k, k+1, ... (what the sweep uses);
- ``output="pixels"``: those coefficients mapped back to pixel space, as the seed did.
Because the components are orthonormal, both give the same cosine similarities.
"""

from __future__ import annotations

import functools
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

Solver = Literal["auto", "covariance", "gram"]
Output = Literal["coefficients", "pixels"]


class PCAState(NamedTuple):
    mean: Float[Array, " d"]  # training mean, subtracted from every image before projecting
    components: Float[Array, "c d"]  # orthonormal rows, descending variance, deterministic sign
    explained_variance: Float[Array, " c"]  # eigenvalues of the sample covariance (ddof=1)


def flatten(images: Float[Array, "n ..."]) -> Float[Array, "n d"]:
    return jnp.reshape(images, (images.shape[0], -1))


def rank_limit(n_samples: int, n_features: int) -> int:
    """How many components centred data of this shape can have."""
    return min(n_samples - 1, n_features)


def choose_solver(n_samples: int, n_features: int, solver: Solver = "auto") -> str:
    if solver == "auto":
        return "gram" if n_samples < n_features else "covariance"
    if solver not in ("covariance", "gram"):
        raise ValueError(f"unknown PCA solver {solver!r}: use auto, covariance or gram")
    return solver


def _flip_signs(components: Float[Array, "c d"]) -> Float[Array, "c d"]:
    # scikit-learn's svd_flip convention: the largest-magnitude entry of each row is positive.
    rows = jnp.arange(components.shape[0])
    pivot = components[rows, jnp.argmax(jnp.abs(components), axis=1)]
    return components * jnp.where(pivot < 0, -1.0, 1.0)[:, None]


@functools.partial(jax.jit, static_argnames=("n_components", "solver"))
def _fit(x: Float[Array, "n d"], n_components: int, solver: str) -> PCAState:
    n = x.shape[0]
    mean = jnp.mean(x, axis=0)
    xc = x - mean
    if solver == "covariance":
        eigvals, eigvecs = jnp.linalg.eigh(xc.T @ xc / (n - 1))
        eigvals = eigvals[::-1][:n_components]
        components = eigvecs[:, ::-1][:, :n_components].T
    else:
        eigvals, eigvecs = jnp.linalg.eigh(xc @ xc.T)
        eigvals = eigvals[::-1][:n_components]
        # Right singular vectors from left ones: v_i = Xc^T u_i / sqrt(lambda_i).
        scale = jnp.where(eigvals > 0, jax.lax.rsqrt(jnp.maximum(eigvals, 1e-30)), 0.0)
        components = (xc.T @ eigvecs[:, ::-1][:, :n_components] * scale).T
        eigvals = eigvals / (n - 1)
    return PCAState(mean, _flip_signs(components), jnp.maximum(eigvals, 0.0))


def fit_pca(
    train: Float[Array, "n ..."],
    n_components: int | None = None,
    solver: Solver = "auto",
) -> PCAState:
    """Fit PCA on training images (any trailing shape; flattened to D pixels).

    ``n_components`` defaults to the rank limit min(N - 1, D).
    """
    x = flatten(jnp.asarray(train, jnp.float32))
    n, d = x.shape
    limit = rank_limit(n, d)
    if limit < 1:
        raise ValueError(f"PCA needs at least 2 training images, got {n}")
    n_components = limit if n_components is None else n_components
    if not 1 <= n_components <= limit:
        raise ValueError(f"n_components={n_components} outside 1..{limit} for {n} x {d} data")
    return _fit(x, n_components, choose_solver(n, d, solver))


@jax.jit
def project(state: PCAState, images: Float[Array, "n ..."]) -> Float[Array, "n c"]:
    """Coefficients of every component, centred with the TRAINING mean."""
    return (flatten(images) - state.mean) @ state.components.T


@functools.partial(jax.jit, static_argnames=("output",))
def encode(
    state: PCAState,
    images: Float[Array, "n ..."],
    removed_pcs: int | Int[Array, ""],
    output: Output = "coefficients",
) -> Float[Array, "n e"]:
    """Change-removed descriptors: the first ``removed_pcs`` components are zeroed.

    Zeroing instead of slicing keeps the shape fixed, so one compiled function serves every
    removed-PC count and ``jax.vmap`` over a vector of counts works. ``output="pixels"`` maps
    the kept coefficients back to pixel space, shape (n, D).
    """
    coeffs = project(state, images)
    kept = jnp.arange(coeffs.shape[1]) >= removed_pcs
    coeffs = jnp.where(kept, coeffs, 0.0)
    if output == "pixels":
        return coeffs @ state.components
    if output != "coefficients":
        raise ValueError(f"unknown output {output!r}: use coefficients or pixels")
    return coeffs
