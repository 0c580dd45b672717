"""The in-memory form of a benchmark that is not frame-aligned: a database, queries and
each query's correct database images as sets (``vpr_jax.data.ground_truth.MatchSets``).

Sources that produce one: ``vpr_bench`` (VPR-Bench's ``ref/``, ``query/`` and
``ground_truth_new.npy``, ``vpr_jax.data.vpr_bench``), ``positions`` (GPS-tagged database and
queries, matches within ``data.radius_m``, ``vpr_jax.data.positions``) and ``nordland_star``
(VPR-Bench's Nordland partition of the 64x32 release, ``star_partition`` below).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vpr_jax.data.ground_truth import MatchSets, Tolerance
from vpr_jax.data.route import Route

STAR_QUERY_STEP = 10  # Nordland*: every 10th summer frame is a query
STAR_TOLERANCE = 1  # ... matching the winter references within +-1 frame


class Benchmark(NamedTuple):
    """A database and queries of one benchmark, with its ground truth.

    ``db_ids`` / ``query_ids``: the images' positions along the route (frame ids for
    Nordland, file order otherwise): sequence matching breaks its sequences where they jump.
    """

    source: str
    db_name: str  # what the database side is called: ref, database, winter
    query_name: str
    db: np.ndarray  # (n_db, 32, 64) float32 in [0, 1]
    query: np.ndarray  # (n_query, 32, 64)
    truth: MatchSets
    db_ids: np.ndarray
    query_ids: np.ndarray
    db_names: np.ndarray  # (n_db,) each image's path relative to data.root (Route.names)
    query_names: np.ndarray

    @property
    def pair(self) -> tuple[str, str]:
        return self.db_name, self.query_name


def star_partition(route: Route, db: str = "winter", query: str = "summer") -> Benchmark:
    """VPR-Bench's Nordland* from an aligned route of the clean frames: every frame of the
    ``db`` season is a reference, every 10th frame of ``query`` a query, and a query's
    correct references lie within +-1 position in the frame list (not +-1 frame id: the
    clean list skips its gaps as VPR-Bench's files do)."""
    n = len(route)
    picks = np.arange(0, n, STAR_QUERY_STEP)
    truth = Tolerance.of(picks, np.arange(n), STAR_TOLERANCE).sets()
    return Benchmark(
        source="nordland_star",
        db_name=db,
        query_name=query,
        db=route.images[db],
        query=route.images[query][picks],
        truth=truth._replace(source=f"+-{STAR_TOLERANCE} frame (Nordland*)"),
        db_ids=route.frame_ids,
        query_ids=route.frame_ids[picks],
        db_names=route.names(db),
        query_names=route.names(query)[picks],
    )
