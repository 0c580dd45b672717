"""Sequence matching speed against a straightforward numpy search timed in the same run.

    python benchmarks/bench_sequence.py [--repeats 3] [--ds 10] [--no-full-route] [--tiny]

The peer is tests/sequence_reference.py: openSeqSLAM's search written in numpy (a loop over
queries, then velocities and steps, each step vectorised over the database), the oracle the
tests check ``vpr_jax.evaluation.sequence`` against; this script checks the two agree here too.

Sizes, on the built-in route's raw pixels (cosine similarity of 2,048-pixel descriptors):
  seed test set   3,569 fall queries x 3,569 summer database frames
  full route      3,569 fall queries x every one of the route's 35,768 summer frames
                  (the sweep's split.database=all on the whole route)
Both searches start from the same similarity matrix; ours is timed warm (compilation
reported apart), and also from descriptors, computing the cosine block by block inside
(what the sweep runs: the full matrix is never held).
``--tiny`` (for the tests): 200 queries after ``common.TINY_SIZES``'s training stretch and
gap, a 1,000-frame "full route", one warm run.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from common import TINY_HELP, route_sizes, timed
from common import ratio_row as row
from peers import native_blas_process

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # tests/ holds the peer
from tests.sequence_reference import sequence_top_k_numpy  # noqa: E402
from vpr_jax.data.synthetic import synthetic_route  # noqa: E402
from vpr_jax.evaluation.sequence import sequence_top_k, sequence_top_k_cosine  # noqa: E402

FULL_ROUTE, TINY_FULL_ROUTE = 35768, 1000


def numpy_cosine(q: np.ndarray, d: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    return q @ d.T


def measure(queries, database, ds: int, repeats: int) -> dict:
    """Both searches on the same similarity matrix (seconds); ours also from descriptors,
    and the share of queries whose best match the two agree on."""
    sim = numpy_cosine(queries.astype(np.float64), database.astype(np.float64))
    sim32 = sim.astype(np.float32)
    first, ours = timed(lambda: sequence_top_k(sim32, ds), repeats)
    _, from_desc = timed(lambda: sequence_top_k_cosine(queries, database, ds), repeats)
    start = time.perf_counter()
    _, ref_idx = sequence_top_k_numpy(sim, ds)
    peer = time.perf_counter() - start
    _, idx = sequence_top_k(sim32, ds)
    return {
        "first": first,
        "ours": ours,
        "from_descriptors": from_desc,
        "peer": peer,
        "agree": float(np.mean(idx[:, 0] == ref_idx[:, 0])),
    }


def compare(name: str, queries, database, ds: int, repeats: int) -> None:
    m = measure(queries, database, ds, repeats)
    row(f"{name} ds={ds}", m["ours"], m["peer"], "numpy loop over queries", "< 1x")
    print(
        f"{'':<34} first call {m['first']:.2f} s (compiles); from descriptors, cosine "
        f"included: {m['from_descriptors']:.2f} s; best match agrees with numpy for "
        f"{m['agree']:.1%} of queries"
    )


def main() -> None:
    native_blas_process()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=None, help="warm runs (3; --tiny: 1)")
    parser.add_argument("--ds", type=int, default=10)
    parser.add_argument("--no-full-route", action="store_true")
    parser.add_argument("--tiny", action="store_true", help=TINY_HELP)
    args = parser.parse_args()
    if args.repeats is None:
        args.repeats = 1 if args.tiny else 3
    sizes = route_sizes(args.tiny)
    n_test = sizes["n_test"]
    full_route = TINY_FULL_ROUTE if args.tiny else FULL_ROUTE
    # the paper's test places: after its 2,500 training places and a gap of 100
    first_test = sizes["n_train"] + sizes["gap"]

    n_route = full_route if not args.no_full_route else first_test + n_test
    route = synthetic_route(n_route, ("summer", "fall"), seed=0)
    summer = route.images["summer"].reshape(n_route, -1)
    fall = route.images["fall"].reshape(n_route, -1)
    test = slice(first_test, first_test + n_test)
    compare(f"{n_test:,} x {n_test:,}", fall[test], summer[test], args.ds, args.repeats)
    if not args.no_full_route:
        compare(
            f"{n_test:,} x {full_route:,} (full)",
            fall[test],
            summer,
            args.ds,
            max(1, args.repeats - 2),
        )


if __name__ == "__main__":
    main()
