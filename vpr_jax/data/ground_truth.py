"""Which database frames are correct matches of each query: the ground truth of a benchmark.

Two forms, with the same three questions answered (``has_match``, ``correct``, ``a_match``):

``Tolerance``
    Aligned routes: query frame ``q`` matches database frame ``d`` when ``|q - d| <=
    tolerance`` (frame ids). Nothing is stored per query; ``has_match`` searches a sorted copy
    of the database ids, O((Nq + Ndb) log Ndb). Every aligned source uses this fast path.
``MatchSets``
    Any benchmark: each query's correct database positions as a set, stored sparse (CSR:
    ``indptr`` (Nq + 1,), ``indices`` (nnz,) sorted within each row), as VPR-Bench's
    ``ground_truth_new.npy`` lists them or a radius search over positions finds them.
    ``correct`` looks the retrieved positions up in the sorted keys ``row * Ndb + index``:
    O(Nq K log nnz), never an (Nq, Ndb) matrix.

``Tolerance.sets()`` expresses an aligned route as sets; metrics computed either way agree
exactly (``tests/test_ground_truth.py``). Pure numpy, no IO.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from jaxtyping import Bool, Float, Int

__all__ = ["GroundTruth", "MatchSets", "Tolerance", "match_sets", "within_radius"]


def _as_ids(ids: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(ids)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional, got shape {arr.shape}")
    if np.issubdtype(arr.dtype, np.integer):
        return arr.astype(np.int64, copy=False)
    if np.issubdtype(arr.dtype, np.floating) and np.all(np.isfinite(arr)):
        if np.array_equal(arr, np.round(arr)):
            return arr.astype(np.int64)
    raise ValueError(f"{name} must hold integer frame ids, got dtype {arr.dtype}")


def _check_indices(indices: np.ndarray, n_queries: int, n_db: int) -> np.ndarray:
    idx = np.asarray(indices)
    if idx.ndim != 2 or idx.shape[0] != n_queries:
        raise ValueError(f"indices must have shape ({n_queries}, K), got {idx.shape}")
    if not np.issubdtype(idx.dtype, np.integer):
        raise ValueError(f"indices must be integers, got dtype {idx.dtype}")
    if idx.size and (idx.min() < 0 or idx.max() >= n_db):
        raise ValueError(
            f"indices must lie in [0, {n_db}) (database positions), got [{idx.min()}, {idx.max()}]"
        )
    return idx.astype(np.int64)


def _indptr(counts: np.ndarray) -> np.ndarray:
    return np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)


def _ranges(starts: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ranges ``starts[i] .. starts[i] + counts[i] - 1`` laid end to end: for every
    element, the range it belongs to and its position."""
    rows = np.repeat(np.arange(len(counts)), counts)
    return rows, starts[rows] + np.arange(rows.size) - _indptr(counts)[rows]


class Tolerance(NamedTuple):
    """Query ``i`` (frame ``query_ids[i]``) matches database position ``j`` (frame
    ``db_ids[j]``) when the frame ids differ by at most ``tolerance``."""

    query_ids: Int[np.ndarray, " nq"]
    db_ids: Int[np.ndarray, " ndb"]
    tolerance: int

    @classmethod
    def of(cls, query_ids, db_ids, tolerance: int) -> Tolerance:
        if isinstance(tolerance, bool) or not isinstance(tolerance, int | np.integer):
            raise ValueError(f"tolerance must be a non-negative integer, got {tolerance!r}")
        if tolerance < 0:
            raise ValueError(f"tolerance must be a non-negative integer, got {tolerance}")
        return cls(_as_ids(query_ids, "query_ids"), _as_ids(db_ids, "db_ids"), int(tolerance))

    @property
    def n_queries(self) -> int:
        return len(self.query_ids)

    @property
    def n_db(self) -> int:
        return len(self.db_ids)

    def _window(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        order = np.argsort(self.db_ids, kind="stable")
        d = self.db_ids[order]
        lo = np.searchsorted(d, self.query_ids - self.tolerance, side="left")
        hi = np.searchsorted(d, self.query_ids + self.tolerance, side="right")
        return order, lo, hi

    def has_match(self) -> Bool[np.ndarray, " nq"]:
        _, lo, hi = self._window()
        return hi > lo

    def correct(self, indices: Int[np.ndarray, "nq k"]) -> Bool[np.ndarray, "nq k"]:
        idx = _check_indices(indices, self.n_queries, self.n_db)
        return np.abs(self.db_ids[idx] - self.query_ids[:, None]) <= self.tolerance

    def a_match(self) -> Int[np.ndarray, " nq"]:
        """Per query the database position of the frame nearest its own (the lower on a
        tie; -1 without a match): the image a figure shows as "the right answer"."""
        if self.n_db == 0:
            return np.full(self.n_queries, -1, np.int64)
        order = np.argsort(self.db_ids, kind="stable")
        d = self.db_ids[order]
        at = np.searchsorted(d, self.query_ids)
        below, above = np.clip(at - 1, 0, len(d) - 1), np.clip(at, 0, len(d) - 1)
        gap = lambda pos: np.abs(d[pos] - self.query_ids)  # noqa: E731
        nearest = np.where(gap(below) <= gap(above), below, above)
        return np.where(gap(nearest) <= self.tolerance, order[nearest], -1)

    def sets(self) -> MatchSets:
        """The same ground truth as explicit sets."""
        order, lo, hi = self._window()
        rows, pos = _ranges(lo, hi - lo)
        return MatchSets.from_pairs(rows, order[pos], self.n_queries, self.n_db)

    def describe(self) -> str:
        return f"+-{self.tolerance} frames"


class MatchSets(NamedTuple):
    """Query ``i``'s correct database positions: ``indices[indptr[i]:indptr[i + 1]]``."""

    indptr: Int[np.ndarray, " nq_plus_1"]
    indices: Int[np.ndarray, " nnz"]
    n_db: int
    source: str = "match sets"  # what defined them (results.csv ``ground_truth``)

    @classmethod
    def of(cls, indptr, indices, n_db: int, source: str = "match sets") -> MatchSets:
        """Checked and normalised: each row sorted and without repeats."""
        indptr = np.asarray(indptr, np.int64)
        indices = np.asarray(indices, np.int64)
        if indptr.ndim != 1 or indptr.size < 1 or indptr[0] != 0 or np.any(np.diff(indptr) < 0):
            raise ValueError("indptr must start at 0 and never decrease")
        if indptr[-1] != indices.size:
            raise ValueError(f"indptr ends at {indptr[-1]} but there are {indices.size} indices")
        n_queries = indptr.size - 1
        rows = np.repeat(np.arange(n_queries), np.diff(indptr))
        return cls.from_pairs(rows, indices, n_queries, n_db, source)

    @classmethod
    def from_pairs(
        cls, rows, cols, n_queries: int, n_db: int, source: str = "match sets"
    ) -> MatchSets:
        """Sets from (query, database position) pairs in any order, repeats allowed."""
        cols = np.asarray(cols, np.int64)
        if cols.size and (cols.min() < 0 or cols.max() >= n_db):
            raise ValueError(
                f"match indices must lie in [0, {n_db}), got [{cols.min()}, {cols.max()}]"
            )
        stride = np.int64(max(n_db, 1))
        keys = np.unique(np.asarray(rows, np.int64) * stride + cols)  # sorted, no repeats
        rows, cols = np.divmod(keys, stride)
        return cls(_indptr(np.bincount(rows, minlength=n_queries)), cols, int(n_db), source)

    @property
    def n_queries(self) -> int:
        return len(self.indptr) - 1

    def row(self, i: int) -> np.ndarray:
        return self.indices[self.indptr[i] : self.indptr[i + 1]]

    def has_match(self) -> Bool[np.ndarray, " nq"]:
        return np.diff(self.indptr) > 0

    def correct(self, indices: Int[np.ndarray, "nq k"]) -> Bool[np.ndarray, "nq k"]:
        idx = _check_indices(indices, self.n_queries, self.n_db)
        stride = np.int64(max(self.n_db, 1))
        keys = np.repeat(np.arange(self.n_queries), np.diff(self.indptr)) * stride + self.indices
        wanted = np.arange(self.n_queries)[:, None] * stride + idx
        if keys.size == 0:  # no query has a correct match
            return np.zeros(idx.shape, bool)
        at = np.searchsorted(keys, wanted)
        return (at < keys.size) & (keys[np.minimum(at, keys.size - 1)] == wanted)

    def a_match(self) -> Int[np.ndarray, " nq"]:
        """Per query its first (lowest) correct database position, -1 without one."""
        first = np.full(self.n_queries, -1, np.int64)
        has = self.has_match()
        first[has] = self.indices[self.indptr[:-1][has]]
        return first

    def take(self, queries: Int[np.ndarray, " m"]) -> MatchSets:
        """The ground truth of the queries at positions ``queries`` (in that order)."""
        q = np.asarray(queries, np.int64)
        counts = np.diff(self.indptr)[q]
        _, pos = _ranges(self.indptr[q], counts)
        return MatchSets(
            indptr=_indptr(counts), indices=self.indices[pos], n_db=self.n_db, source=self.source
        )

    def sets(self) -> MatchSets:
        return self

    def describe(self) -> str:
        return self.source


GroundTruth = Tolerance | MatchSets


def match_sets(rows: Sequence[Sequence[int]], n_db: int, source: str = "match sets") -> MatchSets:
    """Sets from one list of correct database positions per query."""
    counts = np.fromiter((len(r) for r in rows), np.int64, len(rows))
    flat = np.fromiter((int(j) for r in rows for j in r), np.int64, int(counts.sum()))
    return MatchSets.of(_indptr(counts), flat, n_db, source)


def within_radius(
    query_xy: Float[np.ndarray, "nq 2"], db_xy: Float[np.ndarray, "ndb 2"], radius: float
) -> MatchSets:
    """Each query's database positions within ``radius`` (Euclidean, e.g. metres in UTM).

    A uniform grid of ``radius``-sized cells: a query's matches lie in its own cell or one of
    the eight around it, so only those candidates are measured. Memory and time grow with
    the number of candidate pairs, never with Nq x Ndb.
    """
    q = np.asarray(query_xy, np.float64)
    d = np.asarray(db_xy, np.float64)
    if not radius > 0:
        raise ValueError(f"radius must be positive, got {radius}")
    if q.ndim != 2 or q.shape[1] != 2 or d.ndim != 2 or d.shape[1] != 2:
        raise ValueError(f"positions must be (n, 2), got {q.shape} and {d.shape}")
    origin = np.minimum(q.min(axis=0), d.min(axis=0)) if len(q) and len(d) else np.zeros(2)
    cell_d = np.floor((d - origin) / radius).astype(np.int64)
    cell_q = np.floor((q - origin) / radius).astype(np.int64)
    width = int(max(cell_d[:, 1].max(initial=0), cell_q[:, 1].max(initial=0))) + 3
    key_d = (cell_d[:, 0] + 1) * width + (cell_d[:, 1] + 1)
    order = np.argsort(key_d, kind="stable")
    sorted_keys = key_d[order]
    pairs_q, pairs_d = [], []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            key = (cell_q[:, 0] + 1 + dx) * width + (cell_q[:, 1] + 1 + dy)
            lo = np.searchsorted(sorted_keys, key, side="left")
            hi = np.searchsorted(sorted_keys, key, side="right")
            rows, pos = _ranges(lo, hi - lo)
            near = np.sum((q[rows] - d[order[pos]]) ** 2, axis=1) <= radius * radius
            pairs_q.append(rows[near])
            pairs_d.append(order[pos][near])
    return MatchSets.from_pairs(
        np.concatenate(pairs_q), np.concatenate(pairs_d), len(q), len(d), f"within {radius:g} m"
    )
