"""What a method hands the runner: ``Descriptors`` of a pair's database, queries and
validation places, and the ``MethodContext`` it may draw on; the shared steps of making
them (timed fits, warm encoding, the degenerate-descriptor check)."""

from __future__ import annotations

import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from jaxtyping import Array, Float

from vpr_jax import host_arrays
from vpr_jax.data.pair import PairData
from vpr_jax.data.precomputed import OutsideSide
from vpr_jax.encoders import pca
from vpr_jax.encoders.train import TrainingLog

_EPS = 1e-12


class PCAFit(NamedTuple):
    """The pair's PCA fit, shared by its PCA and ICA cells (ICA whitens with it)."""

    state: pca.PCAState
    seconds: float


class Fitted(NamedTuple):
    """What a method fitted, to be saved as an encoder (``vpr_jax.encoders.saved``)."""

    folder: str  # under the pair's folder of train.checkpoint_dir: the run's name, less "_dsNN"
    encode: str  # how the state encodes: "module:function" (encode(state, images,
    # removed_pcs), see vpr_jax.encoders.saved), "autoencoder" or "plugin"
    state: Any  # the pytree of arrays (None for the auto-encoders: their checkpoint holds it)
    counts: tuple[int, ...] = (0,)  # the removed-PC counts this state serves


class Descriptors(NamedTuple):
    """What one method made of a pair: the descriptors of the database and the queries, for
    one or more removed-PC counts, and what the fit cost and found."""

    method: str
    removed_pcs: tuple[int, ...]  # the cells these descriptors serve (0 without the axis)
    starts: tuple[int, ...]  # per count: cosine on descriptor features [start:]
    db: jax.Array  # (n_db, d)
    query: jax.Array  # (n_queries, d)
    val_db: jax.Array | None  # (n_val, d): the validation places, database season (None:
    val_query: jax.Array | None  # outside descriptors that do not cover them, NaN scores)
    fit_seconds: float
    encode_ms_per_image: float  # warm (compiled) encoding time
    n_iter: int = 0  # iterations of an iterative fit (0: closed form; epochs when trained)
    converged: bool = True  # ICA: False when it stopped at ica.max_iter
    stopped_early: bool = False  # auto-encoders: early stopping ended training before its end
    basis: tuple[np.ndarray | None, ...] = ()  # per count: (m, 32, 64) images of what the
    basis_name: str = "removed_components"  # method removed or learned; TensorBoard tag
    warning: str | None = None  # one line for the run log (non-convergence, degenerate)
    objective: str = ""  # the auto-encoders' training objective; "" for the other methods
    fitted: Fitted | None = None  # what to save, so load_encoder gives the encoder back


class MethodContext(NamedTuple):
    """What a method may need from the runner besides the pair's images and the config."""

    removed_pcs: tuple[int, ...] = (0,)  # counts still to do (pca, diff_pca, ica)
    objectives: tuple[str, ...] = ("reconstruct",)  # objectives still to do (fae, cae)
    pca_fit: PCAFit | None = None  # the pair's PCA fit (pca, ica): see fit_pair_pca
    checkpoint_dir: Path | None = None  # this pair's model folders go under it
    training_log: Callable[[str], TrainingLog] | None = None  # method name -> its log
    identity: dict | None = None  # what besides its spec determines a trained model
    mesh: Mesh | None = None  # devices to split work over (vpr_jax.sharding); None: one
    outside: dict[str, dict[str, OutsideSide]] = {}  # precomputed sets, read by the plan
    # (validation database, validation query descriptors, suffix starts) -> the validation
    # places' recall@1 per start, as the sweep scores them (the runner matches; methods
    # never do): what the auto-encoders select epochs by and residual inputs choose k by.
    validate: Callable[[Array, Array, tuple[int, ...]], list[float]] | None = None


def method_key(seed: int, name: str) -> jax.Array:
    """The key a method draws its randomness from: the sweep's seed and the method's name
    (so adding or dropping another method changes nothing)."""
    return jax.random.fold_in(jax.random.key(seed), zlib.crc32(name.encode()))


def timed(fn: Callable, *args):
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - start


# Images a method encodes at once; more are encoded a block at a time (``encode_rows``).
ENCODE_BLOCK_ROWS = 4096


def encode_rows(encode: Callable, images, block_rows: int = ENCODE_BLOCK_ROWS):
    """``encode(images)``, for more than ``block_rows`` images a block at a time into one
    aligned host array (``vpr_jax.host_arrays``: the matcher reads it in place). An encoder's
    intermediates are the size of its input: PCA's for the whole 35,768-frame route were
    0.6 GiB beside its 0.3 GiB of descriptors. Fewer images (the paper protocol's 3,569)
    are encoded in one call, as before."""
    n = len(images)
    if n <= block_rows:
        return encode(images)
    first = np.asarray(encode(images[:block_rows]))
    out = host_arrays.empty((n, *first.shape[1:]), first.dtype)
    out[:block_rows] = first
    for start in range(block_rows, n, block_rows):
        out[start : start + block_rows] = np.asarray(encode(images[start : start + block_rows]))
    return out


def _encode(encode: Callable, pair: PairData) -> tuple[jax.Array, jax.Array, float]:
    """Database and query descriptors, and the warm encoding time in ms per image."""
    encode_rows(encode, pair.db)  # compile for these shapes
    db, seconds_db = timed(encode_rows, encode, pair.db)
    query, seconds_q = timed(encode_rows, encode, pair.query)
    return db, query, 1000 * (seconds_db + seconds_q) / (len(pair.db) + len(pair.query))


def encode_validation(encode: Callable, pair: PairData) -> tuple[jax.Array, jax.Array]:
    """(validation database, validation queries) descriptors of ``encode``."""
    if pair.aligned_training:  # one call: the shapes the training already compiled for
        both = encode(pair.val)
        return both[: len(pair.val_db)], both[len(pair.val_db) :]
    return encode(pair.val_db), encode(pair.val_query)


def degenerate_warning(db, query) -> str | None:
    """One run-log line when descriptors cannot tell places apart (zero descriptors, or all
    pointing one way): cosine matching of them is arbitrary, so the cell's metrics mean
    nothing. None when the descriptors are fine."""
    zero, parallel = [], []
    for name, desc in (("database", db), ("query", query)):
        n_zero, one_way = degenerate_rows(jax.numpy.reshape(desc, (len(desc), -1)))
        if int(n_zero):
            zero.append(f"{name} {int(n_zero):,} of {len(desc):,}")
        if bool(one_way):
            parallel.append(name)
    found = [f"zero descriptors ({', '.join(zero)})"] if zero else []
    if parallel:
        found.append(f"the nonzero {' and '.join(parallel)} descriptors all point one way")
    if not found:
        return None
    return (
        f"{' and '.join(found)}: their matches are arbitrary. Check for constant images "
        "(data.drop_constant_frames=true) or, for an auto-encoder, dead units (another "
        "seed, train.learning_rate, more epochs)"
    )


def describe(
    method: str,
    encode: Callable,
    pair: PairData,
    *,
    removed_pcs=(0,),
    starts=(0,),
    basis=(None,),
    warning: str | None = None,
    **fit,
) -> Descriptors:
    """Encode the pair with ``encode`` and add the degenerate-descriptor check's warning."""
    db, query, ms = _encode(encode, pair)
    found = "; ".join(w for w in (warning, degenerate_warning(db, query)) if w) or None
    val_db, val_query = encode_validation(encode, pair)
    return Descriptors(
        method=method,
        removed_pcs=tuple(removed_pcs),
        starts=tuple(starts),
        db=db,
        query=query,
        val_db=val_db,
        val_query=val_query,
        encode_ms_per_image=ms,
        basis=tuple(basis),
        warning=found,
        **fit,
    )


def as_images(vectors: np.ndarray, pair: PairData) -> np.ndarray:
    return np.asarray(vectors).reshape(len(vectors), *pair.train.shape[1:])


@jax.jit
def _row_norms(desc):
    return jnp.sqrt(jnp.sum(desc * desc, axis=1))


@jax.jit
def _largest_gap(desc, inv, first):
    """The largest distance of a unit row (``desc * inv``; zero rows have ``inv`` 0 and
    count 0) from ``first``: all point one way when it is tiny."""
    unit = desc * inv[:, None]  # fused into the sum: never written out
    gap = jnp.sqrt(jnp.sum((unit - first) ** 2, axis=1))  # cosine to first = 1 - gap^2 / 2
    return jnp.max(jnp.where(inv == 0.0, 0.0, gap))


def degenerate_rows(desc: Float[Array, "n d"]) -> tuple[int, bool]:
    """What makes cosine matching arbitrary: (how many rows are zero, whether all the other
    rows point the same way).

    A zero row scores 0 against everything (norm at most 1e-6 of the largest row's, or 0);
    rows that all point one way (pairwise cosine above 1 - 5e-7) score the same against
    every query. Two passes over blocks of ``ENCODE_BLOCK_ROWS`` rows (norms, then each
    row's distance from the first nonzero one), so nothing the size of the descriptors is
    allocated: one program over a 35,768-frame database took 0.26 GiB on its first run.
    """
    rows = [slice(s, s + ENCODE_BLOCK_ROWS) for s in range(0, len(desc), ENCODE_BLOCK_ROWS)]
    norms = np.concatenate([np.asarray(_row_norms(desc[r])) for r in rows] or [np.zeros(0)])
    zero = norms <= max(1e-6 * norms.max(initial=0.0), _EPS)
    inv = np.where(zero, 0.0, 1.0 / np.maximum(norms, _EPS)).astype(np.float32)
    if zero.all():
        return int(zero.sum()), False
    i = int(np.argmin(zero))  # the first nonzero row
    first = np.asarray(desc[i], np.float32) * inv[i]
    gap = max(float(_largest_gap(desc[r], inv[r], first)) for r in rows)
    return int(zero.sum()), gap <= 1e-3 and int((~zero).sum()) > 1
