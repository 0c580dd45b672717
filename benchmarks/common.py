"""Helpers shared by the benchmark scripts: warm timing, the seed's training matrix, rows."""

from __future__ import annotations

import statistics
import time

import jax
import numpy as np

from vpr_jax.data.synthetic import synthetic_route


def timed(fn, repeats: int) -> tuple[float, float]:
    """(first call seconds, median of ``repeats`` further calls); 0 repeats: first only."""
    start = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - start
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - start)
    return first, statistics.median(runs) if runs else first


def seed_route(n_train: int = 2500, gap: int = 100, n_test: int = 3569):
    """Summer and fall of the built-in route: the seed's training and test sizes.

    Returns (train (2 n_train, 2048): both seasons' training places, database (n_test,
    2048) summer, queries (n_test, 2048) fall), float32 in [0, 1].
    """
    route = synthetic_route(n_train + gap + n_test, ("summer", "fall"), seed=0)
    summer, fall = route.images["summer"], route.images["fall"]
    train = np.concatenate([summer[:n_train], fall[:n_train]]).reshape(2 * n_train, -1)
    return (
        train,
        summer[n_train + gap :].reshape(n_test, -1),
        fall[n_train + gap :].reshape(n_test, -1),
    )


def ratio_row(name: str, ours: float, peer: float, peer_name: str, goal: str) -> None:
    print(
        f"{name:<34} {ours:9.4f} s  {peer_name:<30} {peer:9.4f} s  "
        f"ratio {ours / peer:5.2f}x  (goal {goal})"
    )
