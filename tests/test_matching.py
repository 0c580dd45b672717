"""Blockwise running top-K against numpy brute force."""

import numpy as np
import pytest

from tests.conftest import numpy_cosine as _numpy_cosine
from tests.conftest import suffix_cosine
from vpr_jax.evaluation.matching import (
    block_top_k,
    cosine_similarity,
    lane_width,
    top_k_matches,
)


def test_cosine_matches_numpy_and_is_queries_by_database():
    rng = np.random.default_rng(0)
    q, d = rng.normal(size=(7, 12)), rng.normal(size=(11, 12))
    s = np.asarray(cosine_similarity(q.astype(np.float32), d.astype(np.float32)))
    assert s.shape == (7, 11)
    np.testing.assert_allclose(s, _numpy_cosine(q, d), atol=1e-5)


@pytest.mark.parametrize("n_db,block,q_block", [(100, 16, 4096), (100, 100, 7), (5, 4096, 3)])
def test_top_k_equals_brute_force(n_db, block, q_block):
    rng = np.random.default_rng(n_db + block)
    q = rng.normal(size=(23, 9)).astype(np.float32)
    d = rng.normal(size=(n_db, 9)).astype(np.float32)
    scores, idx = top_k_matches(q, d, k=10, block_size=block, query_block_size=q_block)
    k = min(10, n_db)
    s = _numpy_cosine(q, d)
    ref = np.argsort(-s, axis=1, kind="stable")[:, :k]
    assert idx.shape == scores.shape == (1, 23, k)
    np.testing.assert_array_equal(idx[0], ref)
    np.testing.assert_allclose(scores[0], np.take_along_axis(s, ref, 1), atol=1e-5)


def test_ties_keep_lowest_database_index_across_blocks():
    d = np.tile(np.eye(4, dtype=np.float32), (10, 1))  # every 4th row identical
    q = np.eye(4, dtype=np.float32)
    _, idx = top_k_matches(q, d, k=3, block_size=6)
    np.testing.assert_array_equal(idx[0], np.arange(4)[:, None] + np.array([0, 4, 8]))


def test_suffix_starts_equal_slicing():
    rng = np.random.default_rng(3)
    q = rng.normal(size=(8, 20)).astype(np.float32)
    d = rng.normal(size=(30, 20)).astype(np.float32)
    starts = (0, 1, 6, 16)  # the last suffix keeps 4 features: no exact ties
    sims = np.asarray(suffix_cosine(q, d, starts))
    scores, idx = top_k_matches(q, d, k=4, starts=starts, block_size=8)
    for i, s in enumerate(starts):
        ref = _numpy_cosine(q[:, s:], d[:, s:])
        np.testing.assert_allclose(sims[i], ref, atol=1e-5)
        np.testing.assert_array_equal(idx[i], np.argsort(-ref, axis=1, kind="stable")[:, :4])


def test_bad_starts():
    x = np.ones((3, 4), np.float32)
    with pytest.raises(ValueError, match="increasing"):
        top_k_matches(x, x, starts=(2, 1))
    with pytest.raises(ValueError, match="no feature"):
        top_k_matches(x, x, starts=(0, 4))


def _numpy_block_top_k(dot, inv_q, inv_db, valid, k):
    scaled = np.where(valid, dot * inv_q[:, None] * inv_db, -np.inf)
    idx = np.argsort(-scaled, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(scaled, idx, 1), idx


@pytest.mark.parametrize("block", [64, 256, 1000, 1024])
def test_two_level_block_ranking_equals_a_full_sort(block):
    rng = np.random.default_rng(block)
    k = 10
    assert lane_width(block, k) > k  # the two-level path, not the fallback
    dot = rng.normal(size=(37, block)).astype(np.float32)
    lanes = lane_width(block, k)
    # Row 0: its ten best all in one lane, which a per-lane shortcut would lose.
    dot[0, 3::lanes] = 10.0 + np.arange(len(range(3, block, lanes)), dtype=np.float32)
    # Row 1: a tie for the best inside one lane and across lanes: the lower column wins.
    dot[1, [5, 5 + lanes, 7]] = 20.0
    inv_db = rng.uniform(0.5, 2.0, block).astype(np.float32)
    inv_db[[5, 5 + lanes, 7]] = 1.0
    valid = np.ones(block, bool)
    valid[-3:] = False  # padding columns never count, even where their dot is largest
    dot[:, -3:] = 1e6
    inv_q = rng.uniform(0.5, 2.0, len(dot)).astype(np.float32)
    best, idx = block_top_k(dot, inv_q, inv_db, valid, k)
    ref_best, ref_idx = _numpy_block_top_k(dot, inv_q, inv_db, valid, k)
    np.testing.assert_array_equal(np.asarray(idx), ref_idx)
    np.testing.assert_allclose(np.asarray(best), ref_best, rtol=1e-6)
    assert list(np.asarray(idx)[1, :3]) == [5, 7, 5 + lanes]


def test_lane_width_balances_the_two_rankings():
    assert lane_width(4096, 10) == 128  # sqrt(40,960) = 202
    assert lane_width(16, 10) == 0  # too small to split: one top_k
    assert all(lane_width(b, 10) & (lane_width(b, 10) - 1) == 0 for b in (100, 3569, 35768))


def test_blocks_follow_the_cache(monkeypatch):
    from vpr_jax.evaluation import matching

    assert matching.last_level_cache_bytes() >= 1 << 16
    monkeypatch.setattr(matching, "last_level_cache_bytes", lambda: 1 << 20)
    assert matching.score_budget() == (1 << 20) // 16
