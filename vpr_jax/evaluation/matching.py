"""Matching: cosine similarity of query descriptors against the database, with a running top-K.

Similarity matrices here are (n_queries, n_db): row q holds query q's scores against every
database image. That is the transpose of VPR_Tutorial's S, which is (n_db, n_queries).

``top_k_matches`` walks the database in fixed-size blocks and keeps only the K best scores per
query, so memory is O(n_queries * (K + block)) whatever the route length.

Descriptors can be scored on several *suffixes* at once: with ``starts=(0, 5, 10)`` the score
for start s uses only features s, s+1, ... of each descriptor. On PCA coefficients this is
change removal for every removed-PC count from one pass: the dot product over a suffix is a
sum of the block products of the segments it covers, so all counts cost one full product.

Each block's K best are taken in two levels, exact (``block_top_k``): the block's columns
are dealt into W lanes, one fused pass takes every lane's maximum, the K lanes with the
largest maxima hold the block's K best, and only their columns are ranked. On a CPU that is
one read of the scores instead of ``lax.top_k``'s pass per row (docs/speed.md has the
breakdown), and the scores are never scaled as a whole: the database norms are folded into
the lane pass and only the candidates are scored in full.

Precision: the products are float32 on every device unless ``precision="default"`` (the
``matching.precision`` key) allows the platform's fastest, TF32 on recent NVIDIA GPUs
(``vpr_jax.precision``): a faster product whose inputs are rounded to 10 bits of mantissa,
so close scores can swap (docs/speed.md, "Any device").
"""

from __future__ import annotations

import functools
import math
import os
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as P
from jaxtyping import Array, Float, Int

from vpr_jax import sharding
from vpr_jax.precision import f32_matmul, matching_precision
from vpr_jax.sharding import AXIS

_EPS = 1e-12
FALLBACK_CACHE_BYTES = 8 << 20  # where the last-level cache's size cannot be read
MIN_QUERY_ROWS_PER_CORE = 64  # a query block gives every core's product tiles this many rows


@functools.cache
def last_level_cache_bytes() -> int:
    """The largest CPU cache this process can read the size of (Linux sysfs), else
    ``FALLBACK_CACHE_BYTES``."""
    sizes = []
    for path in Path("/sys/devices/system/cpu/cpu0/cache").glob("index*/size"):
        text = path.read_text().strip() if path.is_file() else ""
        unit = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}.get(text[-1:], 1)
        digits = text.rstrip("KMG")
        if digits.isdigit():
            sizes.append(int(digits) * unit)
    return max(sizes, default=FALLBACK_CACHE_BYTES)


def score_budget() -> int:
    """Floats of one matching step's scores when blocks are automatic: a quarter of the
    last-level cache, so a block's scores stay there between the product that writes them
    and the ranking passes that read them; one block of every query would instead write its
    scores to fresh memory on each call (docs/speed.md, "Matching")."""
    return last_level_cache_bytes() // 4 // 4


def live_blocks(starts: tuple[int, ...]) -> int:
    """Score blocks a matching step holds at once: the product's, and with several starts
    also the running sum and the segment product being added to it (``suffix_dots``); the
    scores of the starts are ranked one at a time, never stacked."""
    return 1 if len(starts) == 1 else 3


def even_query_blocks(nq: int, starts: tuple[int, ...], block_size: int) -> int:
    """The automatic query block: ``nq`` queries split evenly into as few blocks as keep
    each within the larger of ``score_budget()`` floats a step and
    ``MIN_QUERY_ROWS_PER_CORE`` rows per core. Even, because the last block is padded to
    the others: 894 queries in blocks of up to 782 rows are two of 447, not 782 and 112
    padded to 782."""
    floor = MIN_QUERY_ROWS_PER_CORE * (os.cpu_count() or 1)
    largest = max(floor, score_budget() // (live_blocks(starts) * block_size))
    n_blocks = -(-nq // largest)  # ceiling division
    return -(-nq // n_blocks)


def lane_width(block: int, k: int) -> int:
    """W for ``block_top_k``: the power of two nearest below sqrt(block x k), which balances
    the ranking of the W lane maxima against that of the K x block / W candidates; 0 when
    the block is too small for two levels to pay (W <= K)."""
    w = 1 << int(math.log2(math.sqrt(block * k))) if block * k >= 1 else 0
    return w if w > k else 0


def l2_normalize(x: Float[Array, "n d"], axis: int = -1) -> Float[Array, "n d"]:
    norm = jnp.sqrt(jnp.sum(x * x, axis=axis, keepdims=True))
    return x / jnp.maximum(norm, _EPS)


@jax.jit
def cosine_similarity(
    query_desc: Float[Array, "nq d"], db_desc: Float[Array, "ndb d"]
) -> Float[Array, "nq ndb"]:
    """Cosine similarity, (n_queries, n_db), at float32. A zero descriptor scores 0 against
    everything."""
    return f32_matmul(l2_normalize(query_desc), l2_normalize(db_desc).T)


class Suffixes(NamedTuple):
    """Descriptors cut at the suffix starts, as the matcher reads them: ``segments[i]`` the
    features ``[starts[i]:starts[i + 1]]`` of every row (the last runs to the end), and
    ``inv_norms[i]`` 1 / the norm of the features ``[starts[i]:]``."""

    segments: tuple[Float[Array, "n _"], ...]
    inv_norms: tuple[Float[Array, " n"], ...]


def suffixes(x: Float[Array, "n d"], starts: tuple[int, ...]) -> Suffixes:
    """``x`` cut at ``starts`` (``Suffixes``). A column slice is a copy, so the matcher cuts
    each side once, never once per block it meets."""
    bounds = (*starts, x.shape[1])
    segments = tuple(x[:, a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True))
    sq, inv_norms = 0.0, []
    for seg in reversed(segments):
        sq = sq + jnp.sum(seg * seg, axis=1)
        inv_norms.append(1.0 / jnp.maximum(jnp.sqrt(sq), _EPS))
    return Suffixes(segments, tuple(reversed(inv_norms)))


def suffix_dots(query: Suffixes, db: Suffixes, precision: str = "float32"):
    """Yield (start index, dot product on features [start:], 1 / query norms, 1 / database
    norms) for every start, last start first; the cosine is ``dot * inv_q[:, None] *
    inv_db[None, :]``. ``precision``: the products' (``matching.precision``).

    The dot product over a suffix is the sum of the segment products it covers, so walking
    the starts backwards adds one thin segment product at a time: every start together costs
    one full product plus one elementwise pass each.
    """
    dot, product = 0.0, matching_precision(precision)
    for i in reversed(range(len(query.segments))):
        dot = dot + jnp.matmul(query.segments[i], db.segments[i].T, precision=product)
        yield i, dot, query.inv_norms[i], db.inv_norms[i]


def block_top_k(
    dot: Float[Array, "nq blk"],
    inv_q: Float[Array, " nq"],
    inv_db: Float[Array, " blk"],
    valid,
    k: int,
) -> tuple[Float[Array, "nq k"], Int[Array, "nq k"]]:
    """The K largest cosines ``dot * inv_q[:, None] * inv_db`` of every row and their
    columns, best first; columns where ``valid`` is False never count. Ties keep the lower
    column, as ``lax.top_k`` does, except a tie at the K-th value across lanes (where the
    lane of the larger maximum wins).

    Two levels when the block is large enough (``lane_width``): column c < W x (block // W)
    goes to lane c mod W (the few columns past the last whole group are candidates as they
    are), one pass takes each lane's maximum, and the K best of the row lie in the K lanes
    with the largest maxima (a value outside them is beaten by K lane maxima, each a
    different column), so only those K x block / W columns are gathered and ranked. The
    lane pass leaves out ``inv_q``, which scales a row alike; the candidates are scored in
    full, to the bit as the one-level path scores them.
    """
    nq, block = dot.shape
    w = lane_width(block, k)
    g = block // w if w else 0
    if g * w < k:
        return jax.lax.top_k(jnp.where(valid, dot * inv_q[:, None] * inv_db, -jnp.inf), k)
    # Written in the (row, group, lane) layout so that the scaling fuses into the reduction:
    # scaling first and reshaping after would write the scaled block out in full.
    m = g * w  # the columns dealt into lanes; the last block % W are ranked on their own
    main, inv_main = dot[:, :m].reshape(nq, g, w), inv_db[:m].reshape(g, w)
    scaled = jnp.where(valid[:m].reshape(g, w), main * inv_main, -jnp.inf)
    lanes = jnp.sort(jax.lax.top_k(scaled.max(axis=1), k)[1], axis=1)  # (nq, k), ascending
    # Candidates in column order (group-major, lanes ascending, then the leftover columns),
    # so the stable top_k below keeps the lower column of a tie.
    cols = (jnp.arange(g, dtype=jnp.int32)[None, :, None] * w + lanes[:, None, :]).reshape(nq, -1)
    rest = jnp.broadcast_to(jnp.arange(m, block, dtype=jnp.int32), (nq, block - m))
    cols = jnp.concatenate([cols, rest], axis=1)
    cand = jnp.take_along_axis(dot, cols, axis=1) * inv_q[:, None] * inv_db[cols]
    best, pos = jax.lax.top_k(jnp.where(valid[cols], cand, -jnp.inf), k)
    return best, jnp.take_along_axis(cols, pos, axis=1)


def _block_matches(
    queries: Suffixes, block, offset, n_db, k: int, starts: tuple[int, ...], precision: str
):
    """Every query block's K best of one database block (rows from ``offset`` on; those
    past ``n_db`` are padding): (query blocks, starts, query block rows, k)."""
    valid = offset + jnp.arange(block.shape[0]) < n_db
    db = suffixes(block, starts)

    def query_block(query: Suffixes):
        scores, idx = [None] * len(starts), [None] * len(starts)
        for i, dot, inv_q, inv_db in suffix_dots(query, db, precision):
            # Top-K of the block for this start right away: the (qb, block) scores are never
            # stacked over starts, which keeps memory traffic to one pass per start.
            scores[i], pos = block_top_k(dot, inv_q, inv_db, valid, k)
            idx[i] = offset + pos.astype(jnp.int32)
        return jnp.stack(scores), jnp.stack(idx)

    return jax.lax.map(query_block, queries)


@functools.partial(jax.jit, static_argnames=("k", "block_size", "starts", "precision"))
def _top_k_query_blocks(
    queries: Suffixes,
    db_desc: Float[Array, "ndb d"],
    n_db: Int[Array, ""],
    k: int,
    block_size: int,
    starts: tuple[int, ...],
    precision: str,
    first_index: Int[Array, ""] = 0,
):
    """Running top-K of every query block (``queries``: ``suffixes`` of each block, stacked)
    over the database's rows a block at a time: (query blocks, starts, query block rows,
    k). ``first_index`` is the global index of the database's first row (a device's part of
    a sharded database starts past 0).

    The database is the outer loop: each of its blocks is read in place (only a last
    partial block is padded, because padding the whole database would copy it), cut into
    its suffix segments once, and scored against every query block in turn (``lax.map``:
    one query block's scores in memory at a time). Cutting inside the query loop copied
    the database's segments once per query block (docs/speed.md, "The removed-PC sweep").
    One compiled program for all of it: a Python loop over query blocks would compile again
    for a shorter last block."""
    n_starts = len(starts)

    def merged(best, new):
        # Earlier blocks come first and top_k is stable, so ties keep the lowest database
        # index, as argmax would.
        scores = jnp.concatenate([best[0], new[0]], axis=-1)
        return _merge_top_k(scores, jnp.concatenate([best[1], new[1]], axis=-1), k)

    def whole_block(best, i):
        block = jax.lax.dynamic_slice_in_dim(db_desc, i * block_size, block_size)
        offset = first_index + i * block_size
        new = _block_matches(queries, block, offset, n_db, k, starts, precision)
        return merged(best, new), None

    n_whole, lists = db_desc.shape[0] // block_size, []
    if n_whole == 1:  # its lists are the running ones: never merged with empty lists
        first = db_desc[:block_size]
        lists.append(_block_matches(queries, first, first_index, n_db, k, starts, precision))
    elif n_whole:  # empty lists, then every whole block in one loop (its body traced once)
        nb, qb = queries.inv_norms[0].shape
        empty = (
            jnp.full((nb, n_starts, qb, k), -jnp.inf, db_desc.dtype),
            jnp.zeros((nb, n_starts, qb, k), jnp.int32),
        )
        lists.append(jax.lax.scan(whole_block, empty, jnp.arange(n_whole, dtype=jnp.int32))[0])
    if db_desc.shape[0] % block_size:  # static: the tail, padded to a whole block
        tail = _blocks(db_desc[n_whole * block_size :], block_size)[0]
        offset = first_index + n_whole * block_size
        lists.append(_block_matches(queries, tail, offset, n_db, k, starts, precision))
    return merged(*lists) if len(lists) == 2 else lists[0]


@functools.partial(
    jax.jit, static_argnames=("k", "block_size", "query_block_size", "starts", "precision")
)
def _top_k_unpadded(query_desc, db_desc, k, block_size, query_block_size, starts, precision):
    """``_top_k_query_blocks`` on the descriptors as they are: the queries cut into blocks
    inside the compiled program (``_query_blocks``), the database read in place. Padding
    outside would take three copies of the database: the padded array, its reshape, and
    jnp.asarray's own."""
    return _top_k_query_blocks(
        _query_blocks(query_desc, query_block_size, starts),
        db_desc,
        db_desc.shape[0],
        k,
        block_size,
        starts,
        precision,
    )


def _query_blocks(query_desc, size: int, starts: tuple[int, ...]) -> Suffixes:
    """The queries cut into their suffix segments, each padded to whole blocks of ``size``
    rows and stacked (one copy: the cut and the padding fuse)."""
    return jax.tree.map(lambda x: _blocks(x, size), suffixes(query_desc, starts))


def _blocks(x, size: int):
    """Rows of ``x`` (numpy or JAX) zero-padded to whole blocks: (blocks, size, ...)."""
    return sharding.pad_rows(x, size).reshape(-1, size, *x.shape[1:])


def _as_input(x, mesh: Mesh | None):
    """float32 descriptors where the matcher reads them: host numpy for a mesh (``put``
    hands each device its part), else on the device, in place where it can."""
    return np.asarray(x, np.float32) if mesh is not None else sharding.on_device(x)


def _merge_top_k(scores, indices, k: int):
    """The K best of longer lists (last axis); ties keep the earlier entry (stable top_k)."""
    top, pos = jax.lax.top_k(scores, k)
    return top, jnp.take_along_axis(indices, pos, axis=-1)


@functools.lru_cache(maxsize=16)
def _sharded_top_k(
    mesh, k: int, block_size: int, query_block_size: int, starts: tuple[int, ...], precision: str
):
    """``_top_k_query_blocks`` with the database blocks split across ``mesh``: every device
    keeps the K best of its own part, then the K-lists are gathered (in device order, so in
    database order) and merged. Queries are replicated."""

    def local(query_desc, db_rows, n_db):
        first = jax.lax.axis_index(AXIS) * db_rows.shape[0]
        queries = _query_blocks(query_desc, query_block_size, starts)
        scores, idx = _top_k_query_blocks(
            queries, db_rows, n_db, k, block_size, starts, precision, first
        )  # (query blocks, starts, block, k)
        scores = jax.lax.all_gather(scores, AXIS, axis=3, tiled=True)
        idx = jax.lax.all_gather(idx, AXIS, axis=3, tiled=True)
        return _merge_top_k(scores, idx, k)

    return jax.jit(
        jax.shard_map(
            local, mesh=mesh, in_specs=(P(), P(AXIS), P()), out_specs=(P(), P()), check_vma=False
        )
    )


def top_k_matches(
    query_desc: Float[Array, "nq d"],
    db_desc: Float[Array, "ndb d"],
    k: int = 10,
    *,
    starts: tuple[int, ...] = (0,),
    block_size: int = 4096,
    query_block_size: int | None = None,
    mesh: Mesh | None = None,
    precision: str = "float32",
) -> tuple[Float[np.ndarray, "s nq k"], Int[np.ndarray, "s nq k"]]:
    """The K best database matches of every query, best first, for every suffix start.

    Returns numpy (scores, indices), each (len(starts), n_queries, min(k, n_db)); indices
    point into ``db_desc``. A step holds ``live_blocks(starts)`` x query_block_size x
    block_size scores, independent of n_db; query blocks are ``even_query_blocks`` unless
    given. Blocks only split the work: the database is read in whole blocks in place and
    its last partial block padded to a whole one, never to the ranking's lanes, because a
    product's rounding changes with its padded width and the scores would move by an ulp.

    With a ``mesh`` the database is split across its devices (``vpr_jax.sharding``): each
    scores its part in the same blocks, and the per-device K-lists are merged.
    ``precision``: the products' (``matching.precision``): ``"float32"``, or ``"default"``
    for the platform's fastest (TF32 on recent NVIDIA GPUs).
    """
    matching_precision(precision)  # an unknown name is refused before anything compiles
    # Host arrays for a mesh (put() hands each device its part); else on the device.
    query_desc, db_desc = (_as_input(x, mesh) for x in (query_desc, db_desc))
    n_db, d = db_desc.shape
    starts = tuple(int(s) for s in starts)
    if not starts or any(b <= a for a, b in zip(starts, starts[1:], strict=False)):
        raise ValueError(f"starts must be strictly increasing, got {starts}")
    if starts[0] < 0 or starts[-1] >= d:
        raise ValueError(f"starts {starts} leave no feature of {d}")
    k = min(k, n_db)
    n_devices = sharding.mesh_size(mesh)
    # No device scores only padding, but a block holds at least k rows: a small database
    # split over many devices pads each device's block (padding scores -inf, never kept).
    block_size = max(min(block_size, -(-n_db // n_devices)), k)
    nq = query_desc.shape[0]
    if query_block_size is None:
        query_block_size = even_query_blocks(nq, starts, block_size)
    query_block_size = min(query_block_size, nq)
    if mesh is None:
        scores, indices = _top_k_unpadded(
            query_desc, db_desc, k, block_size, query_block_size, starts, precision
        )
    else:
        # Every device gets whole blocks: the database is padded to a multiple of all of them.
        db_rows = sharding.pad_rows(db_desc, n_devices * block_size)  # whole blocks each
        program = _sharded_top_k(mesh, k, block_size, query_block_size, starts, precision)
        scores, indices = program(
            sharding.put(query_desc, mesh, P()),
            sharding.put_rows(db_rows, mesh),
            jnp.int32(n_db),
        )
    # (query blocks, starts, block, k) -> (starts, queries, k), padding queries dropped
    scores = np.asarray(scores).transpose(1, 0, 2, 3).reshape(len(starts), -1, k)[:, :nq]
    indices = np.asarray(indices).transpose(1, 0, 2, 3).reshape(len(starts), -1, k)[:, :nq]
    return scores, indices
