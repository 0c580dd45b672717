"""A fingerprint of what a number was measured on (results.csv ``protocol``): which images
are the database and the queries, in which order, which matches count as correct, which
season is the database, and which places validate. Two results with the same fingerprint
were measured on the same protocol; docs/metrics.md spells out the record, so another
implementation can compute it.

The record, as JSON (keys sorted, no spaces, UTF-8), hashed with SHA-256 (the first 12 hex
digits are the fingerprint):

- ``version``: 1;
- ``database_season``, ``query_season``: the direction (a benchmark's: ``ref``, ``query``);
- ``test`` and ``validation``, each with ``database`` and ``queries``: the images in the
  order they are scored, as frame ids (integers) where they are places of an aligned route,
  as names (the file's path relative to ``data.root``) where they are a benchmark's images;
  and ``ground_truth``: ``{"tolerance": k}`` for frame ids within k, or ``{"sets": [[j,
  ...], ...]}``, query i's correct database positions (sorted) for explicit ground truth.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np

from vpr_jax.data.ground_truth import GroundTruth, Tolerance
from vpr_jax.data.pair import PairData

VERSION = 1
FINGERPRINT_DIGITS = 12


def _truth(truth: GroundTruth) -> dict:
    if isinstance(truth, Tolerance):
        return {"tolerance": int(truth.tolerance)}
    return {"sets": [truth.row(i).tolist() for i in range(truth.n_queries)]}


def _images(ids: np.ndarray, names: np.ndarray, by_name: bool) -> list:
    return [str(n) for n in names] if by_name else [int(i) for i in ids]


def protocol_record(pair: PairData, benchmark: bool) -> dict:
    """The record the fingerprint hashes (module docstring). ``benchmark``: the test images
    are a benchmark's (named), not an aligned route's places (frame ids); the validation
    places are the route's when the pair trains on aligned places, else the benchmark's."""
    names = pair.names
    val_by_name = not pair.aligned_training
    return {
        "version": VERSION,
        "database_season": pair.db_season,
        "query_season": pair.query_season,
        "test": {
            "database": _images(pair.db_ids, names.db, benchmark),
            "queries": _images(pair.query_ids, names.query, benchmark),
            "ground_truth": _truth(pair.truth),
        },
        "validation": {
            "database": _images(pair.val_db_ids, names.val_db, val_by_name),
            "queries": _images(pair.val_query_ids, names.val_query, val_by_name),
            "ground_truth": _truth(pair.val_truth),
        },
    }


def fingerprint(record: dict) -> str:
    """The first ``FINGERPRINT_DIGITS`` hex digits of the SHA-256 of the record's JSON."""
    text = json.dumps(record, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:FINGERPRINT_DIGITS]


def describe_protocol(pair: PairData, benchmark: bool) -> str:
    """One line: the direction, the test and validation sizes, how images are named and
    what counts as correct."""
    kind = "images by file name" if benchmark else "places by frame id"
    return (
        f"{pair.db_season} database, {pair.query_season} queries: {len(pair.query_ids):,} "
        f"queries against {len(pair.db_ids):,} {kind}, correct within "
        f"{pair.truth.describe()}; validation {len(pair.val_query_ids):,} queries against "
        f"{len(pair.val_db_ids):,}"
    )
