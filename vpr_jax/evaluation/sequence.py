"""Sequence matching (SeqSLAM, Milford & Wyeth 2012) over any similarity matrix.

One image across seasons is ambiguous; a stretch of them rarely is. For query q and database
frame i the search scores straight lines through the difference matrix, centred on (q, i):
query q + k is paired with database frame i + round(v k) for the ds steps
k = -(ds // 2), ..., ds - ds // 2 - 1 and every velocity v (database frames per query frame).

1. Differences D = 1 - similarity (n_queries, n_db); for cosine that is 1 - cos.
2. Local contrast enhancement along the database axis: each D[q, i] becomes a z-score
   against the window of database frames i - R // 2 ... i + R // 2 of the same query
   (R = ``contrast_window``; 0 leaves D as it is). Frames that look like everything lose
   their pull; a frame clearly closer than its neighbours stands out.
3. A trajectory's cost is the sum of the enhanced differences along it. Steps that cross a
   break in frame numbers (the boundary between test sections, a stretch not recorded) or
   leave the queries are skipped (alike for every candidate of the query); a step that
   leaves the database counts as the query row's average, so no candidate gains from
   running off the end. The cost of (q, i) is the smallest over velocities.
4. Each query keeps its K cheapest database frames. Its uniqueness is how much the best
   trajectory beats the best one more than ``uniqueness_window // 2`` frames away from it;
   the score of candidate j is (that second-best cost - cost_j) / ds, so the best match's
   score is the uniqueness margin (per step, in units of the local standard deviation),
   which the precision-recall curve thresholds, and scores fall with rank.

ds = 1 is single-image matching: the similarity's own top K, no enhancement, so a sweep's
ds axis isolates what the sequence adds.

Everything runs in query blocks (``lax.map`` in one compiled program): a block of B queries
needs its B + ds - 1 rows of the similarity (the ds - 1 extra rows are the trajectories'
halo), so memory is O(B n_db) whatever the route length. ``sequence_top_k`` takes a
similarity matrix; ``sequence_top_k_cosine`` takes descriptors and computes each block's
cosine rows itself, never holding the full matrix.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from vpr_jax.evaluation.matching import l2_normalize, top_k_matches
from vpr_jax.precision import matching_precision

DEFAULT_VELOCITIES = (0.8, 0.9, 1.0, 1.1, 1.2)
SCORE_BUDGET = 1 << 20  # floats of one (block, n_db) array when blocks are automatic
_EPS = 1e-6  # a window whose differences spread less than this is left flat (z = 0)


def velocities(v_min: float, v_max: float, v_step: float) -> tuple[float, ...]:
    """v_min, v_min + v_step, ... up to v_max (inclusive, to 1e-9), rounded to 6 decimals."""
    if v_step <= 0 or v_min <= 0 or v_max < v_min:
        raise ValueError(
            f"velocities need 0 < v_min <= v_max and v_step > 0, got {v_min}, {v_max}, {v_step}"
        )
    n = int(np.floor((v_max - v_min) / v_step + 1e-9)) + 1
    return tuple(round(v_min + i * v_step, 6) for i in range(n))


def trajectory_steps(ds: int) -> np.ndarray:
    """The query offsets k of a trajectory of length ds, centred: -(ds // 2) ... ."""
    return np.arange(-(ds // 2), ds - ds // 2)


def trajectory_offsets(ds: int, vels: tuple[float, ...]) -> tuple[tuple[int, ...], ...]:
    """Database offset round(v k) of every step k, per velocity (halves round up)."""
    k = trajectory_steps(ds)
    return tuple(tuple(int(s) for s in np.floor(np.float64(v) * k + 0.5)) for v in vels)


def stretch_ids(frame_ids: np.ndarray) -> np.ndarray:
    """(N,) int32: which unbroken stretch of the route each frame belongs to.

    A new stretch starts where frame numbers fall back or jump by more than twice the usual
    step (the median gap): the boundary between test sections, or a stretch left out. A
    trajectory never crosses from one stretch into another.
    """
    ids = np.asarray(frame_ids, dtype=np.int64)
    if len(ids) < 2:
        return np.zeros(len(ids), np.int32)
    gaps = np.diff(ids)
    positive = gaps[gaps > 0]
    step = np.median(positive) if len(positive) else 1
    breaks = (gaps <= 0) | (gaps > 2 * step)
    return np.concatenate([[0], np.cumsum(breaks)]).astype(np.int32)


def _enhance(diff: Float[Array, "r n"], window: int) -> Float[Array, "r n"]:
    """Z-score of every difference against its database window (population std)."""
    if window == 0:
        return diff
    half = window // 2
    # Centred rows keep the windowed sums of squares small, so float32 loses nothing.
    diff = diff - jnp.mean(diff, axis=1, keepdims=True)

    def window_sum(x):
        return jax.lax.reduce_window(
            x, 0.0, jax.lax.add, (1, 2 * half + 1), (1, 1), ((0, 0), (half, half))
        )

    # Frames in each window (fewer at the ends), elementwise: a windowed sum of a constant
    # would be constant-folded at compile time, which grows slow with the route's length.
    n, at = diff.shape[1], jnp.arange(diff.shape[1])
    count = (jnp.minimum(at + half, n - 1) - jnp.maximum(at - half, 0) + 1).astype(diff.dtype)
    mean = window_sum(diff) / count
    var = jnp.maximum(window_sum(diff * diff) / count - mean * mean, 0.0)
    std = jnp.sqrt(var)
    return jnp.where(std > _EPS, (diff - mean) / jnp.maximum(std, _EPS), 0.0)


def _search_block(sim_rows, row_stretch, db_stretch, *, ds, offsets, window, unique, k):
    """Top-K trajectories of one query block.

    sim_rows: (B + ds - 1, n) similarity rows, row j + t is query t's step j (query t's own
    row is t + ds // 2). row_stretch: (B + ds - 1,) stretch of each row, -1 for padding.
    """
    n_rows, n_db = sim_rows.shape
    b = n_rows - ds + 1
    enhanced = _enhance(1.0 - sim_rows, window)
    row_mean = jnp.mean(enhanced, axis=1, keepdims=True)
    own = row_stretch[ds // 2 : ds // 2 + b]
    # Padding the database axis once turns every step into a static slice, which XLA fuses
    # into the sum instead of materialising a shifted copy per step.
    reach = max(abs(s) for vel in offsets for s in vel)
    padded = jnp.pad(enhanced, ((0, 0), (reach, reach)))
    stretch = jnp.pad(db_stretch, (reach, reach), constant_values=-1)
    # Step j is usable for query t when row j + t is a query of t's own stretch; a database
    # shift s when frame i + s is in frame i's stretch. Both are shared across velocities.
    query_ok = [((row_stretch[j : j + b] == own) & (own >= 0))[:, None] for j in range(ds)]
    db_ok = {
        s: (stretch[reach + s : reach + s + n_db] == db_stretch)[None, :]
        for s in {s for vel in offsets for s in vel}
    }
    cost = None
    for vel in offsets:
        total = jnp.zeros((b, n_db), enhanced.dtype)
        for j, s in enumerate(vel):
            step = padded[j : j + b, reach + s : reach + s + n_db]
            # A step past the database counts as the query row's average difference.
            step = jnp.where(db_ok[s], step, row_mean[j : j + b])
            total = total + jnp.where(query_ok[j], step, 0)
        cost = total if cost is None else jnp.minimum(cost, total)
    top, idx = _smallest_k(cost, k)
    far = jnp.abs(jnp.arange(n_db)[None, :] - idx[:, :1]) > unique // 2
    second = jnp.min(jnp.where(far, cost, jnp.inf), axis=1, keepdims=True)
    second = jnp.where(jnp.isfinite(second), second, top[:, :1])  # nothing outside
    return (second - top) / ds, idx


def _smallest_k(cost: Float[Array, "b n"], k: int) -> tuple[Array, Array]:
    """The k smallest entries of every row, ascending, ties to the lower index (like a
    stable sort). k passes of argmin: ``lax.top_k`` here compiles, on the CPU, to a full
    sort of every row, because the costs have a second consumer."""
    rows = jnp.arange(cost.shape[0])
    values, indices = [], []
    for _ in range(k):
        i = jnp.argmin(cost, axis=1)
        values.append(cost[rows, i])
        indices.append(i)
        cost = cost.at[rows, i].set(jnp.inf)
    return jnp.stack(values, axis=1), jnp.stack(indices, axis=1).astype(jnp.int32)


@functools.partial(
    jax.jit, static_argnames=("ds", "offsets", "window", "unique", "k", "block", "precision")
)
def _sequence_blocks(
    rows, db, q_stretch, db_stretch, *, ds, offsets, window, unique, k, block, precision
):
    """Every query block in turn. ``rows`` are similarity rows (``db`` None) or query
    descriptors whose cosine rows against ``db`` each block computes for itself, at
    ``precision`` (``matching.precision``)."""
    nq = rows.shape[0]
    n_blocks = -(-nq // block)
    before, after = ds // 2, n_blocks * block - nq + ds - ds // 2 - 1
    if db is not None:
        rows, db = l2_normalize(rows), l2_normalize(db)
    rows = jnp.pad(rows, ((before, after), (0, 0)))
    stretch = jnp.pad(q_stretch, (before, after), constant_values=-1)

    def one(start):
        sim = jax.lax.dynamic_slice_in_dim(rows, start, block + ds - 1)
        if db is not None:
            sim = jnp.matmul(sim, db.T, precision=matching_precision(precision))
        own = jax.lax.dynamic_slice_in_dim(stretch, start, block + ds - 1)
        return _search_block(
            sim, own, db_stretch, ds=ds, offsets=offsets, window=window, unique=unique, k=k
        )

    scores, idx = jax.lax.map(one, jnp.arange(n_blocks) * block)
    return scores.reshape(-1, k)[:nq], idx.reshape(-1, k)[:nq]


def sequence_top_k(
    similarity: Float[Array, "nq ndb"],
    ds: int = 10,
    *,
    query_ids: Int[np.ndarray, " nq"] | None = None,
    db_ids: Int[np.ndarray, " ndb"] | None = None,
    vels: tuple[float, ...] = DEFAULT_VELOCITIES,
    contrast_window: int = 10,
    uniqueness_window: int = 10,
    k: int = 10,
    query_block_size: int | None = None,
) -> tuple[Float[np.ndarray, "nq k"], Int[np.ndarray, "nq k"]]:
    """The K best database frames of every query by sequence matching, best first.

    ``similarity`` is (n_queries, n_db), higher = more alike, queries and database each in
    route order; ``query_ids`` / ``db_ids`` (frame numbers) mark where stretches break
    (default: one unbroken stretch each). Returns numpy (scores, indices), (n_queries,
    min(k, n_db)); ds = 1 returns the similarity's own top K.
    """
    return _search(
        jnp.asarray(similarity, jnp.float32),
        None,
        ds,
        query_ids,
        db_ids,
        vels,
        contrast_window,
        uniqueness_window,
        k,
        query_block_size,
    )


def sequence_top_k_cosine(
    query_desc: Float[Array, "nq d"], db_desc: Float[Array, "ndb d"], ds: int = 10, **options
) -> tuple[Float[np.ndarray, "nq k"], Int[np.ndarray, "nq k"]]:
    """``sequence_top_k`` of the cosine similarity of descriptors (keyword options as
    there, and ``precision``: the products', as ``matching.top_k_matches`` takes it),
    computed block by block: the full matrix is never held. ds = 1 is
    ``matching.top_k_matches``."""
    return _search(
        jnp.asarray(query_desc, jnp.float32), jnp.asarray(db_desc, jnp.float32), ds, **options
    )


def _search(
    rows,
    db,
    ds,
    query_ids=None,
    db_ids=None,
    vels=DEFAULT_VELOCITIES,
    contrast_window=10,
    uniqueness_window=10,
    k=10,
    query_block_size=None,
    precision="float32",
):
    """Similarity rows (``db`` None) or query descriptors against ``db`` descriptors."""
    nq, n_db = rows.shape[0], rows.shape[1] if db is None else db.shape[0]
    if ds < 1:
        raise ValueError(f"ds={ds}: a sequence needs at least one image")
    if contrast_window < 0 or uniqueness_window < 0:
        raise ValueError("contrast_window and uniqueness_window must be >= 0")
    q_ids = np.arange(nq) if query_ids is None else np.asarray(query_ids)
    d_ids = np.arange(n_db) if db_ids is None else np.asarray(db_ids)
    if q_ids.shape != (nq,) or d_ids.shape != (n_db,):
        raise ValueError(
            f"query_ids and db_ids must have {nq} and {n_db} entries, got "
            f"{q_ids.shape} and {d_ids.shape}"
        )
    k = min(k, n_db)
    if ds == 1:
        if db is None:
            scores, idx = jax.lax.top_k(rows, k)
            return np.asarray(scores), np.asarray(idx)
        scores, idx = top_k_matches(rows, db, k, precision=precision)
        return scores[0], idx[0]
    block = query_block_size or max(1, SCORE_BUDGET // max(n_db, 1))
    scores, idx = _sequence_blocks(
        rows,
        db,
        jnp.asarray(stretch_ids(q_ids)),
        jnp.asarray(stretch_ids(d_ids)),
        ds=ds,
        offsets=trajectory_offsets(ds, tuple(vels)),
        window=contrast_window,
        unique=uniqueness_window,
        k=k,
        block=min(block, nq),
        precision=precision,
    )
    return np.asarray(scores), np.asarray(idx)
