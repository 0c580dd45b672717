"""Place-recognition metrics: PR curve, AUC-PR, precision at 100% recall, R@100P, recall@K.

Pure numpy on results already fetched from devices; no file IO. Everything works from each
query's top-K database matches (:func:`evaluate_top_k`), so matching a long route never needs
the full similarity matrix; :func:`evaluate_similarity` is the convenience wrapper for a matrix
that fits in memory. docs/metrics.md defines each metric and PR convention with the
references it follows.
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple

import numpy as np
from jaxtyping import Bool, Float, Int

from vpr_jax.config import PR_CONVENTIONS
from vpr_jax.data.ground_truth import GroundTruth, Tolerance

__all__ = [
    "PR_CONVENTIONS",
    "Evaluation",
    "correct_matches",
    "evaluate_similarity",
    "evaluate_matches",
    "evaluate_top_k",
    "extended_precision",
    "has_true_match",
    "pr_counts",
    "pr_curve",
]

PRConvention = Literal[PR_CONVENTIONS]  # one of config.PR_CONVENTIONS
DEFAULT_KS: tuple[int, ...] = (1, 5, 10)
PRPoints = Float[np.ndarray, " n_points"]
SCALAR_NAMES: tuple[str, ...] = (
    "recall_at_1",
    "precision_at_full_recall",
    "auc_pr",
    "recall_at_100_precision",
    "recall_at_5",
    "recall_at_10",
    "extended_precision",
)


class Evaluation(NamedTuple):
    """Metrics of one database/query pair; docs/metrics.md defines each of them.

    ``pr_precision``, ``pr_recall``, ``pr_thresholds`` (length n_distinct_scores + 1): the PR
    curve from the strictest threshold to the loosest; index 0 is the start point (recall 0,
    precision 1, threshold +inf), index i > 0 accepts queries with best score >= threshold i.
    ``best_scores``, ``best_correct``, ``has_match``: per query (in input order).
    ``recall_at_k``: recall@K for every K asked for (always including 1, 5 and 10);
    ``recall_at_5`` and ``recall_at_10`` read it. ``margin``: ``match_margin``, what breaks
    ties of the validation places' recall@1.
    """

    recall_at_1: float
    precision_at_full_recall: float
    auc_pr: float
    recall_at_100_precision: float
    pr_precision: Float[np.ndarray, " n_points"]
    pr_recall: Float[np.ndarray, " n_points"]
    pr_thresholds: Float[np.ndarray, " n_points"]
    best_scores: Float[np.ndarray, " nq"]
    best_correct: Bool[np.ndarray, " nq"]
    has_match: Bool[np.ndarray, " nq"]
    recall_at_k: dict[int, float]
    pr_convention: str
    extended_precision: float = float("nan")
    margin: float = float("nan")

    @property
    def recall_at_5(self) -> float:
        return self.recall_at_k[5]

    @property
    def recall_at_10(self) -> float:
        return self.recall_at_k[10]

    def scalars(self) -> dict[str, float]:
        """The scalar metrics, by name (the results.csv columns), as Python floats."""
        return {name: float(getattr(self, name)) for name in SCALAR_NAMES}


# ----------------------------------------------------------------------------- validation


def _all_ks(ks: tuple[int, ...]) -> list[int]:
    """The recall@K cut-offs computed: those asked for and always 1, 5 and 10, ascending."""
    return sorted({*DEFAULT_KS, *(int(k) for k in ks)})


def _check_convention(pr_convention: str) -> None:
    if pr_convention not in PR_CONVENTIONS:
        raise ValueError(
            f"unknown pr_convention {pr_convention!r}: use one of {', '.join(PR_CONVENTIONS)}"
        )


def _as_bool(x: np.ndarray, name: str, n: int) -> np.ndarray:
    arr = np.asarray(x)
    if arr.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {arr.shape}")
    if arr.dtype != np.bool_:
        if not np.all((arr == 0) | (arr == 1)):
            raise ValueError(f"{name} must be boolean (or 0/1)")
        arr = arr.astype(bool)
    return arr


def _check_scores(scores: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(scores, dtype=np.float64)
    if np.isnan(arr).any():
        raise ValueError(f"{name} contains NaN: the descriptors or similarities are broken")
    return arr


# --------------------------------------------------------------------------- ground truth


def has_true_match(
    query_ids: Int[np.ndarray, " nq"], db_ids: Int[np.ndarray, " ndb"], tolerance: int
) -> Bool[np.ndarray, " nq"]:
    """Whether some database frame lies within ``tolerance`` of each query's frame id
    (``vpr_jax.data.ground_truth.Tolerance``; ``db_ids`` in any order)."""
    return Tolerance.of(query_ids, db_ids, tolerance).has_match()


def correct_matches(
    indices: Int[np.ndarray, "nq k"],
    query_ids: Int[np.ndarray, " nq"],
    db_ids: Int[np.ndarray, " ndb"],
    tolerance: int,
) -> Bool[np.ndarray, "nq k"]:
    """Whether each retrieved database index (into ``db_ids``) is a true match of its query."""
    return Tolerance.of(query_ids, db_ids, tolerance).correct(indices)


# ------------------------------------------------------------------------------- PR curve


def _accepted_counts(
    scores: np.ndarray, correct: np.ndarray, has_match: np.ndarray, n_accepted: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """TP, FP and accepted-with-a-match counts when the ``n_accepted`` best scores are accepted.

    ``scores`` etc. must already be sorted by score, highest first.
    """
    zero = np.zeros(1, dtype=np.int64)
    cum_tp = np.concatenate([zero, np.cumsum(correct, dtype=np.int64)])
    cum_match = np.concatenate([zero, np.cumsum(has_match, dtype=np.int64)])
    tp = cum_tp[n_accepted]
    fp = n_accepted - tp
    acc_match = cum_match[n_accepted]
    return tp, fp, acc_match


def _recall(
    tp: np.ndarray,
    acc_match: np.ndarray,
    n_correct: int,
    n_has_match: int,
    pr_convention: str,
) -> np.ndarray:
    if pr_convention == "vpr_bench":
        denom = np.full(tp.shape, n_correct, dtype=np.int64)
    elif pr_convention == "has_match":
        denom = tp + (n_has_match - acc_match)
    else:  # vpr_tutorial
        denom = np.full(tp.shape, n_has_match, dtype=np.int64)
    return np.divide(tp, denom, out=np.zeros(tp.shape, dtype=np.float64), where=denom > 0)


def _sorted_inputs(
    best_scores: np.ndarray, best_correct: np.ndarray, has_match: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    scores = _check_scores(best_scores, "best_scores")
    if scores.ndim != 1 or scores.shape[0] == 0:
        raise ValueError(f"best_scores must be a non-empty 1-D array, got shape {scores.shape}")
    if not np.all(np.isfinite(scores)):
        raise ValueError("best_scores must be finite: a query's best match has an infinite score")
    n = scores.shape[0]
    correct = _as_bool(best_correct, "best_correct", n)
    match = _as_bool(has_match, "has_match", n)
    if np.any(correct & ~match):
        raise ValueError("best_correct is True for a query whose has_match is False")
    order = np.argsort(-scores, kind="stable")
    return scores, scores[order], correct[order], match[order]


def pr_curve(
    best_scores: Float[np.ndarray, " nq"],
    best_correct: Bool[np.ndarray, " nq"],
    has_match: Bool[np.ndarray, " nq"],
    *,
    pr_convention: PRConvention = "vpr_bench",
) -> tuple[PRPoints, PRPoints, PRPoints]:
    """Single-best-match PR curve ``(precision, recall, thresholds)``, strictest first.

    Point 0 is the start (precision 1, recall 0, threshold +inf); point i > 0 accepts every
    query with ``score >= thresholds[i]``, the distinct best scores in decreasing order.
    """
    _check_convention(pr_convention)
    _, s, c, m = _sorted_inputs(best_scores, best_correct, has_match)
    # the last position of each run of equal scores: ties enter together
    last = np.flatnonzero(np.append(s[1:] != s[:-1], True))
    n_accepted = last + 1
    tp, fp, acc_match = _accepted_counts(s, c, m, n_accepted)
    precision = tp / (tp + fp)  # at least one query is accepted at every threshold
    recall = _recall(tp, acc_match, int(c.sum()), int(m.sum()), pr_convention)
    return (
        np.concatenate([[1.0], precision]),
        np.concatenate([[0.0], recall]),
        np.concatenate([[np.inf], s[last]]),
    )


def pr_counts(
    best_scores: Float[np.ndarray, " nq"],
    best_correct: Bool[np.ndarray, " nq"],
    has_match: Bool[np.ndarray, " nq"],
    thresholds: Float[np.ndarray, " n_thresholds"],
    *,
    pr_convention: PRConvention = "vpr_bench",
) -> tuple[
    Int[np.ndarray, " n_thresholds"],
    Int[np.ndarray, " n_thresholds"],
    Int[np.ndarray, " n_thresholds"],
    Int[np.ndarray, " n_thresholds"],
]:
    """``(tp, fp, tn, fn)`` at the given thresholds; a query is positive iff ``score >= t``.

    Made for TensorBoard's ``add_pr_curve_raw`` (map cosine scores to [0, 1] first, and pass
    the same map of the scores here), so that ``tp / (tp + fp)`` and ``tp / (tp + fn)``
    reproduce the chosen convention's precision and recall (0 where a denominator is 0;
    precision with nothing accepted is left to the caller: VPR_Tutorial and this module's
    curve use 1 there).

    - ``"vpr_bench"``: fn = rejected & correct, tn = rejected & ~correct (sum = Nq).
    - ``"has_match"``: fn = rejected & has_match, tn = rejected & ~has_match (sum = Nq).
    - ``"vpr_tutorial"``: fn = has_match & ~(accepted & correct), tn = rejected & ~has_match,
      so tp + fn = n_has_match; a wrong accepted match of a query with a true match counts as
      both FP and FN, and the four counts sum to Nq plus that number.
    """
    _check_convention(pr_convention)
    _, s, c, m = _sorted_inputs(best_scores, best_correct, has_match)
    t = _check_scores(thresholds, "thresholds")
    if t.ndim != 1:
        raise ValueError(f"thresholds must be one-dimensional, got shape {t.shape}")
    n = s.shape[0]
    ascending = s[::-1]
    n_accepted = n - np.searchsorted(ascending, t, side="left")
    tp, fp, acc_match = _accepted_counts(s, c, m, n_accepted)
    n_correct = int(c.sum())
    n_has_match = int(m.sum())
    rejected = n - n_accepted
    rej_match = n_has_match - acc_match
    if pr_convention == "vpr_bench":
        fn = n_correct - tp
        tn = rejected - fn
    elif pr_convention == "has_match":
        fn = rej_match
        tn = rejected - fn
    else:
        fn = n_has_match - tp
        tn = rejected - rej_match
    return tp, fp, tn, fn


def extended_precision(precision: PRPoints, recall: PRPoints) -> float:
    """VPR-Bench's extended precision ``EP = (P_R0 + R_P100) / 2`` of a PR curve from
    :func:`pr_curve` (start point first): ``P_R0`` is the precision at the lowest recall the
    method reaches (its strictest threshold, i.e. of its most confident matches), ``R_P100``
    the largest recall at precision 1, or 0 when even the most confident match is wrong
    (Ferrarini et al. 2020; Zaffar et al., VPR-Bench, 2021). It lies in [0, 1]: 1 when the
    most confident match is right and the whole curve holds precision 1."""
    p, r = np.asarray(precision)[1:], np.asarray(recall)[1:]  # without the start point
    if p.size == 0:
        return 0.0
    at_full = r[p == 1.0]
    return float((p[0] + (at_full.max() if at_full.size else 0.0)) / 2)


# ---------------------------------------------------------------------------- evaluation


def evaluate_top_k(
    top_scores: Float[np.ndarray, "nq k"],
    top_indices: Int[np.ndarray, "nq k"],
    query_ids: Int[np.ndarray, " nq"],
    db_ids: Int[np.ndarray, " ndb"],
    tolerance: int,
    *,
    pr_convention: PRConvention = "vpr_bench",
    ks: tuple[int, ...] = DEFAULT_KS,
) -> Evaluation:
    """All metrics from each query's top-K matches, ground truth ``|q - d| <= tolerance``
    on frame ids: :func:`evaluate_matches` with ``Tolerance``."""
    return evaluate_matches(
        top_scores,
        top_indices,
        Tolerance.of(query_ids, db_ids, tolerance),
        pr_convention=pr_convention,
        ks=ks,
    )


def _checked_top_k(
    top_scores, top_indices, truth: GroundTruth, pr_convention: str, ks: tuple[int, ...]
) -> tuple[np.ndarray, np.ndarray, tuple[int, ...]]:
    """(scores, indices, every K) of :func:`evaluate_matches`'s arguments, or ValueError
    naming what does not fit."""
    _check_convention(pr_convention)
    n_q, n_db = truth.n_queries, truth.n_db
    if n_q == 0:
        raise ValueError("no queries to evaluate: query_ids is empty")
    if n_db == 0:
        raise ValueError("no database frames to match against: db_ids is empty")
    scores = _check_scores(top_scores, "top_scores")
    idx = np.asarray(top_indices)
    if scores.ndim != 2 or scores.shape[0] != n_q or scores.shape[1] == 0:
        raise ValueError(
            f"top_scores must have shape ({n_q}, K>=1) to match query_ids, got {scores.shape}"
        )
    if idx.shape != scores.shape:
        raise ValueError(
            f"top_indices shape {idx.shape} differs from top_scores shape {scores.shape}"
        )
    if not np.all(scores[:, 1:] <= scores[:, :-1]):
        raise ValueError("top_scores rows must be sorted best first (non-increasing)")
    n_cols = scores.shape[1]
    all_ks = _all_ks(ks)
    if all_ks[0] < 1:
        raise ValueError(f"every K in ks must be >= 1, got {tuple(ks)}")
    need = min(all_ks[-1], n_db)
    if n_cols < need:
        raise ValueError(
            f"top-K holds {n_cols} matches per query but recall@{all_ks[-1]} needs {need}: "
            f"keep the top {need} (or more) per query"
        )
    return scores, idx, all_ks


def _recall_at_k(correct, has_match, ks: tuple[int, ...], n_db: int) -> dict[int, float]:
    """Recall@K per K in ``ks``, over the queries with a true match (K clipped to Ndb)."""
    n_has_match = int(has_match.sum())
    hit_by_rank = np.logical_or.accumulate(correct, axis=1)[has_match]  # drop unmatched queries
    return {
        k: float(hit_by_rank[:, min(k, n_db) - 1].sum() / n_has_match) if n_has_match else 0.0
        for k in ks
    }


def match_margin(
    top_scores: Float[np.ndarray, "nq k"],
    correct: Bool[np.ndarray, "nq k"],
    has_match: Bool[np.ndarray, " nq"],
) -> float:
    """Mean over the queries with a correct match of the best correct score minus the best
    wrong one among its top-K matches (scores sorted best first): positive where the first
    match is correct, by how much; negative where a wrong one wins, by how much. When no
    correct (or no wrong) match is among the K, the K-th score stands in for it: a bound.
    NaN without queries that have a match. It does not saturate where recall@1 does (every
    query right), so it tells apart settings recall@1 ties (docs/metrics.md)."""
    if not has_match.any():
        return math.nan
    last = top_scores[:, -1]
    best_correct = np.where(
        correct.any(axis=1), np.max(np.where(correct, top_scores, -np.inf), axis=1), last
    )
    best_wrong = np.where(
        (~correct).any(axis=1), np.max(np.where(correct, -np.inf, top_scores), axis=1), last
    )
    return float(np.mean((best_correct - best_wrong)[has_match]))


def evaluate_matches(
    top_scores: Float[np.ndarray, "nq k"],
    top_indices: Int[np.ndarray, "nq k"],
    truth: GroundTruth,
    *,
    pr_convention: PRConvention = "vpr_bench",
    ks: tuple[int, ...] = DEFAULT_KS,
) -> Evaluation:
    """All metrics from each query's top-K matches (docs/metrics.md) against any
    ground truth (``vpr_jax.data.ground_truth``: a tolerance on frame ids or explicit sets).

    ``top_scores[i]`` must be sorted best first and ``top_indices[i]`` hold database
    positions. Recall@K for every K in ``ks`` (1, 5 and 10 are always added) needs ``K >=
    min(k, Ndb)`` columns; with K >= Ndb, larger k are clipped to Ndb. Cost O(Nq K log)
    on top of the ground truth's own lookups.
    """
    scores, idx, all_ks = _checked_top_k(top_scores, top_indices, truth, pr_convention, ks)
    n_q, n_db = truth.n_queries, truth.n_db

    correct = truth.correct(idx)
    match = truth.has_match()
    best_scores = scores[:, 0]
    best_correct = correct[:, 0]

    precision, recall, thresholds = pr_curve(
        best_scores, best_correct, match, pr_convention=pr_convention
    )
    recall_at_1 = float(best_correct.sum() / n_q)
    precision_at_full_recall = float(precision[-1])
    auc_pr = float(np.sum(np.diff(recall) * (precision[1:] + precision[:-1]) / 2.0))
    recall_at_100p = float(recall[precision == 1.0].max())

    return Evaluation(
        recall_at_1=recall_at_1,
        precision_at_full_recall=precision_at_full_recall,
        auc_pr=auc_pr,
        recall_at_100_precision=recall_at_100p,
        pr_precision=precision,
        pr_recall=recall,
        pr_thresholds=thresholds,
        best_scores=best_scores.copy(),
        best_correct=best_correct.copy(),
        has_match=match,
        recall_at_k=_recall_at_k(correct, match, all_ks, n_db),
        pr_convention=pr_convention,
        extended_precision=extended_precision(precision, recall),
        margin=match_margin(scores, correct, match),
    )


def evaluate_similarity(
    similarity: Float[np.ndarray, "nq ndb"],
    query_ids: Int[np.ndarray, " nq"],
    db_ids: Int[np.ndarray, " ndb"],
    tolerance: int,
    **options,
) -> Evaluation:
    """All metrics from a full similarity matrix, higher = more similar; ``options``
    (``pr_convention``, ``ks``) as for :func:`evaluate_top_k`, which this calls.

    ``similarity`` is (n_queries, n_db): row i holds query i against every database frame.
    This is the TRANSPOSE of VPR_Tutorial's ``S`` (database x queries). Sorts each row (a
    stable sort: ties go to the lowest database index, as ``np.argmax`` picks the best
    match) and keeps the top ``max(ks + (10,))``.
    """
    sim = np.asarray(similarity)
    n_q = np.shape(query_ids)[0] if np.ndim(query_ids) == 1 else -1
    n_db = np.shape(db_ids)[0] if np.ndim(db_ids) == 1 else -1
    if sim.ndim != 2 or sim.shape != (n_q, n_db):
        raise ValueError(
            f"similarity must have shape (n_queries, n_db) = ({n_q}, {n_db}), got {sim.shape}"
            " (rows are queries: the transpose of VPR_Tutorial's S)"
        )
    if np.issubdtype(sim.dtype, np.floating) and np.isnan(sim).any():
        raise ValueError("similarity contains NaN: the descriptors or similarities are broken")
    # float64 is exact for float32 and integer scores, and negates unsigned ones correctly
    k = _all_ks(options.get("ks", DEFAULT_KS))[-1]
    top_i = np.argsort(-sim.astype(np.float64), axis=1, kind="stable")[:, :k]
    return evaluate_top_k(
        np.take_along_axis(sim, top_i, axis=1), top_i, query_ids, db_ids, tolerance, **options
    )
