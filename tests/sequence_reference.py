"""A straightforward numpy sequence search, written the way openSeqSLAM writes it (a loop
over queries, then over velocities and steps), from the definition in
``vpr_jax.evaluation.sequence``'s docstring: the oracle of tests/test_sequence.py and the
peer of benchmarks/bench_sequence.py.
Shares only the definition of the trajectories' steps and integer offsets with the code
under test.
"""

from __future__ import annotations

import numpy as np

from vpr_jax.evaluation.sequence import (
    DEFAULT_VELOCITIES,
    stretch_ids,
    trajectory_offsets,
    trajectory_steps,
)


def enhance(diff: np.ndarray, window: int) -> np.ndarray:
    """Each row's z-scores against its database window [i - R//2, i + R//2], float64."""
    diff = np.asarray(diff, np.float64)
    if window == 0:
        return diff
    half, n = window // 2, diff.shape[1]
    out = np.zeros_like(diff)
    for i in range(n):
        win = diff[:, max(0, i - half) : min(n, i + half + 1)]
        mean, std = win.mean(axis=1), win.std(axis=1)
        flat = std <= 1e-6
        out[:, i] = np.where(flat, 0.0, (diff[:, i] - mean) / np.where(flat, 1.0, std))
    return out


def sequence_top_k_numpy(
    similarity,
    ds=10,
    *,
    query_ids=None,
    db_ids=None,
    vels=DEFAULT_VELOCITIES,
    contrast_window=10,
    uniqueness_window=10,
    k=10,
):
    sim = np.asarray(similarity, np.float64)
    nq, n_db = sim.shape
    k = min(k, n_db)
    if ds == 1:
        order = np.argsort(-sim, axis=1, kind="stable")[:, :k]
        return np.take_along_axis(sim, order, axis=1), order
    enhanced = enhance(1.0 - sim, contrast_window)
    q_stretch = stretch_ids(np.arange(nq) if query_ids is None else query_ids)
    d_stretch = stretch_ids(np.arange(n_db) if db_ids is None else db_ids)
    steps = trajectory_steps(ds)
    offsets = trajectory_offsets(ds, tuple(vels))
    columns = np.arange(n_db)
    scores = np.zeros((nq, k))
    indices = np.zeros((nq, k), np.int64)
    for q in range(nq):
        cost = np.full(n_db, np.inf)
        for vel in offsets:
            total = np.zeros(n_db)
            for step, s in zip(steps, vel, strict=True):
                row = q + step
                if not (0 <= row < nq and q_stretch[row] == q_stretch[q]):
                    continue
                target = columns + s
                ok = (target >= 0) & (target < n_db)
                ok[ok] &= d_stretch[target[ok]] == d_stretch[columns[ok]]
                total[ok] += enhanced[row, target[ok]]
                total[~ok] += enhanced[row].mean()
            cost = np.minimum(cost, total)
        order = np.argsort(cost, kind="stable")[:k]
        far = np.abs(columns - order[0]) > uniqueness_window // 2
        second = cost[far].min() if far.any() else cost[order[0]]
        scores[q] = (second - cost[order]) / ds
        indices[q] = order
    return scores, indices
