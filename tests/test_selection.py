"""Which row of a group is selected: the best on validation, whatever order rows arrive in,
and marked again when the table grows; ties of validation recall@1 are broken by the
validation margin (checked against a full similarity matrix), then by the simpler setting."""

import json
import math

import numpy as np
import pytest

from tests.inputs import random_case
from vpr_jax.data.ground_truth import Tolerance
from vpr_jax.evaluation.metrics import evaluate_matches, match_margin
from vpr_jax.outputs.results import (
    COLUMNS,
    SELECTED_BY,
    ResultRow,
    append_results,
    choices,
    decided_by,
    read_results,
)


def _row(method="pca", k=0, val=0.5, margin=0.1, test=0.5, ds=1, pair="summer-fall"):
    values = dict.fromkeys(COLUMNS, 0)
    values.update(
        season_pair=pair,
        db_season="summer",
        query_season="fall",
        method=method,
        objective="",
        setting="",
        settings=json.dumps({"removed_pcs": k} if method == "pca" else {}),
        removed_pcs=k,
        ds=ds,
        recall_at_1=test,
        val_recall_at_1=val,
        val_margin=margin,
        run=f"{pair}/{method}_k{k:03d}_ds{ds}",
    )
    return ResultRow(**values)


def test_best_validation_row_is_selected_not_the_best_test_row(tmp_path):
    path = tmp_path / "results.csv"
    rows = [
        _row(k=0, val=0.6, test=0.9),
        _row(k=5, val=0.8, test=0.7),
        _row(k=20, val=0.8, margin=0.3, test=0.6),  # ties on recall: the margin decides
        _row(k=50, val=0.8, margin=0.3, test=0.95),  # full tie: fewer removed PCs
        _row(method="raw", val=0.1),
        _row(k=5, val=0.9, ds=10),
    ]
    for row in reversed(rows):  # arrival order does not matter
        append_results(path, [row])
    chosen = {(r.method, r.ds): r.removed_pcs for r in read_results(path) if r.selected}
    assert chosen == {("pca", 1): 20, ("raw", 1): 0, ("pca", 10): 5}
    # A better count added later takes the mark; exactly one row per group keeps it.
    append_results(path, [_row(k=100, val=0.85)])
    marked = [r for r in read_results(path) if r.selected and (r.method, r.ds) == ("pca", 1)]
    assert [r.removed_pcs for r in marked] == [100]


def test_rows_without_a_validation_score_lose(tmp_path):
    path = tmp_path / "results.csv"
    append_results(path, [_row(k=0, val=math.nan, margin=math.nan, test=1.0), _row(k=5, val=0.1)])
    assert [r.removed_pcs for r in read_results(path) if r.selected] == [5]


@pytest.mark.parametrize(
    "scores, reason",
    [
        ([(0.9, 0.1), (0.8, 0.5)], SELECTED_BY[0]),
        ([(0.9, 0.1), (0.9, 0.2)], SELECTED_BY[1]),
        ([(0.9, 0.2), (0.9, 0.2), (0.5, 0.9)], SELECTED_BY[2]),
        ([(0.9, 0.2)], SELECTED_BY[3]),
    ],
)
def test_the_table_says_what_decided_each_selection(scores, reason):
    rows = [_row(k=5 * i, val=v, margin=m) for i, (v, m) in enumerate(scores)]
    (group,) = choices(rows).values()
    assert decided_by(group) == reason


def _full_margin(similarity, correct, has_match):
    """The oracle: per query with a match, its best correct similarity minus its best wrong
    one over the whole database."""
    best_correct = np.where(correct, similarity, -np.inf).max(axis=1)
    best_wrong = np.where(correct, -np.inf, similarity).max(axis=1)
    return float(np.mean((best_correct - best_wrong)[has_match]))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_margin_is_best_correct_minus_best_wrong(seed):
    """With every database image among the top K, the margin equals the full matrix's."""
    rng = np.random.default_rng(seed)
    n_q, n_db, tol = 30, 40, 2
    query_ids = rng.choice(60, n_q, replace=False)
    db_ids = np.arange(n_db)
    similarity = rng.uniform(-1, 1, (n_q, n_db))
    truth = Tolerance.of(query_ids, db_ids, tol)
    correct = np.abs(query_ids[:, None] - db_ids[None, :]) <= tol
    has_match = correct.any(axis=1)
    assert has_match.any() and not has_match.all()
    order = np.argsort(-similarity, axis=1, kind="stable")
    top = np.take_along_axis(similarity, order, axis=1)
    ev = evaluate_matches(top, order, truth)
    assert ev.margin == pytest.approx(_full_margin(similarity, correct, has_match), abs=1e-12)
    # The margin's sign is the top match's correctness, query by query.
    one = truth.correct(order)
    for i in np.flatnonzero(has_match):
        assert (match_margin(top[i : i + 1], one[i : i + 1], has_match[i : i + 1]) > 0) == one[i, 0]


def test_a_top_k_margin_is_bounded_by_the_kth_score():
    """Past the top K the K-th score stands in: the margin of a query whose correct match
    lies beyond K is at most the K-th minus the first score."""
    similarity = random_case(4, nq=20, ndb=50)[0]
    order = np.argsort(-similarity, axis=1, kind="stable")[:, :3]
    top = np.take_along_axis(similarity, order, axis=1)
    correct = np.zeros(order.shape, bool)
    has_match = np.ones(len(top), bool)
    assert match_margin(top, correct, has_match) == pytest.approx(np.mean(top[:, -1] - top[:, 0]))
