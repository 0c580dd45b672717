"""The in-memory form every data source produces: aligned seasons of one route."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vpr_jax.shapes import IMAGE_SHAPE

__all__ = ["IMAGE_SHAPE", "SEASON_ORDER", "Route"]

# Database-first order: for an unordered pair, the season earlier in this list is the
# database (the robot's memory) and the later one the queries. It reproduces the seed's
# pairs summer-fall, spring-fall and summer-spring.
SEASON_ORDER = ("summer", "spring", "fall", "winter")


class Route(NamedTuple):
    """Frame-aligned seasons: ``images[s][i]`` shows place ``frame_ids[i]`` in season ``s``.

    frame_ids: (N,) int64, strictly increasing original frame indices (ground truth uses them).
    images: season name -> (N, 32, 64) float32 in [0, 1].
    """

    frame_ids: np.ndarray
    images: dict[str, np.ndarray]

    @property
    def seasons(self) -> tuple[str, ...]:
        return tuple(self.images)

    def __len__(self) -> int:
        return len(self.frame_ids)
