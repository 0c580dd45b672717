"""One season pair as every method sees it: the training images, the database and queries
of the test places, the validation places, and the ground truth of both. Built from an
aligned route and its split (``pair_data``) or from a benchmark (``benchmark_pair``)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vpr_jax.config import SweepConfig
from vpr_jax.data.benchmark import Benchmark
from vpr_jax.data.ground_truth import GroundTruth, Tolerance
from vpr_jax.data.route import Route
from vpr_jax.data.splits import Split
from vpr_jax.host_arrays import stack_rows, take


class Names(NamedTuple):
    """What each image of a pair is called outside the suite (``Route.names``): (n,) text
    arrays, in the rows of ``PairData``'s database, queries and validation places."""

    db: np.ndarray
    query: np.ndarray
    val_db: np.ndarray
    val_query: np.ndarray


class PairData(NamedTuple):
    """One pair's images and ground truth: what every method fits on and is scored with.

    Aligned routes (``pair_data``): ``train`` holds the training places of
    both seasons back to back, row i of each half one place (``aligned_training``), and the
    validation places are aligned the same way. Unaligned benchmarks
    (``benchmark_pair``) train on their database images, or on an aligned
    route's training places (``data.train_source``).
    """

    db_season: str
    query_season: str
    train: np.ndarray  # (n_train_images, 32, 64)
    db: np.ndarray  # (n_db, 32, 64) database season, test places (or every frame)
    query: np.ndarray  # (n_test, 32, 64) query season, test places
    db_ids: np.ndarray  # route positions of the database images (frame ids: sequences)
    query_ids: np.ndarray
    truth: GroundTruth  # correct database positions of each query
    val_db: np.ndarray  # (n_val_db, 32, 64): the validation database
    val_query: np.ndarray  # (n_val_query, 32, 64): the validation queries
    val_db_ids: np.ndarray
    val_query_ids: np.ndarray
    val_truth: GroundTruth
    aligned_training: bool = True  # train (and val) are two seasons' aligned places
    names: Names | None = None  # the images' names: export and outside descriptors use them
    protocol: str = ""  # the fingerprint of what it is scored on (evaluation.protocol)

    @property
    def val(self) -> np.ndarray:
        """The images the auto-encoders' early stopping scores: the validation places of
        both seasons, database first (aligned pairs), or, trained on a benchmark's database,
        the held-out validation queries (the database is the training set)."""
        if not self.aligned_training:
            return self.val_query
        return np.concatenate([self.val_db, self.val_query])

    @property
    def name(self) -> str:
        return f"{self.db_season}-{self.query_season}"

    @property
    def aligned_train(self) -> tuple[np.ndarray, np.ndarray]:
        """(database season, query season) training images: row i of both shows the same
        place (the same frame id: seasons are aligned by frame id when loaded)."""
        if not self.aligned_training:
            raise ValueError(f"pair {self.name} has no aligned training places")
        n = len(self.train) // 2
        return self.train[:n], self.train[n:]


def with_train_places(pair: PairData, places: int | None) -> PairData:
    """The pair fitted on ``places`` of its training places, spread evenly over them (both
    seasons' same places where aligned; a benchmark trained on its database: that many of
    its database images); the validation and test places are unchanged. None: all."""
    if places is None:
        return pair
    seasons = pair.aligned_train if pair.aligned_training else (pair.train,)
    n = len(seasons[0])
    if places > n:
        raise ValueError(f"split.train_places={places} exceeds the {n} training places")
    keep = np.unique(np.linspace(0, n - 1, places).round().astype(int))
    return pair._replace(train=np.concatenate([s[keep] for s in seasons]))


def pair_data(
    route: Route, split: Split, db: str, query: str, database: str, tolerance: int
) -> PairData:
    """Images of one pair of an aligned route, ground truth ``|i - j| <= tolerance`` on
    frame ids; ``database="all"`` matches the queries against every frame of the database
    season (training places included), not only its test places."""
    images = route.images
    everything = database == "all"  # the season's own array: no copy of the whole route
    # Every array gathered straight into aligned memory, which XLA reads in place.
    db_ids = route.frame_ids if everything else route.frame_ids[split.test]
    query_ids, val_ids = route.frame_ids[split.test], route.frame_ids[split.val]
    return PairData(
        db_season=db,
        query_season=query,
        train=stack_rows([(images[db], split.train), (images[query], split.train)]),
        db=images[db] if everything else take(images[db], split.test),
        query=take(images[query], split.test),
        db_ids=db_ids,
        query_ids=query_ids,
        truth=Tolerance.of(query_ids, db_ids, tolerance),
        val_db=take(images[db], split.val),
        val_query=take(images[query], split.val),
        val_db_ids=val_ids,
        val_query_ids=val_ids,
        val_truth=Tolerance.of(val_ids, val_ids, tolerance),
        names=Names(
            db=route.names(db) if everything else route.names(db)[split.test],
            query=route.names(query)[split.test],
            val_db=route.names(db)[split.val],
            val_query=route.names(query)[split.val],
        ),
    )


def benchmark_pair(
    bench: Benchmark, route: Route | None, split: Split | None, cfg: SweepConfig
) -> PairData:
    """A benchmark's one pair. Its queries are scored against its database with its own
    ground truth. The encoders fit on the training places of ``route`` (both of
    ``data.seasons``, aligned; they validate on its validation places), or, without one, on
    the database images, validating on the last ``split.val_fraction`` of the queries
    (held out from the test: nothing is chosen on test queries)."""
    db, query = bench.pair
    if route is not None:
        a, b = route.seasons
        val_ids = route.frame_ids[split.val]
        return PairData(
            db_season=db,
            query_season=query,
            train=stack_rows([(route.images[a], split.train), (route.images[b], split.train)]),
            db=bench.db,
            query=bench.query,
            db_ids=bench.db_ids,
            query_ids=bench.query_ids,
            truth=bench.truth,
            val_db=take(route.images[a], split.val),
            val_query=take(route.images[b], split.val),
            val_db_ids=val_ids,
            val_query_ids=val_ids,
            val_truth=Tolerance.of(val_ids, val_ids, cfg.tolerance),
            names=Names(
                db=bench.db_names,
                query=bench.query_names,
                val_db=route.names(a)[split.val],
                val_query=route.names(b)[split.val],
            ),
        )
    n_query = len(bench.query)
    n_val = min(max(1, round(cfg.split.val_fraction * n_query)), n_query - 1)
    test, val = np.arange(n_query - n_val), np.arange(n_query - n_val, n_query)
    return PairData(
        db_season=db,
        query_season=query,
        train=bench.db,
        db=bench.db,
        query=take(bench.query, test),
        db_ids=bench.db_ids,
        query_ids=bench.query_ids[test],
        truth=bench.truth.take(test),
        val_db=bench.db,
        val_query=take(bench.query, val),
        val_db_ids=bench.db_ids,
        val_query_ids=bench.query_ids[val],
        val_truth=bench.truth.take(val),
        aligned_training=False,
        names=Names(
            db=bench.db_names,
            query=bench.query_names[test],
            val_db=bench.db_names,
            val_query=bench.query_names[val],
        ),
    )
