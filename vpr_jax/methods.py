"""One season pair through one method: fit on training images, encode, match.

Pure computation, no files: the sweep runner writes what these return. Every method returns
one ``CellOutput`` per removed-PC count it was asked for (methods without that knob return
one cell with ``removed_pcs=0``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import numpy as np

from vpr_jax.config import SweepConfig
from vpr_jax.encoders import pca
from vpr_jax.matching import top_k_matches

TOP_K = 10  # enough for recall@10


class PairData(NamedTuple):
    db_season: str
    query_season: str
    train: np.ndarray  # (2 * n_train, 32, 64): training places of BOTH seasons
    db: np.ndarray  # (n_test, 32, 64) database season, test places
    query: np.ndarray  # (n_test, 32, 64) query season, same test places
    db_ids: np.ndarray  # original frame indices of the test places
    query_ids: np.ndarray


class CellOutput(NamedTuple):
    method: str
    removed_pcs: int
    top_scores: np.ndarray  # (n_queries, K) cosine scores, best first
    top_indices: np.ndarray  # (n_queries, K) indices into the database
    fit_seconds: float
    encode_ms_per_image: float
    basis_images: np.ndarray | None  # (m, 32, 64) what the method removed or learned, if any


def _timed(fn: Callable, *args):
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - start


def _encode_ms(encode: Callable, pair: PairData) -> tuple[np.ndarray, np.ndarray, float]:
    """Encode database and queries; ms per image measured on a warm (compiled) function."""
    encode(pair.db)  # compile for this shape
    db, seconds_db = _timed(encode, pair.db)
    query, seconds_q = _timed(encode, pair.query)
    ms = 1000 * (seconds_db + seconds_q) / (len(pair.db) + len(pair.query))
    return db, query, ms


def run_raw(pair: PairData, removed_pcs: tuple[int, ...], cfg: SweepConfig) -> list[CellOutput]:
    """Raw pixels, centred with the training mean; cosine does the L2 normalisation."""
    del removed_pcs
    mean, fit_s = _timed(lambda x: jax.numpy.mean(pca.flatten(x), axis=0), pair.train)
    db, query, ms = _encode_ms(jax.jit(lambda x: pca.flatten(x) - mean), pair)
    scores, idx = top_k_matches(query, db, TOP_K, block_size=cfg.matching.block_size)
    return [CellOutput("raw", 0, scores[0], idx[0], fit_s, ms, None)]


def run_pca(pair: PairData, removed_pcs: tuple[int, ...], cfg: SweepConfig) -> list[CellOutput]:
    """One PCA fit and one matching pass serve every removed-PC count.

    Matching scores coefficient suffixes (``starts=removed_pcs``), which equals zeroing the
    first k coefficients or, with ``pca.output=pixels``, mapping the kept ones back to pixels.
    """
    state, fit_s = _timed(lambda x: pca.fit_pca(x, solver=cfg.pca.solver), pair.train)
    n_components = state.components.shape[0]
    if cfg.pca.output == "pixels":
        outputs = []
        for k in removed_pcs:
            db, query, ms = _encode_ms(lambda x, k=k: pca.encode(state, x, k, "pixels"), pair)
            scores, idx = top_k_matches(query, db, TOP_K, block_size=cfg.matching.block_size)
            outputs.append((k, scores[0], idx[0], ms))
    else:
        db, query, ms = _encode_ms(lambda x: pca.project(state, x), pair)
        scores, idx = top_k_matches(query, db, TOP_K, starts=removed_pcs,
                                    block_size=cfg.matching.block_size)
        outputs = [(k, scores[i], idx[i], ms) for i, k in enumerate(removed_pcs)]
    components = np.asarray(state.components).reshape(n_components, *pair.train.shape[1:])
    n_show = cfg.tb.n_basis_images
    return [
        CellOutput("pca", k, s, i, fit_s, ms, components[: min(k, n_show)] if k else None)
        for k, s, i, ms in outputs
    ]


METHODS: dict[str, Callable[[PairData, tuple[int, ...], SweepConfig], list[CellOutput]]] = {
    "raw": run_raw,
    "pca": run_pca,
}

# Methods whose cells are indexed by a removed-PC count; the others run once with k = 0.
SWEEPS_REMOVED_PCS = {"pca"}
