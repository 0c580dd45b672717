"""Training and test places: disjoint stretches of the route with a gap between them.

Neighbouring frames look alike, so a test place next to a training place would leak; the gap
is measured in original frame indices, so it means the same distance whatever the frame step.
Each season's training stretch ends in a validation stretch (``split.val_fraction`` of it,
after another gap): the encoders are fitted on the rest, every cell is also scored on the
validation places, and those scores choose each method's setting (and stop the
auto-encoders' training early), so the test places are never used to choose anything.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vpr_jax.config import SplitConfig
from vpr_jax.errors import UserError


class Split(NamedTuple):
    train: np.ndarray  # positions into the route's frames, ascending: what encoders fit on
    test: np.ndarray
    val: np.ndarray  # validation places: the end of the training stretch, after a gap


def make_split(frame_ids: np.ndarray, cfg: SplitConfig) -> Split:
    frame_ids = np.asarray(frame_ids)
    stretch, test = _train_and_test(frame_ids, cfg)
    return _hold_out_validation(frame_ids, stretch, test, cfg.val_fraction, cfg.gap)


def _hold_out_validation(
    frame_ids: np.ndarray, stretch: np.ndarray, test: np.ndarray, fraction: float, gap: int
) -> Split:
    """The last ``fraction`` of the training stretch validates; the training places more
    than ``gap`` frames before its first frame are fitted on."""
    n_val = max(1, round(fraction * len(stretch)))
    val = stretch[-n_val:]
    rest = stretch[:-n_val]
    fit = rest[frame_ids[rest] < frame_ids[val[0]] - gap]
    if len(fit) < 2:
        raise UserError(
            f"the training stretch of {len(stretch)} frames leaves {len(fit)} to fit on after "
            f"{n_val} validation frames (split.val_fraction={fraction}) and a gap of {gap}: "
            "raise split.n_train, or lower split.val_fraction or split.gap"
        )
    return Split(fit, test, val)


def _train_and_test(frame_ids: np.ndarray, cfg: SplitConfig) -> tuple[np.ndarray, np.ndarray]:
    if cfg.test_sections > 0:
        return _sections(frame_ids, cfg.test_sections, cfg.n_test, cfg.gap)
    n = len(frame_ids)
    n_train = round(cfg.train_fraction * n) if cfg.train_fraction is not None else cfg.n_train
    if not 2 <= n_train < n:
        raise UserError(
            f"split needs 2 <= training frames < {n} route frames, got {n_train}: "
            "lower split.n_train or change split.train_fraction"
        )
    first_test = int(np.searchsorted(frame_ids, frame_ids[n_train - 1] + cfg.gap, side="right"))
    available = n - first_test
    n_test = available if cfg.train_fraction is not None else cfg.n_test
    if available < max(n_test, 1):
        raise UserError(
            f"the route has {n} frames but the split needs {n_train} training + a gap of "
            f"{cfg.gap} frames + {n_test} test: lower split.n_train / split.n_test / split.gap "
            "or load more frames (data.n_frames, data.frame_step)"
        )
    return np.arange(n_train), np.arange(first_test, first_test + n_test)


def _sections(
    frame_ids: np.ndarray, n_sections: int, length: int, gap: int
) -> tuple[np.ndarray, np.ndarray]:
    """Olid et al.'s partition: ``n_sections`` test sections of ``length`` frames centred at
    (i + 1/2) / n_sections of the route; training = every frame more than ``gap`` original
    frame indices away from every test frame."""
    n = len(frame_ids)
    starts = [round((i + 0.5) * n / n_sections - length / 2) for i in range(n_sections)]
    ends = [start + length for start in starts]
    inside = length >= 1 and starts[0] >= 0 and ends[-1] <= n
    if not inside or any(
        frame_ids[b] - frame_ids[e - 1] <= 2 * gap
        for e, b in zip(ends[:-1], starts[1:], strict=True)
    ):  # every section needs its gap on both sides clear of the next one
        raise UserError(
            f"{n_sections} test sections of {length} frames with {gap}-frame gaps do not fit "
            f"in a route of {n} frames: lower split.test_sections / split.n_test / split.gap "
            "or load more frames"
        )
    test = np.concatenate([np.arange(a, b) for a, b in zip(starts, ends, strict=True)])
    lo = np.searchsorted(frame_ids[test], frame_ids - gap, side="left")
    near = (lo < len(test)) & (frame_ids[test][np.minimum(lo, len(test) - 1)] <= frame_ids + gap)
    train = np.flatnonzero(~near)
    if len(train) < 2:
        raise UserError(
            f"{n_sections} test sections of {length} frames with {gap}-frame gaps leave "
            f"{len(train)} training frames: lower split.n_test or split.gap"
        )
    return train, test
