"""Ground truth as sets (vpr_jax.data.ground_truth) against dense numpy references, and the
aligned route's tolerance expressed as sets giving exactly today's numbers."""

import numpy as np
import pytest

from tests.inputs import random_case
from vpr_jax.data.ground_truth import MatchSets, Tolerance, match_sets, within_radius
from vpr_jax.evaluation.metrics import evaluate_matches, evaluate_similarity
from vpr_jax.evaluation.sequence import sequence_top_k_cosine


def dense(truth, n_db):
    """(Nq, Ndb) boolean matrix of a MatchSets, row by row."""
    out = np.zeros((truth.n_queries, n_db), bool)
    for i in range(truth.n_queries):
        out[i, truth.row(i)] = True
    return out


@pytest.mark.parametrize("seed", range(4))
def test_tolerance_as_sets_is_the_dense_tolerance_matrix(seed):
    _, q, d = random_case(seed)
    tol = Tolerance.of(q, d, 2)
    sets = tol.sets()
    reference = np.abs(q[:, None] - d[None, :]) <= 2
    np.testing.assert_array_equal(dense(sets, len(d)), reference)
    np.testing.assert_array_equal(sets.has_match(), reference.any(axis=1))
    idx = np.random.default_rng(seed).integers(0, len(d), (len(q), 7))
    expected = np.take_along_axis(reference, idx, axis=1)
    np.testing.assert_array_equal(sets.correct(idx), expected)
    np.testing.assert_array_equal(tol.correct(idx), expected)
    for truth in (tol, sets):  # a true match, or -1 without one
        a = truth.a_match()
        assert np.all((a >= 0) == reference.any(axis=1))
        assert np.all(reference[np.flatnonzero(a >= 0), a[a >= 0]])


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("convention", ["vpr_bench", "has_match", "vpr_tutorial"])
def test_metrics_from_sets_equal_the_tolerance_path_exactly(seed, convention):
    sim, q, d = random_case(seed, ties=seed % 2 == 1)
    fast = evaluate_similarity(sim, q, d, 3, pr_convention=convention)
    top = np.argsort(-sim, axis=1, kind="stable")[:, :10]
    scores = np.take_along_axis(sim, top, axis=1)
    sets = evaluate_matches(scores, top, Tolerance.of(q, d, 3).sets(), pr_convention=convention)
    for a, b in zip(fast, sets, strict=True):
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(a, b)
        else:
            assert a == b


def test_sequence_matches_score_the_same_against_sets():
    rng = np.random.default_rng(3)
    db = rng.normal(size=(80, 16)).astype(np.float32)
    query = db[5:65] + rng.normal(0, 0.8, (60, 16)).astype(np.float32)
    db_ids, query_ids = np.arange(80), np.arange(5, 65)
    top = sequence_top_k_cosine(query, db, 5, query_ids=query_ids, db_ids=db_ids, k=10)
    tol = Tolerance.of(query_ids, db_ids, 1)
    a, b = evaluate_matches(*top, tol), evaluate_matches(*top, tol.sets())
    assert a.scalars() == b.scalars() and a.recall_at_1 > 0.5
    np.testing.assert_array_equal(a.pr_precision, b.pr_precision)


def test_within_radius_equals_the_dense_distance_matrix():
    rng = np.random.default_rng(0)
    db = rng.uniform(-500, 1500, (400, 2)) + [3.5e5, 6.9e6]  # UTM-like metres
    query = np.concatenate(
        [db[:50] + rng.normal(0, 20, (50, 2)), rng.uniform(-500, 1500, (50, 2)) + [3.5e5, 6.9e6]]
    )
    query[0] = db[7] + [25.0, 0.0]  # exactly on the radius: a match (<=)
    for radius in (25.0, 60.0, 300.0):
        sets = within_radius(query, db, radius)
        distance = np.sqrt(((query[:, None] - db[None]) ** 2).sum(-1))
        np.testing.assert_array_equal(dense(sets, len(db)), distance <= radius)
        assert sets.describe() == f"within {radius:g} m"
    assert 7 in within_radius(query, db, 25.0).row(0)


def test_match_sets_sorts_rows_drops_repeats_and_takes_queries():
    sets = match_sets([[4, 1, 1], [], [0, 2]], n_db=5)
    assert [list(sets.row(i)) for i in range(3)] == [[1, 4], [], [0, 2]]
    np.testing.assert_array_equal(sets.has_match(), [True, False, True])
    idx = np.array([[1, 0], [3, 4], [2, 1]])
    np.testing.assert_array_equal(sets.correct(idx), [[True, False], [False, False], [True, False]])
    part = sets.take(np.array([2, 0]))
    assert [list(part.row(i)) for i in range(2)] == [[0, 2], [1, 4]]
    with pytest.raises(ValueError, match=r"\[0, 5\)"):
        match_sets([[5]], n_db=5)
    with pytest.raises(ValueError, match="database positions"):
        sets.correct(np.array([[9], [0], [0]]))
    assert isinstance(sets, MatchSets)
    nothing = match_sets([[], []], n_db=3)  # no query has a correct match
    assert not nothing.correct(np.array([[0, 1], [2, 0]])).any()
    assert list(nothing.a_match()) == [-1, -1]
