"""The protocol fingerprint (results.csv ``protocol``): computed again here from the
definition in docs/metrics.md alone (JSON of the frame ids, ground truth, direction and
validation places; SHA-256), equal for the same data and split, different for another
tolerance, direction or frame list. That every row of a real sweep carries it is
tests/test_sweep.py's (it shares that module's sweep)."""

import hashlib
import json
import re

import numpy as np

from vpr_jax.config import SplitConfig
from vpr_jax.data.ground_truth import match_sets
from vpr_jax.data.pair import pair_data
from vpr_jax.data.route import Route
from vpr_jax.data.splits import make_split
from vpr_jax.evaluation.protocol import fingerprint, protocol_record

SPLIT = SplitConfig(n_train=60, n_test=30, gap=5)


def _route(frame_ids) -> Route:
    """Blank images: the fingerprint never reads pixels."""
    frame_ids = np.asarray(frame_ids, np.int64)
    blank = np.zeros((len(frame_ids), 32, 64), np.float32)
    return Route(frame_ids, {"summer": blank, "winter": blank.copy()})


def _fingerprint(route: Route, db="summer", query="winter", tolerance=2) -> str:
    pair = pair_data(route, make_split(route.frame_ids, SPLIT), db, query, "test", tolerance)
    return fingerprint(protocol_record(pair, benchmark=False))


def _by_the_docs(route: Route, db: str, query: str, tolerance: int) -> str:
    """docs/metrics.md's recipe, written from the text: the test and validation frame ids
    in order, the tolerance, the two seasons; sorted-key JSON without spaces; SHA-256."""
    split = make_split(route.frame_ids, SPLIT)
    test, val = route.frame_ids[split.test].tolist(), route.frame_ids[split.val].tolist()
    record = {
        "version": 1,
        "database_season": db,
        "query_season": query,
        "test": {"database": test, "queries": test, "ground_truth": {"tolerance": tolerance}},
        "validation": {"database": val, "queries": val, "ground_truth": {"tolerance": tolerance}},
    }
    text = json.dumps(record, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def test_the_fingerprint_follows_its_definition_and_sees_every_change():
    route = _route(np.arange(200) * 10 + 202)
    first = _fingerprint(route)
    a_test_place = make_split(route.frame_ids, SPLIT).test[5]
    assert re.fullmatch(r"[0-9a-f]{12}", first)
    assert first == _by_the_docs(route, "summer", "winter", 2)
    assert first == _fingerprint(_route(np.arange(200) * 10 + 202))  # the same data again
    changed = {
        "tolerance": _fingerprint(route, tolerance=1),
        "direction": _fingerprint(route, db="winter", query="summer"),
        "frame list": _fingerprint(_route(np.delete(np.arange(201) * 10 + 202, a_test_place))),
    }
    assert len({first, *changed.values()}) == 4, changed


def test_explicit_ground_truth_and_names_enter_a_benchmarks_fingerprint():
    route = _route(np.arange(200))
    pair = pair_data(route, make_split(route.frame_ids, SPLIT), "summer", "winter", "test", 1)
    n_q, n_db = len(pair.query_ids), len(pair.db_ids)
    sets = match_sets([[i] for i in range(n_q)], n_db)
    shifted = match_sets([[min(i + 1, n_db - 1)] for i in range(n_q)], n_db)
    as_bench = pair._replace(truth=sets, aligned_training=False)
    prints = {
        fingerprint(protocol_record(as_bench, benchmark=True)),
        fingerprint(protocol_record(as_bench._replace(truth=shifted), benchmark=True)),
        fingerprint(
            protocol_record(
                as_bench._replace(
                    names=as_bench.names._replace(db=np.array([f"x/{n}" for n in pair.names.db]))
                ),
                benchmark=True,
            )
        ),
    }
    assert len(prints) == 3
