"""PCA change removal (Lowry & Milford): fit PCA on training images of both seasons, drop the
first principal components, which carry most of the appearance change between seasons.

The descriptor for a removed count k is the centred image minus its projection on the first
k components. Everything outside those k directions is kept, also what the training images
never spanned: with fewer training images than pixels, k = 0 is exactly raw pixels.

Fits (``solver``) all end in ``jnp.linalg.eigh``:
- ``covariance``: of the (D, D) covariance, summed over blocks of images: every component;
- ``gram``: of the (N, N) Gram matrix of the centred data, for fewer images than pixels;
- ``subspace``: only the leading ``n_components``, by a randomized range finder with a few
  power iterations over the scatter (``X_c^T (X_c V)``, never formed) and ``eigh`` of the
  small projected matrix (Rayleigh-Ritz; Halko, Martinsson & Tropp 2011, algorithm 4.4);
- ``auto``: ``subspace`` when the components asked for are few (``n_components`` +
  oversampling at most a quarter of the rank limit), else the smaller of the other two.

Every solver returns orthonormal components, and only as many as the data's numerical rank
holds (``numerical_rank``): real routes repeat frames (a train at a station, black tunnel
frames), so training images are often rank-deficient. The Gram and subspace solvers end in
a Householder QR of the directions they found and a Rayleigh-Ritz step (the scatter's
eigenvectors within their span), which is orthonormal whatever the rank; directions whose
variance is below the rank's floor are dropped. ``fit_pca`` checks the result
(``check_orthonormal``) and raises rather than return a fit that is not PCA.

A removed count's descriptor has two forms with the same cosine similarities:
- ``output="coefficients"``: ``[c_1 .. c_K, r]`` with the first k coefficients zeroed, ``c``
  the coefficients on the K fitted components and ``r`` the residual after all K (left out
  when the components span every pixel; on the covariance solver's remaining eigenvectors,
  ``PCAState.complement``, D - K values, where the fit holds them, as a full solve does
  below the numerical rank). The features ``[k:]`` of ``suffix_descriptors``
  are the k-removed descriptor, so one matching pass scores every k (``starts=ks``);
- ``output="pixels"``: the descriptor in pixel space, as the paper back-projected it.
"""

from __future__ import annotations

import functools
import math
import typing
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as P
from jaxtyping import Array, Float, Int

from vpr_jax import sharding
from vpr_jax.precision import f32_matmul
from vpr_jax.sharding import AXIS

Solver = Literal["auto", "covariance", "gram", "subspace"]
SOLVERS: tuple[str, ...] = typing.get_args(Solver)  # what pca.solver names
Output = Literal["coefficients", "pixels"]


class PCAState(NamedTuple):
    mean: Float[Array, " d"]  # training mean, subtracted from every image before projecting
    components: Float[Array, "c d"]  # orthonormal rows, descending variance, deterministic sign
    explained_variance: Float[Array, " c"]  # eigenvalues of the sample covariance (ddof=1)
    # Orthonormal rows completing the components to a basis of every pixel, where the solver
    # found them (the covariance solver's other eigenvectors: those past n_components or
    # below the numerical rank); None otherwise. Only suffix_descriptors reads them.
    complement: Float[Array, "r d"] | None = None


def flatten(images: Float[Array, "n ..."]) -> Float[Array, "n d"]:
    return jnp.reshape(images, (images.shape[0], -1))


def device_rows(images) -> Float[Array, "n d"]:
    """(n, D) float32 rows of ``images`` on the device. A host array is flattened on the
    host (a view) and put in place (``sharding.on_device``); an eager ``jnp.reshape`` or
    ``jnp.asarray`` would copy the whole training set."""
    if isinstance(images, jax.Array):
        return flatten(sharding.on_device(images))
    return sharding.on_device(np.reshape(images, (len(images), -1)))


def rank_limit(n_samples: int, n_features: int) -> int:
    """How many components centred data of this shape can have."""
    return min(n_samples - 1, n_features)


def rank_tolerance(n_samples: int, n_features: int) -> float:
    """The numerical rank's floor on a component's variance, relative to the largest:
    ``sqrt(max(n, d)) * eps`` (float32). Every solver forms sums of products of length n or
    d in float32, whose rounding grows as the square root of the length (Higham's
    probabilistic bound); LAPACK's worst-case rule, ``max(n, d) * eps``, would drop
    components float32 resolves well (the measurements: docs/methods.md, "PCA on any
    training set"). It holds because every product here is float32 on every device
    (``vpr_jax.precision``): TF32 rounds a product's inputs by up to 2^-11, 60 times this
    floor for the default route's 4,300 training images."""
    return math.sqrt(max(n_samples, n_features)) * float(np.finfo(np.float32).eps)


def numerical_rank(explained_variance, n_samples: int, n_features: int) -> int:
    """How many of these variances (descending) stand above ``rank_tolerance`` of the
    largest: the components the data hold."""
    var = np.asarray(explained_variance, np.float64)
    if not var.size or not var[0] > 0:
        return 0
    return int(np.sum(var > var[0] * rank_tolerance(n_samples, n_features)))


ORTHONORMAL_TOLERANCE = 1e-4  # largest |C C^T - I| a fit may have


class NotOrthonormal(ValueError):
    """A solver's components are not orthonormal: the fit is not PCA and is never used."""


@jax.jit
def orthonormality_error(components: Float[Array, "c d"]) -> Float[Array, ""]:
    """``max |C C^T - I|`` of the rows of ``components``."""
    gram = f32_matmul(components, components.T)
    return jnp.max(jnp.abs(gram - jnp.eye(gram.shape[0], dtype=gram.dtype)))


def check_orthonormal(state: PCAState, solver: str) -> None:
    """``NotOrthonormal`` unless the fit's components are orthonormal within tolerance:
    such a fit is not PCA, and every method built on it would score nonsense without a
    word. A complement (``PCAState.complement``) is checked with them: the suffix
    descriptors' equality with each removed count's rests on the whole basis."""
    rest = state.complement
    rows = state.components if rest is None else jnp.concatenate([state.components, rest])
    error = float(orthonormality_error(rows))
    if not error < ORTHONORMAL_TOLERANCE:  # NaN fails too
        raise NotOrthonormal(
            f"the {solver} PCA solver gave components that are not orthonormal (max |C C^T "
            f"- I| = {error:.2g}, tolerance {ORTHONORMAL_TOLERANCE:g})"
        )


SUBSPACE_OVERSAMPLE = 40  # extra directions the range finder carries (Halko et al.'s p)
SUBSPACE_POWER_ITERATIONS = 4  # scatter products before the Rayleigh-Ritz step


def choose_solver(
    n_samples: int, n_features: int, solver: Solver = "auto", n_components: int | None = None
) -> str:
    """The solver ``auto`` stands for (see the module docstring), or ``solver`` checked."""
    if solver not in SOLVERS:
        raise ValueError(f"unknown PCA solver {solver!r}: use {', '.join(SOLVERS)}")
    if solver != "auto":
        return solver
    few = n_components is not None and (
        4 * (n_components + SUBSPACE_OVERSAMPLE) <= rank_limit(n_samples, n_features)
    )
    if few:
        return "subspace"
    return "gram" if n_samples < n_features else "covariance"


def flip_signs(components: Float[Array, "c d"]) -> Float[Array, "c d"]:
    # scikit-learn's svd_flip convention: the largest-magnitude entry of each row is positive.
    rows = jnp.arange(components.shape[0])
    pivot = components[rows, jnp.argmax(jnp.abs(components), axis=1)]
    return components * jnp.where(pivot < 0, -1.0, 1.0)[:, None]


COVARIANCE_BLOCK_ROWS = 4096  # rows centred at once: the covariance never copies all of X


def _scatter(x, mean, n_valid, first_row, block_rows: int):
    """Sum of (x_i - mean)(x_i - mean)^T over rows whose global index is below ``n_valid``,
    accumulated over blocks of ``block_rows`` (rows past ``n_valid`` are padding)."""
    m, d = x.shape
    n_blocks = m // block_rows

    def block_scatter(block, start):
        valid = (start + jnp.arange(block.shape[0]) < n_valid)[:, None]
        xc = jnp.where(valid, block - mean, 0.0)
        return f32_matmul(xc.T, xc)

    def body(acc, i):
        block = jax.lax.dynamic_slice_in_dim(x, i * block_rows, block_rows)
        return acc + block_scatter(block, first_row + i * block_rows), None

    acc = jnp.zeros((d, d), x.dtype)
    if n_blocks:
        acc, _ = jax.lax.scan(body, acc, jnp.arange(n_blocks))
    if m % block_rows:  # the tail, static size: no padded copy of the data
        acc = acc + block_scatter(x[n_blocks * block_rows :], first_row + n_blocks * block_rows)
    return acc


@functools.partial(jax.jit, static_argnames=("block_rows",))
def _moments(x: Float[Array, "n d"], block_rows: int):
    """Mean and centred scatter matrix of all rows, on one device."""
    n = x.shape[0]
    mean = jnp.mean(x, axis=0)
    return mean, _scatter(x, mean, n, 0, block_rows)


@functools.lru_cache(maxsize=16)
def _sharded_moments(mesh, block_rows: int):
    """``_moments`` with the rows split across ``mesh``: each device sums its own rows
    (zero padding rows past ``n`` excluded), one ``psum`` per statistic."""

    def local(x, n):
        mean = jax.lax.psum(jnp.sum(x, axis=0), AXIS) / n  # padding rows are zeros
        first = jax.lax.axis_index(AXIS) * x.shape[0]
        return mean, jax.lax.psum(_scatter(x, mean, n, first, block_rows), AXIS)

    return jax.jit(
        jax.shard_map(
            local, mesh=mesh, in_specs=(P(AXIS), P()), out_specs=(P(), P()), check_vma=False
        )
    )


@functools.partial(jax.jit, static_argnames=("n_components",))
def _from_scatter(mean, scatter, n, n_components: int) -> PCAState:
    eigvals, eigvecs = jnp.linalg.eigh(scatter / (n - 1))
    eigvals, eigvecs = eigvals[::-1], eigvecs[:, ::-1].T  # descending, one a row
    components = flip_signs(eigvecs[:n_components])
    return PCAState(
        mean=mean,
        components=components,
        explained_variance=jnp.maximum(eigvals[:n_components], 0.0),
        complement=eigvecs[n_components:],
    )


def _rayleigh_ritz(centred_times, n: int, basis, n_components: int) -> PCAState:
    """The leading ``n_components`` principal components within the span of ``basis``
    (d, l): Householder QR makes an orthonormal Q whatever the basis's rank, then the
    eigenvectors of the scatter restricted to Q (``B^T B`` with ``B = X_c Q``, from
    ``centred_times(Q)``) rotate it. ``mean`` is filled in by the caller."""
    q, _ = jnp.linalg.qr(basis)
    b = centred_times(q)
    small = f32_matmul(b.T, b)
    eigvals, eigvecs = jnp.linalg.eigh((small + small.T) / 2)
    eigvals = eigvals[::-1][:n_components] / (n - 1)
    components = f32_matmul(q, eigvecs[:, ::-1][:, :n_components]).T
    return PCAState(
        mean=None, components=flip_signs(components), explained_variance=jnp.maximum(eigvals, 0.0)
    )


@functools.partial(jax.jit, static_argnames=("n_components",))
def _fit_gram(x: Float[Array, "n d"], n_components: int) -> PCAState:
    n = x.shape[0]
    mean = jnp.mean(x, axis=0)
    xc = x - mean
    _, eigvecs = jnp.linalg.eigh(f32_matmul(xc, xc.T))
    # Right singular vectors from left ones, v_i = Xc^T u_i / sigma_i, hold only where
    # lambda_i stands well above rounding (on real frames they drift from orthogonal well
    # before the rank's floor); as a basis for Rayleigh-Ritz, they give exact components.
    leading = eigvecs[:, ::-1][:, :n_components]
    return _rayleigh_ritz(
        lambda q: f32_matmul(xc, q), n, f32_matmul(xc.T, leading), n_components
    )._replace(mean=mean)


def _scatter_times(x, mean, v):
    """``X_c^T (X_c V)`` with ``X_c = x - mean``, without forming ``X_c``: the centring
    is applied to the (n, l) product, so no copy of the images is made."""
    w = f32_matmul(x, v) - f32_matmul(mean, v)
    return f32_matmul(x.T, w) - jnp.outer(mean, jnp.sum(w, axis=0))


def _cholesky_inverse(gram, floor):
    """``L^{-1}`` for the Cholesky factor ``L`` of a small symmetric positive matrix, by
    column-by-column loops of matrix-vector products: XLA operations only. A pivot is at
    least ``floor``, the smallest eigenvalue the matrix has in exact arithmetic (its
    shift): rounding can take a pivot of a matrix near float32's conditioning limit to zero
    or below, and dividing by it turned every component NaN."""
    size = gram.shape[0]
    rows = jnp.arange(size)

    def factor_column(j, low):
        v = gram[:, j] - f32_matmul(low, low[j])  # columns >= j of low are still zero
        pivot = jnp.sqrt(jnp.maximum(v[j], floor))
        return low.at[:, j].set(jnp.where(rows >= j, v / pivot, 0.0))

    low = jax.lax.fori_loop(0, size, factor_column, jnp.zeros_like(gram))

    def solve_row(i, inv):  # forward substitution of L Z = I, row by row
        row = jnp.eye(size, dtype=gram.dtype)[i] - f32_matmul(low[i], inv)
        return inv.at[i].set(row / low[i, i])

    return jax.lax.fori_loop(0, size, solve_row, jnp.zeros_like(gram))


# Shift of the Gram matrix in the power iterations' Cholesky QR, relative to its trace.
CHOLESKY_SHIFT = 1e-5


def _orthonormalise(y):
    """Columns spanning ``y``'s leading directions, orthonormal where ``y`` is well
    conditioned: shifted Cholesky QR twice, ``R = chol(Y^T Y + s I)`` with ``s`` =
    ``CHOLESKY_SHIFT`` x the mean diagonal, at least the factor's rounding (the block's width
    x eps x its largest diagonal entry). Plain Cholesky QR squares the block's condition
    number, which on real frames' steep spectrum passes float32's 1 / epsilon and turned
    every component NaN; the shift keeps the factor finite, and directions below it (noise
    to the power iteration) merely come out short. The last block goes through Householder
    QR before Rayleigh-Ritz, so the fitted components are orthonormal regardless. Pure XLA:
    a LAPACK call between the power iterations leaves OpenBLAS threads spinning, which slows
    the next product (docs/speed.md)."""
    for _ in range(2):
        gram = f32_matmul(y.T, y)
        size = gram.shape[0]
        rounding = size * jnp.finfo(y.dtype).eps * jnp.max(jnp.diag(gram))
        shift = jnp.maximum(CHOLESKY_SHIFT * jnp.trace(gram) / size, rounding)
        shift = shift + jnp.finfo(y.dtype).tiny
        inverse = _cholesky_inverse(gram + shift * jnp.eye(gram.shape[0], dtype=y.dtype), shift)
        y = f32_matmul(y, inverse.T)
    return y


@functools.partial(jax.jit, static_argnames=("n_components", "n_iter", "oversample"))
def _fit_subspace(x, key, n_components: int, n_iter: int, oversample: int) -> PCAState:
    """The leading ``n_components`` by subspace iteration and Rayleigh-Ritz (one device)."""
    n, d = x.shape
    mean = jnp.mean(x, axis=0)
    width = min(n_components + oversample, rank_limit(n, d))
    basis = _orthonormalise(jax.random.normal(key, (d, width), x.dtype))
    for _ in range(n_iter - 1):  # a few: unrolled, each one scatter product
        basis = _orthonormalise(_scatter_times(x, mean, basis))
    # The last block through Householder QR and Rayleigh-Ritz: robust whatever the rank.
    state = _rayleigh_ritz(
        lambda q: f32_matmul(x, q) - f32_matmul(mean, q),
        n,
        _scatter_times(x, mean, basis),
        n_components,
    )
    return state._replace(mean=mean)


def fit_pca(
    train: Float[Array, "n ..."],
    n_components: int | None = None,
    solver: Solver = "auto",
    *,
    mesh: Mesh | None = None,
    block_rows: int = COVARIANCE_BLOCK_ROWS,
    seed: int = 0,
) -> PCAState:
    """Fit PCA on training images (any trailing shape; flattened to D pixels).

    ``n_components`` defaults to the rank limit min(N - 1, D); the fit holds fewer where
    the data's numerical rank is lower (``numerical_rank``: repeated or constant images, or
    a spectrum that falls below float32's resolution). ``NotOrthonormal`` for a fit that is
    not orthonormal (``check_orthonormal``). The covariance solver sums the centred scatter
    over blocks of ``block_rows`` images, and with a ``mesh`` splits the images across its
    devices (``vpr_jax.sharding``); the Gram and subspace solvers run on one device (the
    subspace solver's products are a few passes over the images). ``seed`` draws the
    subspace solver's starting directions.
    """
    if mesh is None:
        x = device_rows(train)
    else:  # host rows, split across the mesh below
        x = np.reshape(np.asarray(train, np.float32), (len(train), -1))
    n, d = x.shape
    limit = rank_limit(n, d)
    if limit < 1:
        raise ValueError(f"PCA needs at least 2 training images, got {n}")
    n_components = limit if n_components is None else n_components
    if not 1 <= n_components <= limit:
        raise ValueError(f"n_components={n_components} outside 1..{limit} for {n} x {d} data")
    chosen = choose_solver(n, d, solver, n_components)
    if chosen == "gram":
        state = _fit_gram(x, n_components)
    elif chosen == "subspace":
        state = _fit_subspace(
            jnp.asarray(x, jnp.float32),
            jax.random.key(seed),
            n_components,
            SUBSPACE_POWER_ITERATIONS,
            SUBSPACE_OVERSAMPLE,
        )
    else:
        if mesh is None:
            mean, scatter = _moments(x, block_rows)
        else:
            rows = sharding.put_rows(sharding.pad_rows(x, sharding.mesh_size(mesh)), mesh)
            mean, scatter = _sharded_moments(mesh, block_rows)(rows, jnp.float32(n))
        state = _from_scatter(mean, scatter, n, n_components)
    state = within_rank(state, n, d)
    check_orthonormal(state, chosen)
    return state


def within_rank(state: PCAState, n: int, d: int) -> PCAState:
    """``state`` less the components beyond the numerical rank of its ``n`` x ``d`` training
    images (host slices); those still complete the basis where it has a complement."""
    kept = numerical_rank(state.explained_variance, n, d)
    if kept < 1:
        raise ValueError(f"PCA of {n} training images found no variance: every image is the same")
    if kept == len(state.components):
        return state
    rest = state.complement
    return state._replace(
        components=state.components[:kept],
        explained_variance=state.explained_variance[:kept],
        complement=None if rest is None else jnp.concatenate([state.components[kept:], rest]),
    )


@jax.jit
def project(state: PCAState, images: Float[Array, "n ..."]) -> Float[Array, "n c"]:
    """Coefficients of every component, centred with the TRAINING mean."""
    return f32_matmul(flatten(images) - state.mean, state.components.T)


@jax.jit
def suffix_descriptors(state, images: Float[Array, "n ..."]) -> Float[Array, "n e"]:
    """``[c_1 .. c_K, r]``: coefficients on the K components of ``state`` (anything with
    orthonormal ``components`` rows and a ``mean``) and the residual after all K: left out
    when the components span every pixel, its coordinates on ``state.complement`` where the
    fit holds the rest of a basis (D values a row in all, not K + D), else the residual
    itself in pixels. Cosine on the features ``[k:]`` equals cosine of
    ``encode(state, images, k)`` for every k <= K: the coefficients lie on orthonormal
    directions and the residual is orthogonal to them, so dot products and norms of the
    suffix are those of the k-removed descriptors."""
    x = flatten(images) - state.mean
    coefficients = f32_matmul(x, state.components.T)
    n_components, n_pixels = state.components.shape
    if n_components == n_pixels:  # a complete basis: nothing is left over
        return coefficients
    rest = getattr(state, "complement", None)
    if rest is not None and n_components + rest.shape[0] == n_pixels:
        return jnp.concatenate([coefficients, f32_matmul(x, rest.T)], axis=1)
    return jnp.concatenate([coefficients, x - f32_matmul(coefficients, state.components)], axis=1)


@functools.partial(jax.jit, static_argnames=("output",))
def encode(
    state: PCAState,
    images: Float[Array, "n ..."],
    removed_pcs: int | Int[Array, ""],
    output: Output = "coefficients",
) -> Float[Array, "n e"]:
    """Change-removed descriptors: the centred images minus their projection on the first
    ``removed_pcs`` components (at most K = ``len(state.components)``).

    ``output="coefficients"``: ``suffix_descriptors`` with the first ``removed_pcs``
    features zeroed, shape (n, K + D), or (n, D) for a complete basis or one completed by
    ``state.complement``; ``"pixels"``: the
    same descriptor in pixel space, (n, D). Both give the same cosine similarities. Zeroing
    instead of slicing keeps the shape fixed, so one compiled function serves every count
    and ``jax.vmap`` over a vector of counts works (``state`` may be any fit with a
    ``mean`` and orthonormal ``components``, e.g. ``diff_pca``'s).
    """
    if output == "pixels":
        x = flatten(images) - state.mean
        first = jnp.arange(state.components.shape[0]) < removed_pcs
        kept = jnp.where(first, f32_matmul(x, state.components.T), 0.0)
        return x - f32_matmul(kept, state.components)
    if output != "coefficients":
        raise ValueError(f"unknown output {output!r}: use coefficients or pixels")
    described = suffix_descriptors(state, images)
    return jnp.where(jnp.arange(described.shape[1]) >= removed_pcs, described, 0.0)
