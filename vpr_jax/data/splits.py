"""Training and test places: disjoint stretches of the route with a gap between them.

Neighbouring frames look alike, so a test place next to a training place would leak; the gap
is measured in original frame indices, so it means the same distance whatever the frame step.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vpr_jax.config import SplitConfig
from vpr_jax.errors import UserError


class Split(NamedTuple):
    train: np.ndarray  # positions into the route's frames, ascending
    test: np.ndarray


def make_split(frame_ids: np.ndarray, cfg: SplitConfig) -> Split:
    n = len(frame_ids)
    n_train = round(cfg.train_fraction * n) if cfg.train_fraction is not None else cfg.n_train
    if not 2 <= n_train < n:
        raise UserError(f"split needs 2 <= training frames < {n} route frames, got {n_train}: "
                        "lower split.n_train or change split.train_fraction")
    first_test = int(np.searchsorted(frame_ids, frame_ids[n_train - 1] + cfg.gap, side="right"))
    available = n - first_test
    n_test = available if cfg.train_fraction is not None else cfg.n_test
    if available < max(n_test, 1):
        raise UserError(
            f"the route has {n} frames but the split needs {n_train} training + a gap of "
            f"{cfg.gap} frames + {n_test} test: lower split.n_train / split.n_test / split.gap "
            "or load more frames (data.n_frames, data.frame_step)")
    return Split(np.arange(n_train), np.arange(first_test, first_test + n_test))
