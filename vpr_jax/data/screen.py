"""Frames that show no place: black (tunnels), over-exposed or otherwise constant images.

Real routes have them: Nordland's train runs through tunnels (black frames in every season)
and, in videos, the camera sometimes saturates. A constant image has no structure to match,
so its best match is decided by noise; whether such places belong in an evaluation is the
researcher's call. ``screen_route`` always reports them in the run log and drops them only
when asked (``data.drop_constant_frames=true``), from every season at once so the seasons
stay aligned. Frames that repeat the one before (a train standing at a station) are only
reported: they are real places, matched and scored by frame number like any other.
"""

from __future__ import annotations

import numpy as np

from vpr_jax.data.route import Route
from vpr_jax.errors import UserError
from vpr_jax.progress import Log

# Mean absolute difference (in [0, 1] grey) below which a frame repeats the one before:
# under half a grey level, i.e. the same image up to compression noise.
REPEAT_TOL = 0.5 / 255
_BLOCK = 4096  # frames per pass: temporaries stay small on the full route


def constant_frames(images: np.ndarray, max_std: float) -> np.ndarray:
    """(N,) bool: frames whose pixel standard deviation is at most ``max_std``."""
    std = np.concatenate(
        [
            np.asarray(images[i : i + _BLOCK], dtype=np.float32).std(axis=(1, 2))
            for i in range(0, len(images), _BLOCK)
        ]
        or [np.zeros(0, np.float32)]
    )
    return std <= max_std


def repeated_frames(images: np.ndarray, tol: float = REPEAT_TOL) -> np.ndarray:
    """(N,) bool: frames that equal the frame before (mean absolute difference < ``tol``)."""
    out = np.zeros(len(images), dtype=bool)
    for i in range(1, len(images), _BLOCK):
        block = np.asarray(images[i - 1 : i + _BLOCK], dtype=np.float32)
        out[i : i + _BLOCK] = np.abs(np.diff(block, axis=0)).mean(axis=(1, 2)) < tol
    return out


def _counts(masks: dict[str, np.ndarray]) -> str:
    return ", ".join(f"{s} {int(m.sum()):,}" for s, m in masks.items())


def screen_route(route: Route, *, max_std: float, drop: bool, log: Log = print) -> Route:
    """Report constant and repeated frames; with ``drop``, remove the places where any season
    shows a constant frame. Returns the route unchanged when nothing is dropped."""
    constant = {s: constant_frames(im, max_std) for s, im in route.images.items()}
    # A tunnel's black frames repeat each other too; they count as constant only.
    repeated = {s: repeated_frames(im) & ~constant[s] for s, im in route.images.items()}
    if any(m.any() for m in repeated.values()):
        log(
            f"repeated frames (the same image as the frame before, e.g. a train standing at a "
            f"station): {_counts(repeated)}; kept, and scored by frame number like any other"
        )
    bad = np.logical_or.reduce(list(constant.values()))
    if not bad.any():
        return route
    what = (
        f"constant frames (pixel std <= data.constant_std={max_std:g}: black, "
        f"over-exposed or blank): {_counts(constant)}, at {int(bad.sum()):,} places"
    )
    if not drop:
        log(f"{what}; kept (data.drop_constant_frames=true drops them)")
        return route
    keep = ~bad
    if not keep.any():
        raise UserError(
            f"every frame is constant (pixel std <= {max_std:g}), nothing is left "
            "to match: check data.root, or lower data.constant_std"
        )
    log(
        f"{what}; dropped from every season (data.drop_constant_frames=true), "
        f"{int(keep.sum()):,} places left"
    )
    return route.take(keep)
