"""What the runner makes of one fit of a method: ``Descriptors`` of a pair's database,
queries and validation places, with a ``Part`` per cell; and the shared steps of making
them (timed fits, blocked warm encoding, the degenerate-descriptor check)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from vpr_jax import host_arrays
from vpr_jax.data.pair import PairData
from vpr_jax.methods.contract import Report

_EPS = 1e-12


class Part(NamedTuple):
    """A cell's part of a fit's descriptors: its swept values and its run."""

    swept: dict  # the cell's swept values, by name ({} none): results.csv's settings column
    run: str  # its run's name less the pair and ds: fae_cross_season, ica_n_components=64_k005


class Descriptors(NamedTuple):
    """What one fit of a method made of a pair: the descriptors of the database, queries
    and validation places for one or more cells, and what the fit cost and found."""

    method: str
    objective: str  # the auto-encoders' training objective; "" for the other methods
    seed: int  # the fit's
    parts: tuple[Part, ...]  # the cells these descriptors serve
    starts: tuple[int, ...]  # per part: cosine on descriptor features [start:]
    db: jax.Array  # (n_db, d)
    query: jax.Array  # (n_queries, d)
    val_db: jax.Array | None  # (n_val, d): the validation places, database season (None:
    val_query: jax.Array | None  # outside descriptors that do not cover them, NaN scores)
    fit_seconds: float
    encode_ms_per_image: float  # warm (compiled) encoding time
    report: Report = Report()  # what the fit found (the first part's: its columns)
    n_train: int | None = None  # images the fit learnt from (None: the pair's all)
    basis: tuple[np.ndarray | None, ...] = ()  # per part: (m, 32, 64) images of what the
    # method removed or learned (TensorBoard tag basis/<report.basis_name>)
    warning: str | None = None  # one line for the run log (the report's, degenerate)
    start_db: jax.Array | None = None  # a trained fit that kept a later epoch: its start's
    start_query: jax.Array | None = None  # descriptors (one part), for the paired comparison


def timed(fn: Callable, *args):
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - start


# Images a method encodes at once; more are encoded a block at a time (``encode_rows``).
ENCODE_BLOCK_ROWS = 4096


def encode_rows(encode: Callable, images, block_rows: int = ENCODE_BLOCK_ROWS):
    """``encode(images)``, for more than ``block_rows`` images a block at a time into one
    aligned host array (``vpr_jax.host_arrays``: the matcher reads it in place). An encoder's
    intermediates are the size of its input, so encoding a long route in one call would hold
    them beside its descriptors. Fewer images (the paper protocol's 3,569) are encoded in
    one call."""
    n = len(images)
    if n <= block_rows:
        return encode(images)
    first = np.asarray(encode(images[:block_rows]))
    out = host_arrays.empty((n, *first.shape[1:]), first.dtype)
    out[:block_rows] = first
    for start in range(block_rows, n, block_rows):
        out[start : start + block_rows] = np.asarray(encode(images[start : start + block_rows]))
    return out


def encode_pair(encode: Callable, pair: PairData) -> tuple[jax.Array, jax.Array, float]:
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


def as_images(vectors, shape: tuple[int, ...]) -> np.ndarray | None:
    """Rows of pixels as images of ``shape``; None for rows of other values (a method that
    sees gradient histograms, or a combination of inputs, has no basis images)."""
    vectors = np.asarray(vectors)
    if vectors.ndim != 2 or vectors.shape[1] != int(np.prod(shape)):
        return None
    return vectors.reshape(len(vectors), *shape)


@jax.jit
def _row_norms(desc):
    return jnp.sqrt(jnp.sum(desc * desc, axis=1))


@jax.jit
def _largest_gap(desc, inv, rows, i, inv_i):
    """The largest distance of a unit row (``desc * inv``; zero rows have ``inv`` 0 and
    count 0) from the unit row ``rows[i] * inv_i``: all point one way when it is tiny. The
    row is taken here, not by an indexing of its own (two more programs to compile for
    every shape of descriptors)."""
    first = rows[i].astype(jnp.float32) * inv_i
    unit = desc * inv[:, None]  # fused into the sum: never written out
    gap = jnp.sqrt(jnp.sum((unit - first) ** 2, axis=1))  # cosine to first = 1 - gap^2 / 2
    return jnp.max(jnp.where(inv == 0.0, 0.0, gap))


class Degenerate(NamedTuple):
    """What makes cosine matching arbitrary (``degenerate``)."""

    zero: np.ndarray  # bool per row: the row is zero
    one_way: bool  # every other row points the same way


def degenerate_rows(desc: Float[Array, "n d"]) -> tuple[int, bool]:
    """(how many rows are zero, whether all the other rows point the same way)."""
    found = degenerate(desc)
    return int(found.zero.sum()), found.one_way


def degenerate(desc: Float[Array, "n d"]) -> Degenerate:
    """Which rows are zero, and whether all the other rows point the same way.

    A zero row scores 0 against everything (norm at most 1e-6 of the largest row's, or 0);
    rows that all point one way (pairwise cosine above 1 - 5e-7) score the same against
    every query. Two passes over blocks of ``ENCODE_BLOCK_ROWS`` rows (norms, then each
    row's distance from the first nonzero one), so nothing the size of the descriptors is
    allocated, as one program over the whole database would on its first run.
    """
    rows = [slice(s, s + ENCODE_BLOCK_ROWS) for s in range(0, len(desc), ENCODE_BLOCK_ROWS)]
    norms = np.concatenate([np.asarray(_row_norms(desc[r])) for r in rows] or [np.zeros(0)])
    zero = norms <= max(1e-6 * norms.max(initial=0.0), _EPS)
    inv = np.where(zero, 0.0, 1.0 / np.maximum(norms, _EPS)).astype(np.float32)
    if zero.all():
        return Degenerate(zero, False)
    i = int(np.argmin(zero))  # the first nonzero row
    # host rows (outside descriptors): hand over that row alone, not all of them
    source, at = (desc[i][None], 0) if isinstance(desc, np.ndarray) else (desc, i)
    gap = max(float(_largest_gap(desc[r], inv[r], source, at, inv[i])) for r in rows)
    return Degenerate(zero, gap <= 1e-3 and int((~zero).sum()) > 1)
