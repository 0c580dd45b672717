"""Confidence intervals for a cell's metrics: a circular block bootstrap over queries.

Neighbouring places look alike, so neighbouring queries succeed or fail together and a
bootstrap that resamples single queries would claim too much certainty. A resample here is
``ceil(n / L)`` blocks of ``L`` consecutive queries (in route order), each starting at a
uniformly drawn query and wrapping around the end (Politis & Romano's circular block
bootstrap: every query is equally likely to be drawn), cut to n queries. ``L`` is
``bootstrap.block_length`` (default 10 places) or the sequence length ds when that is
longer, since a sequence's score shares ds - 1 frames with its neighbour's.

A resample is stored as each query's count (how often it was drawn), so every statistic is a
weighted version of the metric in ``vpr_jax.evaluation.metrics``: recall@1 is the weighted
fraction of correct best matches, AUC-PR the trapezoidal area under the weighted
single-best-match PR curve (the exact curve of the resampled queries: a query drawn twice is
accepted twice at its threshold). Intervals are the 2.5th and 97.5th percentiles of 1,000
resamples; a paired difference draws the same resamples for two methods on the same queries,
so what the two have in common cancels. Vectorised numpy, so the intervals add little to a
cell's time.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

LEVEL = 0.95  # the intervals' coverage


class Interval(NamedTuple):
    low: float
    high: float


class Difference(NamedTuple):
    """A method's metric minus the baseline's on the same queries, with its interval."""

    value: float
    low: float
    high: float

    @property
    def label(self) -> str:
        """better / worse when the interval excludes 0, else no clear difference."""
        if self.low > 0:
            return "better"
        if self.high < 0:
            return "worse"
        return "no clear difference"


def resample_counts(n: int, block_length: int, resamples: int, seed: int) -> np.ndarray:
    """(resamples, n) int32: how often each of n queries is drawn in each resample."""
    if n < 1 or block_length < 1 or resamples < 1:
        raise ValueError(
            f"need n, block_length, resamples >= 1, got {n}, {block_length}, {resamples}"
        )
    length = min(block_length, n)
    n_blocks = -(-n // length)
    rng = np.random.default_rng(seed)
    starts = rng.integers(0, n, size=(resamples, n_blocks))
    drawn = (starts[:, :, None] + np.arange(length)).reshape(resamples, -1)[:, :n] % n
    flat = (np.arange(resamples)[:, None] * n + drawn).ravel()
    return np.bincount(flat, minlength=resamples * n).reshape(resamples, n).astype(np.int32)


def weighted_recall_at_1(correct: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Fraction of drawn queries whose best match is correct, per resample."""
    return counts @ np.asarray(correct, np.float64) / counts.sum(axis=1)


def weighted_auc_pr(
    scores: np.ndarray,
    correct: np.ndarray,
    has_match: np.ndarray,
    counts: np.ndarray,
    pr_convention: str = "vpr_bench",
) -> np.ndarray:
    """AUC-PR of each resample (``vpr_jax.evaluation.metrics``' single-best-match curve, trapezoids
    over recall from the start point (0, 1)); counts of all ones give ``metrics``' value.

    Thresholds are every distinct score; a query of count 0 adds a point equal to the one
    before it, which adds no area, so the curve of a resample needs no compaction. Resamples
    are scored ``RESAMPLE_CHUNK`` at a time: each is its own row, and all at once would hold
    a dozen (resamples, queries) float64 arrays in memory together.
    """
    order = np.argsort(-np.asarray(scores), kind="stable")
    s = np.asarray(scores)[order]
    c = np.asarray(correct, np.float64)[order]
    m = np.asarray(has_match, np.float64)[order]
    return np.concatenate(
        [
            _auc_pr_of_resamples(s, c, m, counts[i : i + RESAMPLE_CHUNK, order], pr_convention)
            for i in range(0, len(counts), RESAMPLE_CHUNK)
        ]
    )


RESAMPLE_CHUNK = 128


def _auc_pr_of_resamples(s, c, m, counts, pr_convention: str) -> np.ndarray:
    """``weighted_auc_pr`` of resamples ``counts`` (rows) over queries sorted by score."""
    w = counts.astype(np.float64)
    last = np.flatnonzero(np.append(s[1:] != s[:-1], True))  # ties enter together
    accepted = np.cumsum(w, axis=1)[:, last]
    tp = np.cumsum(w * c, axis=1)[:, last]
    acc_match = np.cumsum(w * m, axis=1)[:, last]
    n_correct, n_match = tp[:, -1:], acc_match[:, -1:]
    if pr_convention == "vpr_bench":
        denom = np.broadcast_to(n_correct, tp.shape)
    elif pr_convention == "has_match":
        denom = tp + (n_match - acc_match)
    elif pr_convention == "vpr_tutorial":
        denom = np.broadcast_to(n_match, tp.shape)
    else:
        raise ValueError(f"unknown pr_convention {pr_convention!r}")
    recall = np.divide(tp, denom, out=np.zeros_like(tp), where=denom > 0)
    precision = np.divide(tp, accepted, out=np.ones_like(tp), where=accepted > 0)
    ones = np.ones((len(w), 1))
    recall = np.concatenate([0 * ones, recall], axis=1)
    precision = np.concatenate([ones, precision], axis=1)
    return np.sum(np.diff(recall, axis=1) * (precision[:, 1:] + precision[:, :-1]) / 2, axis=1)


def interval(values: np.ndarray) -> Interval:
    tail = 100 * (1 - LEVEL) / 2
    low, high = np.percentile(values, [tail, 100 - tail])
    return Interval(float(low), float(high))


class CellIntervals(NamedTuple):
    recall_at_1: Interval
    auc_pr: Interval


def cell_intervals(
    scores,
    correct,
    has_match,
    *,
    block_length: int,
    resamples: int,
    seed: int,
    pr_convention: str = "vpr_bench",
) -> CellIntervals:
    """95% intervals of recall@1 and AUC-PR of one cell's queries (in route order)."""
    counts = resample_counts(len(scores), block_length, resamples, seed)
    return CellIntervals(
        interval(weighted_recall_at_1(correct, counts)),
        interval(weighted_auc_pr(scores, correct, has_match, counts, pr_convention)),
    )


def paired_recall_difference(
    correct: np.ndarray,
    baseline_correct: np.ndarray,
    *,
    block_length: int,
    resamples: int,
    seed: int,
) -> Difference:
    """recall@1 of a method minus the baseline's on the same queries (same order), with a
    95% interval from the same block resamples for both."""
    correct, baseline_correct = np.asarray(correct), np.asarray(baseline_correct)
    if correct.shape != baseline_correct.shape:
        raise ValueError(
            f"paired cells need the same queries, got {correct.shape} and {baseline_correct.shape}"
        )
    counts = resample_counts(len(correct), block_length, resamples, seed)
    diff = weighted_recall_at_1(correct, counts) - weighted_recall_at_1(baseline_correct, counts)
    low, high = interval(diff)
    return Difference(float(np.mean(correct) - np.mean(baseline_correct)), low, high)
