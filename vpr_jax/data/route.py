"""The in-memory form every data source produces: aligned seasons of one route."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vpr_jax import host_arrays
from vpr_jax.shapes import IMAGE_SHAPE

__all__ = ["IMAGE_SHAPE", "SEASON_ORDER", "Route"]

# Database-first order: for an unordered pair, the season earlier in this list is the
# database (the robot's memory) and the later one the queries. It reproduces the paper's
# pairs summer-fall, spring-fall and summer-spring.
SEASON_ORDER = ("summer", "spring", "fall", "winter")


class Route(NamedTuple):
    """Frame-aligned seasons: ``images[s][i]`` shows place ``frame_ids[i]`` in season ``s``.

    frame_ids: (N,) int64, strictly increasing original frame indices (ground truth uses them).
    images: season name -> (N, 32, 64) float32 in [0, 1].
    files: season name -> (N,) the image files' paths relative to ``data.root``, for routes
    read from image files; None for rendered or decoded frames.
    """

    frame_ids: np.ndarray
    images: dict[str, np.ndarray]
    files: dict[str, np.ndarray] | None = None

    def names(self, season: str) -> np.ndarray:
        """(N,) what each frame of ``season`` is called outside the suite: its file's path
        relative to ``data.root``, or ``<season>/<frame id>`` (the built-in route, videos)."""
        if self.files is not None:
            return self.files[season]
        return np.array([f"{season}/{int(i)}" for i in self.frame_ids], dtype=object)

    def take(self, rows: np.ndarray) -> Route:
        """The frames at ``rows`` (indices or a mask) of every season."""
        files = None if self.files is None else {s: f[rows] for s, f in self.files.items()}
        images = {s: host_arrays.take(im, rows) for s, im in self.images.items()}
        return Route(self.frame_ids[rows], images, files)

    @property
    def seasons(self) -> tuple[str, ...]:
        return tuple(self.images)

    def __len__(self) -> int:
        return len(self.frame_ids)
