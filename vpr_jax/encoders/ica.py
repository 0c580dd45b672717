"""Symmetric (parallel) FastICA in JAX: independent components as place descriptors.

The data are whitened with the suite's PCA fit (``vpr_jax.encoders.pca``), optionally after
dropping the first ``removed_pcs`` components (change removal, then ICA): the whitened
coordinates are the coefficients on components k, ..., k + c - 1, each divided by its
standard deviation, so the training data have identity covariance.

On whitened samples z, FastICA (Hyvarinen 1999) looks for an orthogonal W whose rows give
maximally non-Gaussian projections. The one-unit fixed-point update for a row w is

    w+ = E[z g(w.z)] - E[g'(w.z)] w

with g the derivative of the contrast G (``fun``: logcosh, exp or cube). ``one_unit_update``
is written for one row and ``jax.vmap``-ed over the rows of W; then the rows are made
orthonormal together by symmetric decorrelation W <- (W W^T)^(-1/2) W (through ``eigh``),
and this repeats in ``lax.while_loop`` until max |abs(diag(W_new W^T)) - 1| < tol or
``max_iter`` updates. This is scikit-learn's ``FastICA(algorithm="parallel")``, fitted
with the same whitening (population variance), contrast functions and stopping rule.

The fitted ``ICAState`` is a pytree of arrays; ``encode(state, images)`` is pure and jitted,
so it works under ``jax.vmap`` and inside other jitted functions. Components come out in a
fixed order and sign: by decreasing pixel-space energy of their mixing column (the image an
independent component adds), with that column's largest-magnitude pixel positive.
"""

from __future__ import annotations

import contextlib
import functools
import typing
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Bool, Float, Int
from threadpoolctl import threadpool_limits

from vpr_jax.encoders import pca
from vpr_jax.precision import f32_matmul

Fun = Literal["logcosh", "exp", "cube"]
FUNS: tuple[str, ...] = typing.get_args(Fun)  # the contrasts ica.fun names


class ICAState(NamedTuple):
    mean: Float[Array, " d"]  # training mean, subtracted before whitening
    whitening: Float[Array, "c d"]  # PCA components k..k+c-1 over their standard deviations
    unmixing: Float[Array, "c c"]  # orthogonal W: sources = W @ whitened
    n_iter: Int[Array, ""]  # fixed-point updates run (of the kept initialisation)
    converged: Bool[Array, ""]  # reached tol before max_iter


# ------------------------------------------------------------------------- the algorithm


def nonlinearity(fun: str, u: Float[Array, "..."], alpha: float | Float[Array, ""] = 1.0):
    """g(u) and g'(u) for the contrast ``fun`` (logcosh with ``alpha`` in [1, 2])."""
    if fun == "logcosh":
        gu = jnp.tanh(alpha * u)
        return gu, alpha * (1.0 - gu * gu)
    if fun == "exp":
        e = jnp.exp(-0.5 * u * u)
        return u * e, (1.0 - u * u) * e
    if fun == "cube":
        return u * u * u, 3.0 * u * u
    raise ValueError(f"unknown ICA contrast fun={fun!r}: use one of {', '.join(FUNS)}")


def contrast(fun: str, u: Float[Array, "..."], alpha: float | Float[Array, ""] = 1.0):
    """The contrast G itself (G' = g), for the negentropy objective."""
    if fun == "logcosh":
        # log cosh(a u) = |a u| + log1p(exp(-2 |a u|)) - log 2, stable for large |u|.
        au = jnp.abs(alpha * u)
        return (au + jnp.log1p(jnp.exp(-2.0 * au)) - jnp.log(2.0)) / alpha
    if fun == "exp":
        return -jnp.exp(-0.5 * u * u)
    if fun == "cube":
        return 0.25 * u**4
    raise ValueError(f"unknown ICA contrast fun={fun!r}: use one of {', '.join(FUNS)}")


def one_unit_update(
    w: Float[Array, " c"],
    z: Float[Array, "n c"],
    fun: str,
    alpha,
    z_t: Float[Array, "c n"] | None = None,
) -> Float[Array, " c"]:
    """The fixed-point step for one row: w+ = E[z g(w.z)] - E[g'(w.z)] w.

    ``z_t`` is z transposed, when the caller keeps a copy: under ``vmap`` over rows the
    second product then reads contiguous rows, which is faster than a strided read.
    """
    gy, dgy = nonlinearity(fun, f32_matmul(z, w), alpha)
    z_t = z.T if z_t is None else z_t
    return f32_matmul(z_t, gy) / z.shape[0] - jnp.mean(dgy) * w


def symmetric_decorrelation(w: Float[Array, "c c"]) -> Float[Array, "c c"]:
    """W <- (W W^T)^(-1/2) W: the nearest matrix with orthonormal rows."""
    s, u = jnp.linalg.eigh(f32_matmul(w, w.T))
    s = jnp.maximum(s, jnp.finfo(w.dtype).tiny)  # rounding can make tiny eigenvalues negative
    return f32_matmul(u * lax.rsqrt(s), f32_matmul(u.T, w))


@functools.partial(jax.jit, static_argnames=("fun",))
def fastica(
    z: Float[Array, "n c"],
    w_init: Float[Array, "c c"],
    fun: str = "logcosh",
    alpha: float | Float[Array, ""] = 1.0,
    max_iter: int | Int[Array, ""] = 200,
    tol: float | Float[Array, ""] = 1e-4,
) -> tuple[Float[Array, "c c"], Int[Array, ""], Float[Array, ""]]:
    """Symmetric FastICA on whitened samples ``z``: (W, updates run, last change).

    ``alpha``, ``max_iter`` and ``tol`` are traced, so changing them does not recompile;
    ``jax.vmap`` over ``w_init`` runs several initialisations at once.
    """
    update_rows = jax.vmap(one_unit_update, in_axes=(0, None, None, None, None))
    z_t = z.T  # materialised once, outside the loop

    def keep_going(carry):
        _, i, change = carry
        return (i < max_iter) & (change >= tol)

    def step(carry):
        w, i, _ = carry
        w_new = symmetric_decorrelation(update_rows(w, z, fun, alpha, z_t))
        change = jnp.max(jnp.abs(jnp.abs(jnp.sum(w_new * w, axis=1)) - 1.0))
        return w_new, i + 1, change

    w0 = symmetric_decorrelation(w_init.astype(z.dtype))
    start = (w0, jnp.asarray(0, jnp.int32), jnp.asarray(jnp.inf, z.dtype))
    return lax.while_loop(keep_going, step, start)


@functools.cache
def _gaussian_contrast(fun: str, alpha: float) -> float:
    """E[G(v)] for a standard normal v, by 80-point Gauss-Hermite quadrature."""
    x, w = np.polynomial.hermite_e.hermegauss(80)
    return float(np.sum(w * np.asarray(contrast(fun, jnp.asarray(x), alpha))) / np.sqrt(2 * np.pi))


def negentropy(
    w: Float[Array, "c c"], z: Float[Array, "n c"], fun: str, alpha: float
) -> Float[Array, ""]:
    """FastICA's objective: sum over components of (E[G(w.z)] - E[G(gaussian)])^2."""
    projections = f32_matmul(z, w.T)
    gap = jnp.mean(contrast(fun, projections, alpha), axis=0) - _gaussian_contrast(fun, alpha)
    return jnp.sum(gap * gap)


# ------------------------------------------------------------------------------ fitting


def data_rank(state: pca.PCAState, n_samples: int) -> int:
    """Numerical rank of the training data behind a PCA fit (``pca.numerical_rank``)."""
    return pca.numerical_rank(state.explained_variance, n_samples, state.components.shape[1])


def resolve_n_components(n_components: int | str | None, removed_pcs: int, rank: int) -> int:
    """``"all"`` / None -> every component left after removal; check an explicit count."""
    left = rank - removed_pcs
    if n_components in (None, "all"):
        if left < 1:
            raise ValueError(
                f"removed_pcs={removed_pcs} leaves no component for ICA: the training data "
                f"have rank {rank}"
            )
        return left
    n = int(n_components)
    if n < 1 or n > left:
        raise ValueError(
            f"ica.n_components={n} with removed_pcs={removed_pcs} needs {removed_pcs + n} "
            f"components but the training data have rank {rank}: use ica.n_components <= "
            f"{max(left, 0)} or ica.n_components=all"
        )
    return n


@functools.partial(jax.jit, static_argnames=("n_components",))
def whitening_matrix(
    state: pca.PCAState,
    n_samples: int | Int[Array, ""],
    removed_pcs: int | Int[Array, ""],
    n_components: int,
) -> Float[Array, "c d"]:
    """Rows: PCA components k..k+c-1 over their population standard deviation.

    ``removed_pcs`` is traced: a sweep over k compiles this once per component count."""
    comps = lax.dynamic_slice_in_dim(state.components, removed_pcs, n_components)
    var = lax.dynamic_slice_in_dim(state.explained_variance, removed_pcs, n_components)
    return comps * lax.rsqrt(var * (n_samples - 1) / n_samples)[:, None]


@jax.jit
def mixing(state: ICAState) -> Float[Array, "d c"]:
    """Columns: the image each independent component adds (pseudo-inverse of W @ K).

    The whitening rows are orthogonal (scaled PCA components), so pinv(K) = K^T / |rows|^2.
    """
    k = state.whitening
    return f32_matmul(k.T / jnp.sum(k * k, axis=1), state.unmixing.T)


@jax.jit
def _canonical(state: ICAState) -> ICAState:
    """Rows of W ordered by decreasing mixing-column energy; each column's peak positive."""
    a = mixing(state)
    order = jnp.argsort(-jnp.sum(a * a, axis=0))
    a = a[:, order]
    peak = a[jnp.argmax(jnp.abs(a), axis=0), jnp.arange(a.shape[1])]
    sign = jnp.where(peak < 0, -1.0, 1.0).astype(a.dtype)
    return state._replace(unmixing=state.unmixing[order] * sign[:, None])


@contextlib.contextmanager
def _one_blas_thread():
    """Hold BLAS (OpenBLAS under jax's CPU eigh) to one thread for the FastICA loop.

    On CPU the eigh in every iteration is a LAPACK call; OpenBLAS workers keep spinning after
    it returns and take a core from XLA's matrix products, which slows every iteration. A
    tiny eigh first loads that library, so the limit reaches it.
    """
    jax.block_until_ready(jnp.linalg.eigh(jnp.eye(2)))
    with threadpool_limits(1, user_api="blas"):
        yield


def fit_ica(
    train: Float[Array, "n ..."],
    key: jax.Array | None = None,
    *,
    n_components: int | str | None = "all",
    removed_pcs: int = 0,
    fun: Fun = "logcosh",
    alpha: float = 1.0,
    max_iter: int = 200,
    tol: float = 1e-4,
    w_init: Float[Array, "c c"] | None = None,
    n_init: int = 1,
    pca_state: pca.PCAState | None = None,
    pca_solver: pca.Solver = "auto",
) -> ICAState:
    """Fit symmetric FastICA on training images (any trailing shape; flattened).

    ``key`` draws the initial W (standard normal, as scikit-learn does); or pass ``w_init``.
    ``n_init > 1`` runs that many initialisations at once (vmapped over keys) and keeps the
    one with the largest negentropy. ``pca_state`` reuses a PCA fit of the same ``train``
    (the sweep shares one per season pair); otherwise PCA is fitted here, only as far as a
    given ``n_components`` reaches.
    ``n_components="all"`` keeps every component the data allow after removing
    ``removed_pcs`` (the paper's "all ICs, no dimension reduction").
    """
    _check_settings(fun, alpha, max_iter, tol, n_init, key, w_init)

    x = pca.device_rows(train)
    n = x.shape[0]
    if pca_state is None:
        # A count of components needs only the leading removed_pcs + count of PCA (the
        # subspace solver's partial fit); "all" needs every one.
        limit = pca.rank_limit(n, x.shape[1])
        wanted = None if n_components in (None, "all") else removed_pcs + int(n_components)
        wanted = wanted if wanted is not None and 1 <= wanted <= limit else None
        pca_state = pca.fit_pca(x, wanted, solver=pca_solver)
    c = resolve_n_components(n_components, removed_pcs, data_rank(pca_state, n))
    k_white = whitening_matrix(pca_state, n, removed_pcs, c)
    z = f32_matmul(x - pca_state.mean, k_white.T)

    if w_init is not None:
        inits = jnp.asarray(w_init, jnp.float32)[None]
        if inits.shape[1:] != (c, c):
            raise ValueError(f"w_init has shape {inits.shape[1:]}, expected {(c, c)}")
    else:
        inits = jax.vmap(lambda k: jax.random.normal(k, (c, c)))(jax.random.split(key, n_init))
    w, n_iter, change = _best_of_inits(z, inits, fun, alpha, max_iter, tol)
    return _canonical(
        ICAState(
            mean=pca_state.mean,
            whitening=k_white,
            unmixing=w,
            n_iter=n_iter,
            converged=change < tol,
        )
    )


def _check_settings(fun, alpha, max_iter, tol, n_init, key, w_init) -> None:
    if fun not in FUNS:
        raise ValueError(f"unknown ICA contrast fun={fun!r}: use one of {', '.join(FUNS)}")
    if fun == "logcosh" and not 1.0 <= alpha <= 2.0:
        raise ValueError(f"ica.alpha={alpha} must lie in [1, 2] (logcosh)")
    if max_iter < 1 or tol <= 0:
        raise ValueError(f"need max_iter >= 1 and tol > 0, got {max_iter} and {tol}")
    if n_init < 1 or (w_init is not None and n_init != 1):
        raise ValueError(f"n_init={n_init}: use n_init >= 1, and n_init=1 with w_init")
    if (key is None) == (w_init is None):
        raise ValueError("pass exactly one of key (random initial W) and w_init")


def _best_of_inits(z, inits, fun: Fun, alpha: float, max_iter: int, tol: float):
    """(W, iterations, last change) of FastICA from each initial W of ``inits`` (vmapped
    when there are several), the one with the largest negentropy."""
    with _one_blas_thread():
        if len(inits) == 1:
            return jax.block_until_ready(fastica(z, inits[0], fun, alpha, max_iter, tol))
        ws, iters, changes = jax.block_until_ready(
            jax.vmap(fastica, in_axes=(None, 0, None, None, None, None))(
                z, inits, fun, alpha, max_iter, tol
            )
        )
        scores = jax.vmap(negentropy, in_axes=(0, None, None, None))(ws, z, fun, alpha)
        best = jnp.argmax(scores)
        return ws[best], iters[best], changes[best]


@jax.jit
def encode(state: ICAState, images: Float[Array, "n ..."]) -> Float[Array, "n c"]:
    """Independent-component coefficients (sources) of images; unit variance on training."""
    whitened = f32_matmul(pca.flatten(images) - state.mean, state.whitening.T)
    return f32_matmul(whitened, state.unmixing.T)


def amari_distance(unmixing: np.ndarray, true_mixing: np.ndarray) -> float:
    """Amari et al. (1996) distance of P = unmixing @ true_mixing from a scaled permutation.

    0 when every recovered component is exactly one source; at most 1.
    """
    p = np.abs(np.asarray(unmixing, np.float64) @ np.asarray(true_mixing, np.float64))
    n = p.shape[0]
    if n < 2:
        return 0.0
    rows = np.sum(p.sum(axis=1) / p.max(axis=1) - 1.0)
    cols = np.sum(p.sum(axis=0) / p.max(axis=0) - 1.0)
    return float((rows + cols) / (2.0 * n * (n - 1)))
