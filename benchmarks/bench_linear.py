"""Linear-method speed on the paper's sizes, every figure a ratio to a peer timed in this run.

    python benchmarks/bench_linear.py [--repeats 3] [--tiny]

Sizes: a 5,000 x 2,048 training matrix (2,500 frames of two seasons of the built-in route)
and 3,569 queries x 3,569 database images. Times are medians of warm runs (compilation
excluded; it is reported separately). Goals:
  PCA fit vs scikit-learn PCA(svd_solver="covariance_eigh")      <= 1.0x
  PCA fit of 100 components vs PCA(100, svd_solver="randomized") <= 1.0x
    and vs the full covariance_eigh                              <= 0.35x
  whole removed-PC sweep (6 counts) vs one count                 <= 1.2x
  matching (running top-10) vs numpy brute force                 <= 1.2x
The scikit-learn and numpy peers run in a fresh process without OPENBLAS_CORETYPE /
OPENBLAS_L2_SIZE (``peers.py``); the dense-metrics peer is numpy indexing, in this process.
and, at the full route's size (3,569 queries, top-10 of a 35,768-frame database), the
metrics against a numpy peer that builds the dense (queries x database) ground truth.
``--tiny`` (for the tests): ``common.TINY_SIZES``, a 2,000-frame database for the metrics,
one warm run, the peers on the same tiny data, in this process.
"""

from __future__ import annotations

import argparse

import jax
import numpy as np
from common import TINY_HELP, paper_route, route_sizes, timed
from common import ratio_row as row
from peers import FORCING, ours_report, run_peer

from vpr_jax.encoders import pca
from vpr_jax.evaluation.matching import top_k_matches
from vpr_jax.evaluation.metrics import evaluate_top_k

REMOVED_PCS = (0, 5, 10, 20, 50, 100)
FULL_ROUTE, TINY_ROUTE = 35_768, 2_000  # the metrics' database


def dense_metrics(top_idx, query_ids, db_ids, tolerance: int) -> tuple[float, float]:
    """recall@1 and recall@10 from the dense (queries x database) ground-truth matrix."""
    truth = np.abs(query_ids[:, None] - db_ids[None, :]) <= tolerance
    has = truth.any(axis=1)
    hit = np.take_along_axis(truth, top_idx, axis=1)
    return float(hit[:, 0].mean()), float(hit.any(axis=1)[has].mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=None, help="warm runs (3; --tiny: 1)")
    parser.add_argument("--tiny", action="store_true", help=TINY_HELP)
    args = parser.parse_args()
    if args.repeats is None:
        args.repeats = 1 if args.tiny else 3
    tiny = args.tiny

    train, db, query = paper_route(**route_sizes(tiny))
    print(
        f"jax {jax.__version__} on {jax.devices()[0].platform}; train {train.shape}, "
        f"queries {query.shape[0]} x database {db.shape[0]}\n"
    )

    full = run_peer("pca_covariance_eigh", args.repeats, tiny)
    print(f"peers' BLAS (run without {', '.join(FORCING)}): {full['blas']}")
    print(f"ours: {ours_report()}\n")
    first, ours = timed(lambda: pca.fit_pca(train, solver="covariance"), args.repeats)
    row("PCA fit", ours, full["seconds"], "sklearn covariance_eigh", "<= 1.0x")
    print(f"{'':<34} first call incl. compilation {first:.3f} s")
    _, ours = timed(lambda: pca.fit_pca(train, 100), args.repeats)
    row(
        "PCA fit, 100 components",
        ours,
        run_peer("pca_randomized_100", args.repeats, tiny)["seconds"],
        "sklearn randomized",
        "<= 1.0x",
    )
    row("  the same", ours, full["seconds"], "sklearn covariance_eigh", "<= 0.35x")

    state = pca.fit_pca(train, max(REMOVED_PCS))

    def removed_pc_sweep(ks):
        return top_k_matches(
            pca.suffix_descriptors(state, query), pca.suffix_descriptors(state, db), 10, starts=ks
        )

    _, all_k = timed(lambda: removed_pc_sweep(REMOVED_PCS), args.repeats)
    _, one_k = timed(lambda: removed_pc_sweep((50,)), args.repeats)
    row(f"removed-PC sweep, {len(REMOVED_PCS)} counts", all_k, one_k, "one count (k=50)", "<= 1.2x")
    print(f"{'':<34} encode + match only; each count adds one elementwise pass and a top-K")
    print(f"{'':<34} over the {query.shape[0]} x {db.shape[0]} scores (the size of its ranking)")

    def pair_pipeline(ks):
        fitted = pca.fit_pca(train, max(ks))
        return top_k_matches(
            pca.suffix_descriptors(fitted, query), pca.suffix_descriptors(fitted, db), 10, starts=ks
        )

    _, all_k = timed(lambda: pair_pipeline(REMOVED_PCS), args.repeats)
    _, one_k = timed(lambda: pair_pipeline((50,)), args.repeats)
    row("  the same with the PCA fit", all_k, one_k, "fit + one count", "<= 1.5x")

    _, ours = timed(lambda: top_k_matches(query, db, 10), args.repeats)
    row(
        "matching, top-10 cosine",
        ours,
        run_peer("numpy_top_k", args.repeats, tiny)["seconds"],
        "numpy brute force",
        "<= 1.2x",
    )

    rng = np.random.default_rng(0)  # route-sized top-10 lists with ~30% true matches
    n_db, n_q = TINY_ROUTE if tiny else FULL_ROUTE, query.shape[0]
    db_ids, query_ids = rng.permutation(n_db) + 1, np.arange(1, n_db + 1, 10)[:n_q]
    where = np.empty(n_db + 1, np.int64)
    where[db_ids] = np.arange(n_db)
    top_idx = np.where(
        rng.random((n_q, 10)) < 0.3, where[query_ids][:, None], rng.integers(0, n_db, (n_q, 10))
    )
    top_scores = -np.sort(-rng.random((n_q, 10)), axis=1)
    _, ours = timed(lambda: evaluate_top_k(top_scores, top_idx, query_ids, db_ids, 2), args.repeats)
    _, peer = timed(lambda: dense_metrics(top_idx, query_ids, db_ids, 2), args.repeats)
    row(f"metrics, {n_q} top-10 lists of {n_db}", ours, peer, "numpy dense ground truth", "<= 1.0x")

    both = np.concatenate([db, query])
    _, enc = timed(lambda: pca.suffix_descriptors(state, both), args.repeats)
    print(
        f"\n{'PCA encode (100 + residual)':<34} {1000 * enc / len(both):9.4f} ms per image "
        f"(paper's Table 5 baseline: 0.1 ms)"
    )


if __name__ == "__main__":
    main()
