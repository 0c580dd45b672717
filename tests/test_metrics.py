"""vpr_jax.evaluation.metrics against loop-based reference implementations, hand-computed
cases and sklearn.

The references below are deliberately naive: a full (Ndb, Nq) boolean ground-truth matrix as
VPR_Tutorial builds it, a per-query argmax, and a Python loop over thresholds and queries.
"""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from sklearn.metrics import auc, average_precision_score, precision_recall_curve

from tests.inputs import random_case
from vpr_jax.evaluation.metrics import (
    PR_CONVENTIONS,
    SCALAR_NAMES,
    Evaluation,
    correct_matches,
    evaluate_similarity,
    evaluate_top_k,
    has_true_match,
    pr_counts,
    pr_curve,
)

# every division-by-zero or invalid-value warning is a test failure
pytestmark = pytest.mark.filterwarnings("error")

SCALARS = SCALAR_NAMES  # the results.csv columns, in order


# ------------------------------------------------------------------ reference implementations


def ref_gt(query_ids, db_ids, tol):
    """(Ndb, Nq) boolean ground truth, VPR_Tutorial's GThard layout."""
    gt = np.zeros((len(db_ids), len(query_ids)), dtype=bool)
    for j, qid in enumerate(query_ids):
        for i, did in enumerate(db_ids):
            gt[i, j] = abs(int(qid) - int(did)) <= tol
    return gt


def ref_best(s_dbq, gt):
    """Per query (column): best score, whether the best match is true, whether any is true."""
    scores, correct, has = [], [], []
    for j in range(s_dbq.shape[1]):
        i = int(np.argmax(s_dbq[:, j]))  # first maximum = lowest index
        scores.append(float(s_dbq[i, j]))
        correct.append(bool(gt[i, j]))
        has.append(bool(gt[:, j].any()))
    return np.array(scores), np.array(correct), np.array(has)


def ref_curve(scores, correct, has, convention):
    """Loop over every distinct score (highest first) and every query."""
    n_match = sum(has)
    precision, recall, thresholds = [1.0], [0.0], [np.inf]
    for t in sorted(set(scores.tolist()), reverse=True):
        tp = fp = fn = 0
        for s, c, m in zip(scores, correct, has, strict=True):
            accepted = s >= t
            if accepted and c:
                tp += 1
            elif accepted:
                fp += 1
            elif convention == "vpr_bench" and c:
                fn += 1
            elif convention == "has_match" and m:
                fn += 1
        denom = n_match if convention == "vpr_tutorial" else tp + fn
        precision.append(tp / (tp + fp))
        recall.append(tp / denom if denom else 0.0)
        thresholds.append(t)
    return np.array(precision), np.array(recall), np.array(thresholds)


def ref_auc(precision, recall):
    area = 0.0
    for i in range(1, len(recall)):
        area += (recall[i] - recall[i - 1]) * (precision[i] + precision[i - 1]) / 2
    return area


def ref_recall_at_100p(precision, recall):
    return max(r for p, r in zip(precision, recall, strict=True) if p == 1.0)


def ref_extended_precision(precision, recall):
    """VPR-Bench's EP = (P_R0 + R_P100) / 2 from the loop curve: the precision at the first
    (strictest) threshold and the largest recall at precision 1 (0 if none)."""
    at_full = [r for p, r in zip(precision[1:], recall[1:], strict=True) if p == 1.0]
    return (precision[1] + (max(at_full) if at_full else 0.0)) / 2


def ref_recall_at_k(s_dbq, gt, k):
    """VPR_Tutorial recallAtK: drop queries without a true match; ties to the lowest index."""
    hits = total = 0
    for j in range(s_dbq.shape[1]):
        if not gt[:, j].any():
            continue
        total += 1
        ranked = sorted(range(s_dbq.shape[0]), key=lambda i: (-s_dbq[i, j], i))
        hits += any(gt[i, j] for i in ranked[:k])
    return hits / total if total else 0.0


def ref_evaluate(sim, query_ids, db_ids, tol, convention, ks=(1, 5, 10)):
    s_dbq = sim.T  # VPR_Tutorial layout
    gt = ref_gt(query_ids, db_ids, tol)
    scores, correct, has = ref_best(s_dbq, gt)
    p, r, t = ref_curve(scores, correct, has, convention)
    rk = {k: ref_recall_at_k(s_dbq, gt, min(k, len(db_ids))) for k in ks}
    return {
        "recall_at_1": correct.mean(),
        "precision_at_full_recall": p[-1],
        "auc_pr": ref_auc(p, r),
        "recall_at_100_precision": ref_recall_at_100p(p, r),
        "recall_at_5": rk[5],
        "recall_at_10": rk[10],
        "extended_precision": ref_extended_precision(p, r),
        "recall_at_k": rk,
        "p": p,
        "r": r,
        "t": t,
        "scores": scores,
        "correct": correct,
        "has": has,
    }


def assert_matches_ref(ev: Evaluation, ref: dict):
    for name in SCALARS:
        assert getattr(ev, name) == pytest.approx(ref[name], abs=1e-12), name
    np.testing.assert_allclose(ev.pr_precision, ref["p"], atol=1e-12)
    np.testing.assert_allclose(ev.pr_recall, ref["r"], atol=1e-12)
    np.testing.assert_array_equal(ev.pr_thresholds, ref["t"])
    np.testing.assert_array_equal(ev.best_scores, ref["scores"])
    np.testing.assert_array_equal(ev.best_correct, ref["correct"])
    np.testing.assert_array_equal(ev.has_match, ref["has"])
    for k, v in ref["recall_at_k"].items():
        assert ev.recall_at_k[k] == pytest.approx(v, abs=1e-12), k


# --------------------------------------------------------------------------- hand-made cases

# rows = queries (ids 0..3), columns = database frames; best matches:
# q0 -> db0 0.9 correct, q1 -> db3 0.8 wrong (db1 0.5 right, rank 2), q2 -> db2 0.7 correct,
# q3 -> db0 0.6 wrong (its true frame db3 is ranked last).
HAND_SIM = np.array(
    [
        [0.9, 0.1, 0.2, 0.3],
        [0.1, 0.5, 0.2, 0.8],
        [0.0, 0.1, 0.7, 0.3],
        [0.6, 0.5, 0.4, 0.0],
    ]
)
HAND_P = [1.0, 1.0, 0.5, 2 / 3, 0.5]

HAND_ALL_MATCH = {  # db ids 0..3: every query has its frame
    "vpr_bench": ([0, 0.5, 0.5, 1, 1], 0.5 + 7 / 24, 0.5),
    "has_match": ([0, 1 / 4, 1 / 3, 2 / 3, 1], 1 / 4 + 1 / 16 + 7 / 36 + 7 / 36, 0.25),
    "vpr_tutorial": ([0, 0.25, 0.25, 0.5, 0.5], 1 / 4 + 7 / 48, 0.25),
}


@pytest.mark.parametrize("convention", PR_CONVENTIONS)
def test_hand_made_all_queries_matched(convention):
    ev = evaluate_similarity(
        HAND_SIM, np.arange(4), np.arange(4), 0, pr_convention=convention, ks=(2, 3)
    )
    recall, area, r100 = HAND_ALL_MATCH[convention]
    np.testing.assert_allclose(ev.pr_precision, HAND_P)
    np.testing.assert_allclose(ev.pr_recall, recall)
    np.testing.assert_array_equal(ev.pr_thresholds, [np.inf, 0.9, 0.8, 0.7, 0.6])
    assert ev.auc_pr == pytest.approx(area)
    assert ev.recall_at_100_precision == pytest.approx(r100)
    assert ev.recall_at_1 == 0.5
    assert ev.precision_at_full_recall == 0.5
    # K is clipped to the 4 database frames, so recall@5 = recall@10 = recall@4
    assert ev.recall_at_k == {1: 0.5, 2: 0.75, 3: 0.75, 5: 1.0, 10: 1.0}
    assert ev.recall_at_5 == 1.0 and ev.recall_at_10 == 1.0
    np.testing.assert_array_equal(ev.best_correct, [True, False, True, False])
    assert ev.has_match.all()
    assert ev.pr_convention == convention


HAND_UNMATCHED = {  # db ids [0, 1, 2, 5]: query id 3 has no true match at tolerance 0
    "vpr_bench": ([0, 0.5, 0.5, 1, 1], 0.5 + 7 / 24, 0.5),
    "has_match": ([0, 1 / 3, 0.5, 1, 1], 18 / 24, 1 / 3),
    "vpr_tutorial": ([0, 1 / 3, 1 / 3, 2 / 3, 2 / 3], 1 / 3 + 7 / 36, 1 / 3),
}


@pytest.mark.parametrize("convention", PR_CONVENTIONS)
def test_hand_made_with_an_unmatched_query(convention):
    db_ids = np.array([0, 1, 2, 5])
    ev = evaluate_similarity(HAND_SIM, np.arange(4), db_ids, 0, pr_convention=convention, ks=(2,))
    recall, area, r100 = HAND_UNMATCHED[convention]
    np.testing.assert_allclose(ev.pr_precision, HAND_P)
    np.testing.assert_allclose(ev.pr_recall, recall)
    assert ev.auc_pr == pytest.approx(area)
    assert ev.recall_at_100_precision == pytest.approx(r100)
    np.testing.assert_array_equal(ev.has_match, [True, True, True, False])
    # recall@1 counts all 4 queries; recall@K drops the unmatched one (2 of 3 right at K=1)
    assert ev.recall_at_1 == 0.5
    assert ev.recall_at_k[1] == pytest.approx(2 / 3)
    assert ev.recall_at_k[2] == 1.0
    assert ev.precision_at_full_recall == 0.5


def test_hand_made_tolerance_turns_a_wrong_match_right():
    db_ids = np.array([0, 1, 2, 5])
    # q3 (id 3): best match db0 (id 0) is 3 frames off; tolerance 2 gives it true matches (1, 2,
    # 5) but its best match stays wrong; tolerance 3 makes it right.
    ev2 = evaluate_similarity(HAND_SIM, np.arange(4), db_ids, 2)
    assert ev2.has_match.all()
    # q1 (id 1): best match id 5 is 4 off -> still wrong; q3 too
    np.testing.assert_array_equal(ev2.best_correct, [True, False, True, False])
    ev3 = evaluate_similarity(HAND_SIM, np.arange(4), db_ids, 3)
    np.testing.assert_array_equal(ev3.best_correct, [True, False, True, True])
    assert ev3.recall_at_1 == 0.75


# ------------------------------------------------------------- random cases against reference


@pytest.mark.parametrize("convention", PR_CONVENTIONS)
@pytest.mark.parametrize("ties", [False, True])
@pytest.mark.parametrize("seed", range(5))
def test_random_matches_reference(seed, ties, convention):
    sim, qids, dids = random_case(seed, ties=ties, all_match=seed % 2 == 1)
    tol = seed % 3
    ev = evaluate_similarity(sim, qids, dids, tol, pr_convention=convention, ks=(1, 2, 5, 10, 20))
    assert_matches_ref(ev, ref_evaluate(sim, qids, dids, tol, convention, ks=(1, 2, 5, 10, 20)))


def test_random_cases_exercise_what_they_claim():
    """Guard the generator: unmatched queries, wrong best matches and ties really occur."""
    sim, qids, dids = random_case(0, ties=True)
    ev = evaluate_similarity(sim, qids, dids, 0)
    assert 0 < ev.has_match.sum() < len(qids)
    assert 0 < ev.best_correct.sum() < ev.has_match.sum()
    assert len(np.unique(ev.best_scores)) < len(qids)


@pytest.mark.parametrize("seed", range(4))
def test_small_query_sets_match_reference(seed):
    rng = np.random.default_rng(100 + seed)
    nq, ndb = int(rng.integers(1, 4)), int(rng.integers(1, 7))
    sim = np.round(rng.normal(size=(nq, ndb)), 1)
    qids, dids = rng.integers(0, 8, nq), rng.integers(0, 8, ndb)
    for convention in PR_CONVENTIONS:
        ev = evaluate_similarity(sim, qids, dids, 1, pr_convention=convention)
        assert_matches_ref(ev, ref_evaluate(sim, qids, dids, 1, convention))


# ------------------------------------------------------------------------------- scikit-learn


@pytest.mark.parametrize("seed", range(4))
def test_against_sklearn_precision_recall_curve(seed):
    sim, qids, dids = random_case(seed, ties=seed % 2 == 0)
    ev = evaluate_similarity(sim, qids, dids, 1)  # vpr_bench
    assert ev.best_correct.any()
    sk_p, sk_r, sk_t = precision_recall_curve(ev.best_correct, ev.best_scores)
    # sklearn lists loosest first and puts (precision 1, recall 0) last; ours is the reverse
    np.testing.assert_allclose(ev.pr_precision, sk_p[::-1], atol=1e-12)
    np.testing.assert_allclose(ev.pr_recall, sk_r[::-1], atol=1e-12)
    np.testing.assert_array_equal(ev.pr_thresholds[1:], sk_t[::-1])
    # VPR-Bench compute_auc_PR / CALC: sklearn auc(recall, precision)
    assert ev.auc_pr == pytest.approx(auc(sk_r, sk_p), abs=1e-12)
    # average precision is the step sum over the same points, not the trapezoid
    step = np.sum(np.diff(ev.pr_recall) * ev.pr_precision[1:])
    assert step == pytest.approx(average_precision_score(ev.best_correct, ev.best_scores))

    n_correct = int(ev.best_correct.sum())
    for convention in PR_CONVENTIONS:
        p, _, t = pr_curve(ev.best_scores, ev.best_correct, ev.has_match, pr_convention=convention)
        np.testing.assert_allclose(p, sk_p[::-1], atol=1e-12)  # precision never depends on it
        tp, *_ = pr_counts(
            ev.best_scores, ev.best_correct, ev.has_match, t[1:], pr_convention=convention
        )
        np.testing.assert_allclose(sk_r[::-1][1:] * n_correct, tp, atol=1e-9)


# ----------------------------------------------------------------- evaluate vs evaluate_top_k


def ref_top_k(sim, k):
    idx = np.argsort(-sim, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(sim, idx, axis=1), idx


@pytest.mark.parametrize("seed", range(3))
def test_evaluate_equals_evaluate_top_k(seed):
    sim, qids, dids = random_case(seed, ties=True)
    s, i = ref_top_k(sim, 10)
    for convention in PR_CONVENTIONS:
        a = evaluate_similarity(sim, qids, dids, 1, pr_convention=convention)
        b = evaluate_top_k(s, i, qids, dids, 1, pr_convention=convention)
        assert a.scalars() == b.scalars()
        for f in ("pr_precision", "pr_recall", "pr_thresholds", "best_scores", "best_correct"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
        assert a.recall_at_k == b.recall_at_k
    # more columns than needed change nothing
    s20, i20 = ref_top_k(sim, 20)
    assert (
        evaluate_top_k(s20, i20, qids, dids, 1).scalars()
        == evaluate_similarity(sim, qids, dids, 1).scalars()
    )


def test_evaluate_sends_ties_to_the_lowest_database_index():
    rng = np.random.default_rng(7)
    sim = rng.integers(0, 3, size=(25, 40)).astype(np.float64)  # massive ties
    sim[0] = 1.0  # a row of all-equal scores
    ids = np.arange(40) * 10  # tolerance 0: only the query's own frame is correct
    for query_ids in (ids[:25], ids[15:]):
        ev = evaluate_similarity(sim, query_ids, ids, 0)
        _, ref = ref_top_k(sim, 10)
        np.testing.assert_array_equal(ev.best_correct, ids[ref[:, 0]] == query_ids)
        for k in (1, 5, 10):
            hit = (ids[ref[:, :k]] == query_ids[:, None]).any(axis=1)
            assert ev.recall_at_k[k] == hit.mean()


def test_scalars_dict():
    ev = evaluate_similarity(HAND_SIM, np.arange(4), np.arange(4), 0)
    d = ev.scalars()
    assert list(d) == list(SCALARS)
    assert all(type(v) is float for v in d.values())
    assert d["auc_pr"] == ev.auc_pr


# ------------------------------------------------------------------------------- pr_counts


@pytest.mark.parametrize("convention", PR_CONVENTIONS)
@pytest.mark.parametrize("seed", range(3))
def test_pr_counts_reproduce_the_curve(seed, convention):
    sim, qids, dids = random_case(seed, ties=True)
    ev = evaluate_similarity(sim, qids, dids, 1, pr_convention=convention)
    b = (ev.best_scores, ev.best_correct, ev.has_match)
    tp, fp, tn, fn = pr_counts(*b, ev.pr_thresholds, pr_convention=convention)
    nq = len(qids)
    assert np.all(np.array([tp, fp, tn, fn]) >= 0)
    accepted = np.array([(ev.best_scores >= t).sum() for t in ev.pr_thresholds])
    np.testing.assert_array_equal(tp + fp, accepted)
    total = tp + fp + tn + fn
    if convention == "vpr_tutorial":
        wrong_with_match = [
            (ev.best_scores >= t)[~ev.best_correct & ev.has_match].sum() for t in ev.pr_thresholds
        ]
        np.testing.assert_array_equal(total, nq + np.array(wrong_with_match))
        np.testing.assert_array_equal(tp + fn, ev.has_match.sum())
    else:
        np.testing.assert_array_equal(total, nq)
    # start point (threshold +inf): nothing accepted
    assert tp[0] == fp[0] == 0
    prec = tp[1:] / (tp[1:] + fp[1:])
    denom = tp + fn
    rec = np.where(denom > 0, tp / np.maximum(denom, 1), 0.0)
    np.testing.assert_allclose(prec, ev.pr_precision[1:], atol=1e-12)
    np.testing.assert_allclose(rec, ev.pr_recall, atol=1e-12)


def ref_create_pr_tutorial(s_dbq, gt, n_thresh=100):
    """VPR_Tutorial createPR(matching='single') semantics, written as a plain loop."""
    gtp = gt.any(0).sum()
    best = s_dbq.argmax(0)
    best_gt = gt[best, np.arange(gt.shape[1])]
    best_s = s_dbq.max(0)
    precision, recall = [1.0], [0.0]
    for t in np.linspace(best_s.max(), best_s.min(), n_thresh):
        tp = fp = 0
        for s, g in zip(best_s, best_gt, strict=True):
            if s >= t and g:
                tp += 1
            elif s >= t:
                fp += 1
        precision.append(tp / (tp + fp))
        recall.append(tp / gtp)
    return np.array(precision), np.array(recall)


@pytest.mark.parametrize("seed", range(3))
def test_pr_counts_at_vpr_tutorial_sampled_thresholds(seed):
    sim, qids, dids = random_case(seed)
    ev = evaluate_similarity(sim, qids, dids, 1, pr_convention="vpr_tutorial")
    ref_p, ref_r = ref_create_pr_tutorial(sim.T, ref_gt(qids, dids, 1))
    t = np.linspace(ev.best_scores.max(), ev.best_scores.min(), 100)
    tp, fp, _, fn = pr_counts(
        ev.best_scores, ev.best_correct, ev.has_match, t, pr_convention="vpr_tutorial"
    )
    np.testing.assert_allclose(tp / (tp + fp), ref_p[1:], atol=1e-12)
    np.testing.assert_allclose(tp / (tp + fn), ref_r[1:], atol=1e-12)
    # the exact curve is finer than the tutorial's 100 samples: the same maximum recall
    assert ev.pr_recall.max() == pytest.approx(ref_r.max())


def test_pr_counts_tensorboard_thresholds():
    sim, qids, dids = random_case(3)
    ev = evaluate_similarity(sim, qids, dids, 1)
    mapped = (np.tanh(ev.best_scores) + 1) / 2  # any increasing map into [0, 1]
    t = np.linspace(0, 1, 21)
    tp, fp, tn, fn = pr_counts(mapped, ev.best_correct, ev.has_match, t)
    assert np.all(np.diff(tp) <= 0) and np.all(np.diff(fp) <= 0)  # loosest first
    assert tp[0] == ev.best_correct.sum() and fp[0] == (~ev.best_correct).sum()
    assert tn[0] == fn[0] == 0
    assert np.all(tp + fp + tn + fn == len(qids))
    assert tp[-1] + fp[-1] == (mapped >= 1).sum()


# --------------------------------------------------------------------------- properties


@pytest.mark.parametrize("seed", range(4))
def test_precision_at_full_recall_is_fraction_correct(seed):
    sim, qids, dids = random_case(seed, ties=True, all_match=True)
    for convention in PR_CONVENTIONS:
        ev = evaluate_similarity(sim, qids, dids, 0, pr_convention=convention)
        assert ev.has_match.all()
        assert ev.precision_at_full_recall == pytest.approx(ev.recall_at_1)
        assert ev.recall_at_k[1] == pytest.approx(ev.recall_at_1)
        if convention == "vpr_tutorial":
            assert ev.pr_recall[-1] == pytest.approx(ev.recall_at_1)
        else:
            assert ev.pr_recall[-1] == 1.0
            first_full = np.argmax(ev.pr_recall == 1.0)
            assert ev.pr_precision[first_full] >= ev.precision_at_full_recall


@pytest.mark.parametrize("seed", range(4))
def test_curves_are_monotone_and_conventions_ordered(seed):
    sim, qids, dids = random_case(seed, ties=True)
    evs = {c: evaluate_similarity(sim, qids, dids, 1, pr_convention=c) for c in PR_CONVENTIONS}
    for ev in evs.values():
        assert np.all(np.diff(ev.pr_recall) >= 0)
        assert np.all(np.diff(ev.pr_thresholds) < 0)
        assert 0 <= ev.auc_pr <= 1
    assert np.all(evs["has_match"].pr_recall <= evs["vpr_bench"].pr_recall + 1e-12)
    assert evs["has_match"].auc_pr <= evs["vpr_bench"].auc_pr
    # has_match and vpr_tutorial agree wherever no false positive was accepted
    clean = evs["vpr_bench"].pr_precision == 1.0
    np.testing.assert_allclose(
        evs["has_match"].pr_recall[clean], evs["vpr_tutorial"].pr_recall[clean]
    )


@pytest.mark.parametrize("seed", range(4))
def test_widening_tolerance_never_lowers_recall(seed):
    sim, qids, dids = random_case(seed, all_match=True)
    previous = None
    for tol in range(0, 8):
        ev = evaluate_similarity(sim, qids, dids, tol)
        if previous is not None:
            assert ev.recall_at_1 >= previous.recall_at_1
            for k, v in ev.recall_at_k.items():  # every query has a match at every tolerance
                assert v >= previous.recall_at_k[k]
            assert np.all(ev.best_correct >= previous.best_correct)
        previous = ev
    # with some queries unmatched, recall@1 over all queries still never drops
    sim, qids, dids = random_case(seed)
    r1 = [evaluate_similarity(sim, qids, dids, tol).recall_at_1 for tol in range(8)]
    assert np.all(np.diff(r1) >= 0)


def test_permuting_database_and_queries_changes_nothing():
    sim, qids, dids = random_case(11)  # continuous scores: no ties to break differently
    rng = np.random.default_rng(0)
    pq, pd = rng.permutation(len(qids)), rng.permutation(len(dids))
    for convention in PR_CONVENTIONS:
        a = evaluate_similarity(sim, qids, dids, 2, pr_convention=convention)
        b = evaluate_similarity(sim[pq][:, pd], qids[pq], dids[pd], 2, pr_convention=convention)
        for name in SCALARS:
            assert getattr(a, name) == pytest.approx(getattr(b, name), abs=1e-12)
        np.testing.assert_array_equal(a.best_correct[pq], b.best_correct)


def test_has_true_match_against_brute_force():
    rng = np.random.default_rng(5)
    dids = rng.integers(-50, 50, 80)  # unsorted, duplicates, negatives
    qids = rng.integers(-60, 60, 100)
    for tol in (0, 1, 3):
        np.testing.assert_array_equal(
            has_true_match(qids, dids, tol), ref_gt(qids, dids, tol).any(0)
        )
    idx = rng.integers(0, 80, size=(100, 4))
    expected = np.abs(dids[idx] - qids[:, None]) <= 2
    np.testing.assert_array_equal(correct_matches(idx, qids, dids, 2), expected)


def test_route_sized_top_k_is_exact_without_a_dense_matrix():
    """35,768-frame database, 3,569 queries: no (Nq, Ndb) matrix is needed or built (its
    speed against a dense numpy peer is in benchmarks/bench_linear.py)."""
    rng = np.random.default_rng(0)
    ndb, nq, k = 35_768, 3_569, 10
    dids = rng.permutation(ndb) + 1
    qids = np.arange(1, ndb + 1, 10)[:nq]
    position = np.empty(ndb + 1, dtype=np.int64)
    position[dids] = np.arange(ndb)
    true_idx = position[qids]
    idx = np.where(rng.random((nq, k)) < 0.3, true_idx[:, None], rng.integers(0, ndb, (nq, k)))
    scores = -np.sort(-rng.random((nq, k)), axis=1)
    tracemalloc.start()
    try:
        ev = evaluate_top_k(scores, idx, qids, dids, 2)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    # A dense (Nq, Ndb) boolean ground truth alone would take nq * ndb bytes (128 MB).
    assert peak < nq * ndb // 8, peak
    assert ev.has_match.all()
    sub = rng.choice(nq, 50, replace=False)
    for q in sub:
        expected = [abs(int(dids[j]) - int(qids[q])) <= 2 for j in idx[q]]
        assert bool(ev.best_correct[q]) == expected[0]
    hit = np.abs(dids[idx] - qids[:, None]) <= 2
    assert ev.recall_at_10 == pytest.approx(hit.any(axis=1).mean())
    assert 0.2 < ev.recall_at_1 < 0.5


# ----------------------------------------------------------------------- degenerate inputs


@pytest.mark.parametrize("convention", PR_CONVENTIONS)
def test_no_query_has_a_match(convention):
    sim = np.random.default_rng(0).normal(size=(5, 6))
    ev = evaluate_similarity(sim, np.arange(100, 105), np.arange(6), 2, pr_convention=convention)
    assert not ev.has_match.any()
    assert ev.scalars() == dict.fromkeys(SCALARS, 0.0)
    np.testing.assert_array_equal(ev.pr_recall, 0.0)
    np.testing.assert_array_equal(ev.pr_precision[1:], 0.0)


@pytest.mark.parametrize("convention", PR_CONVENTIONS)
def test_all_scores_equal(convention):
    sim = np.full((4, 5), 0.3)
    ev = evaluate_similarity(sim, np.arange(4), np.arange(5), 0, pr_convention=convention)
    # every query picks db 0 (lowest index); only query 0 is right
    np.testing.assert_array_equal(ev.best_correct, [True, False, False, False])
    np.testing.assert_array_equal(ev.pr_thresholds, [np.inf, 0.3])
    np.testing.assert_allclose(ev.pr_precision, [1.0, 0.25])
    expected_recall = 0.25 if convention == "vpr_tutorial" else 1.0
    np.testing.assert_allclose(ev.pr_recall, [0.0, expected_recall])
    assert ev.auc_pr == pytest.approx(expected_recall * (1 + 0.25) / 2)
    assert ev.recall_at_100_precision == 0.0
    assert ev.recall_at_1 == ev.precision_at_full_recall == 0.25


@pytest.mark.parametrize("convention", PR_CONVENTIONS)
@pytest.mark.parametrize("right", [True, False])
def test_single_query(convention, right):
    sim = np.array([[0.2, 0.9, 0.1]]) if right else np.array([[0.9, 0.2, 0.1]])
    ev = evaluate_similarity(sim, [1], [0, 1, 2], 0, pr_convention=convention)
    assert ev.recall_at_1 == float(right)
    assert ev.auc_pr == (1.0 if right else 0.0)
    assert ev.recall_at_100_precision == float(right)
    assert ev.recall_at_5 == 1.0  # the true frame is among 3 (K clipped to 3)
    if not right:
        assert ev.recall_at_k[1] == 0.0


def test_nan_scores_raise():
    sim = np.random.default_rng(0).normal(size=(3, 4))
    sim[1, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        evaluate_similarity(sim, np.arange(3), np.arange(4), 0)
    s, i = ref_top_k(np.nan_to_num(sim), 4)
    s[2, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        evaluate_top_k(s, i, np.arange(3), np.arange(4), 0)
    with pytest.raises(ValueError, match="NaN"):
        pr_counts(np.array([0.1, np.nan]), [1, 0], [1, 1], [0.0])


def test_bad_inputs_raise_one_line_errors():
    q, d = np.arange(4), np.arange(4)
    s, i = ref_top_k(HAND_SIM, 4)
    s_inf = s.copy()
    s_inf[1, 0] = np.inf
    cases = [
        (lambda: evaluate_similarity(HAND_SIM, q, d, 0, pr_convention="lowry"), "pr_convention"),
        (lambda: evaluate_similarity(HAND_SIM.T[:3], q, d, 0), "n_queries, n_db"),
        (lambda: evaluate_similarity(HAND_SIM, q, d, -1), "tolerance"),
        (lambda: evaluate_similarity(HAND_SIM, q, d, 1.5), "tolerance"),
        (lambda: evaluate_similarity(HAND_SIM, q + 0.5, d, 0), "integer frame ids"),
        (lambda: evaluate_top_k(s, i + 1, q, d, 0), r"\[0, 4\)"),
        (lambda: evaluate_top_k(s[:, ::-1], i[:, ::-1], q, d, 0), "best first"),
        (lambda: evaluate_top_k(s[:, :2], i[:, :2], q, d, 0), "top 4"),
        (lambda: evaluate_top_k(s, i[:, :2], q, d, 0), "shape"),
        (lambda: evaluate_top_k(s[:0], i[:0], q[:0], d, 0), "no queries"),
        (lambda: evaluate_top_k(s, i, q, d, 0, ks=(0,)), ">= 1"),
        (lambda: evaluate_top_k(s_inf, i, q, d, 0), "finite"),
        (lambda: pr_counts([0.5], [True], [False], [0.1]), "has_match"),
    ]
    for call, message in cases:
        with pytest.raises(ValueError, match=message) as info:
            call()
        assert "\n" not in str(info.value)


def test_integral_float_ids_and_padded_top_k_are_accepted():
    s, i = ref_top_k(HAND_SIM, 4)
    a = evaluate_top_k(s, i, np.arange(4.0), np.arange(4.0), 0)
    b = evaluate_top_k(s, i, np.arange(4), np.arange(4), 0)
    assert a.scalars() == b.scalars()
    # trailing -inf padding (a matcher with fewer candidates than K) is fine past column 0
    s2 = np.concatenate([s, np.full((4, 6), -np.inf)], axis=1)
    i2 = np.concatenate([i, np.zeros((4, 6), dtype=int)], axis=1)
    assert evaluate_top_k(s2, i2, np.arange(4), np.arange(4), 0).scalars() == b.scalars()


def test_float32_and_integer_similarities():
    sim, qids, dids = random_case(2, ties=True)
    sim32 = sim.astype(np.float32)
    a = evaluate_similarity(sim32, qids, dids, 1)
    b = evaluate_similarity(sim32.astype(np.float64), qids, dids, 1)
    assert a.scalars() == b.scalars()
    np.testing.assert_array_equal(a.best_scores, b.best_scores)
    simu8 = np.round((sim - sim.min()) * 10).astype(np.uint8)  # heavy ties, unsigned
    c = evaluate_similarity(simu8, qids, dids, 1)
    assert_matches_ref(c, ref_evaluate(simu8.astype(np.float64), qids, dids, 1, "vpr_bench"))


@pytest.mark.parametrize("seed", range(6))
def test_extended_precision_matches_sklearn_curve(seed):
    """EP from scikit-learn's PR curve of the best matches (the vpr_bench convention): its
    strictest threshold's precision plus its largest recall at precision 1, halved."""
    sim, q, d = random_case(seed, ties=seed % 2 == 1)
    ev = evaluate_similarity(sim, q, d, 2)
    precision, recall, _ = precision_recall_curve(ev.best_correct, ev.best_scores)
    precision, recall = precision[:-1], recall[:-1]  # drop sklearn's appended (1, 0)
    at_full = recall[precision == 1.0]
    expected = (precision[-1] + (at_full.max() if at_full.size else 0.0)) / 2
    assert ev.extended_precision == pytest.approx(expected, abs=1e-12)
    assert 0.0 <= ev.extended_precision <= 1.0


def test_extended_precision_hand_cases():
    # most confident match wrong: R_P100 = 0, P_R0 = 0
    ev = evaluate_similarity(
        np.array([[0.9, 0.0], [0.0, 0.5]]), np.array([10, 20]), np.array([20, 10]), 0
    )
    assert ev.extended_precision == 0.0
    # all right: P_R0 = 1 and R_P100 = 1
    ev = evaluate_similarity(
        np.array([[0.9, 0.0], [0.0, 0.5]]), np.array([10, 20]), np.array([10, 20]), 0
    )
    assert ev.extended_precision == 1.0
