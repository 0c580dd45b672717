"""Blockwise running top-K against numpy brute force."""

import numpy as np
import pytest

from tests.conftest import numpy_cosine as _numpy_cosine
from vpr_jax.evaluation.matching import cosine_similarity, suffix_cosine, top_k_matches


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
