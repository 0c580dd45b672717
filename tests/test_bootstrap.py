"""The block bootstrap against plain loops over explicit resamples, and its coverage on a
simulated metric whose true value is known."""

from statistics import NormalDist

import numpy as np
import pytest
from sklearn.metrics import auc as auc_of
from sklearn.metrics import precision_recall_curve

from vpr_jax.evaluation import bootstrap
from vpr_jax.evaluation.metrics import PR_CONVENTIONS, pr_curve


def _cell(n=120, seed=0):
    rng = np.random.default_rng(seed)
    scores = np.round(rng.random(n), 2)  # rounded: ties in the scores
    has_match = rng.random(n) < 0.9
    correct = has_match & (rng.random(n) < scores)
    return scores, correct, has_match


def test_resamples_are_wrapped_blocks_of_consecutive_queries():
    n, length, resamples, seed = 23, 5, 7, 3
    counts = bootstrap.resample_counts(n, length, resamples, seed)
    starts = np.random.default_rng(seed).integers(0, n, size=(resamples, 5))
    for r in range(resamples):  # the plain loop: draw blocks one by one
        drawn = []
        for start in starts[r]:
            drawn += [(start + i) % n for i in range(length)]
        np.testing.assert_array_equal(counts[r], np.bincount(drawn[:n], minlength=n))
    assert np.all(counts.sum(axis=1) == n)


@pytest.mark.parametrize("convention", PR_CONVENTIONS)
def test_weighted_metrics_equal_the_metrics_of_the_resampled_queries(convention):
    scores, correct, has_match = _cell()
    counts = bootstrap.resample_counts(len(scores), 10, 5, seed=1)
    counts = np.concatenate([np.ones((1, len(scores)), np.int32), counts])
    auc = bootstrap.weighted_auc_pr(scores, correct, has_match, counts, convention)
    recall = bootstrap.weighted_recall_at_1(correct, counts)
    for r, w in enumerate(counts):  # plain loop: repeat each query as often as drawn
        s, c, m = (np.repeat(a, w) for a in (scores, correct, has_match))
        precision, rec, _ = pr_curve(s, c, m, pr_convention=convention)
        assert auc[r] == pytest.approx(np.trapezoid(precision, rec), abs=1e-12)
        assert recall[r] == pytest.approx(c.mean(), abs=1e-12)
    if convention == "vpr_bench":  # counts of one against scikit-learn's curve
        sk_precision, sk_recall, _ = precision_recall_curve(correct, scores)
        assert auc[0] == pytest.approx(auc_of(sk_recall, sk_precision), abs=1e-12)


def test_interval_covers_a_known_recall_on_correlated_queries():
    """Queries whose successes are correlated along the route (a latent AR(1) with
    coefficient 0.8, success when it is below the p-quantile): the 95% interval of the
    success rate should cover the true p in about 95% of simulated routes."""
    p, n, phi, trials = 0.6, 400, 0.8, 300
    rng = np.random.default_rng(0)
    covered = 0
    for t in range(trials):
        latent = np.empty(n)
        latent[0] = rng.normal()
        noise = rng.normal(size=n) * np.sqrt(1 - phi**2)
        for i in range(1, n):
            latent[i] = phi * latent[i - 1] + noise[i]
        correct = latent < NormalDist().inv_cdf(p)
        counts = bootstrap.resample_counts(n, 20, 1000, seed=t)
        low, high = bootstrap.interval(bootstrap.weighted_recall_at_1(correct, counts))
        covered += low <= p <= high
    assert 0.88 <= covered / trials <= 0.99


def test_paired_difference_labels():
    rng = np.random.default_rng(2)
    base = rng.random(450) < 0.6
    better = base | (rng.random(450) < 0.5)
    same = base.copy()
    same[:5] = ~same[:5]
    kw = dict(block_length=10, resamples=1000, seed=0)
    up = bootstrap.paired_recall_difference(better, base, **kw)
    assert (
        up.label == "better"
        and up.low > 0
        and up.value == pytest.approx(better.mean() - base.mean())
    )
    assert bootstrap.paired_recall_difference(base, better, **kw).label == "worse"
    assert bootstrap.paired_recall_difference(same, base, **kw).label == "no clear difference"
    with pytest.raises(ValueError, match="same queries"):
        bootstrap.paired_recall_difference(base[:10], base, **kw)
