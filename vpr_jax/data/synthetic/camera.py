"""The pinhole camera every layer projects through, and the per-block camera pose.

Frames are 32 x 64 (height x width); row r spans [r, r + 1) and column u spans [u, u + 1).
World units: 1 unit = 1 frame of travel along the route. The pose of a block of frames
(:class:`_View`) is computed once, by ``world._camera_view``, and passed to every layer.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vpr_jax.data.route import IMAGE_SHAPE

_H, _W = IMAGE_SHAPE
_F = 36.0  # focal length, pixels (about 83 degrees horizontal field of view)
_HORIZON = 12.5  # image row (continuous, row r spans [r, r + 1)) of the horizon
_CAM_H = 1.0  # camera height above the ground, world units (1 unit = 1 frame of travel)
_TOP_ROWS = int(np.ceil(_HORIZON + 0.4))  # rows [0, _TOP_ROWS) can show sky

_U = np.arange(_W, dtype=np.float64) + 0.5  # pixel-centre columns
_Y = np.arange(_H, dtype=np.float64) + 0.5  # pixel-centre rows


class _View(NamedTuple):
    """Where the camera is for a block of B frames, and how the pixels look out of it."""

    ids: np.ndarray  # (B,) int64 frame ids
    fid: np.ndarray  # (B,) the same, float64
    z: np.ndarray  # (B,) position along the route (frame id + synchronisation jitter)
    theta: np.ndarray  # (B,) heading of the track, radians
    kappa: np.ndarray  # (B,) curvature of the track
    cx: np.ndarray  # (B,) column of the optical axis (lateral camera offset), pixels
    yh: np.ndarray  # (B,) row of the horizon (vertical camera offset), pixels
    du: np.ndarray  # (B, W) column offset from the optical axis, pixels
    dy: np.ndarray  # (B, H) row offset below the horizon, pixels
    ept: np.ndarray  # (B, _TOP_ROWS) float32 pixels above the horizon, sky rows only
