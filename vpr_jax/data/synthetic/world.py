"""The world along the route, and the camera's pose in it.

A small pseudo-3D world that depends only on ``seed``: the track's heading and curvature,
the forest walls on either side (their distance, height and tree-line change along the
route: near walls fill the side of the image, far ones are a strip on the horizon), the
standalone objects between track and forest, and the textures of the ground and the
forest. :func:`_camera_view` places the camera of one ride (synchronisation jitter,
lateral and vertical offset) on this route for a block of frames.
"""

from __future__ import annotations

import functools

import numpy as np

from vpr_jax.data.synthetic.camera import _HORIZON, _TOP_ROWS, _U, _Y, _View
from vpr_jax.data.synthetic.lighting import _Conditions
from vpr_jax.data.synthetic.noise import _clip01, _Noise1D, _texture
from vpr_jax.data.synthetic.objects import _BIRCH, _BUSH, _HOUSE, _POLE, _SPRUCE, _Objects

_SEG = 32.0  # world generation segment length (objects come from one RNG per segment)
_TEX_Z = 8192  # ground/wall texture length in texels along the route (0.5 unit each)


class _World:
    """Everything that stands along the route: depends only on the seed."""

    def __init__(self, seed: int):
        self.seed = seed
        rng = np.random.default_rng([seed, 0x5EED, 1])
        n = [_Noise1D(rng, 4093 - 2 * i) for i in range(18)]  # distinct periods
        (
            self.head1,
            self.head2,
            self.open_l,
            self.open_r,
            self.near_l,
            self.near_r,
            self.wall_h_l,
            self.wall_h_r,
            self.mix,
            self.jag,
            self.mtn_amp,
            self.mtn1,
            self.mtn2,
            self.mtn3,
            self.hill_amp,
            self.hill1,
            self.hill2,
            self.poles,
        ) = n
        # Ground: land use (fields, meadows, bare patches) and fine detail; walls: foliage.
        self.ground_a = _texture(rng, (_TEX_Z, 128), [((64, 16), 1.0), ((16, 8), 0.5)])
        self.ground_b = _texture(rng, (_TEX_Z, 128), [((32, 32), 1.0), ((16, 8), 0.4)])
        self.ground_c = _texture(rng, (_TEX_Z, 128), [((32, 16), 1.0), ((8, 8), 0.4)])
        self.ground_fine = _texture(rng, (_TEX_Z, 128), [((4, 4), 1.0), ((2, 2), 0.6)])
        self.wall_tex = _texture(rng, (_TEX_Z, 32), [((4, 2), 1.0), ((2, 2), 0.7)])
        self.wall_patch = _texture(rng, (_TEX_Z, 32), [((8, 4), 1.0), ((4, 4), 0.5)])
        self._segments: dict[int, _Objects] = {}

    # -- route geometry -------------------------------------------------------------------
    def heading(self, z: np.ndarray) -> np.ndarray:
        return 0.9 * self.head1(z / 150.0) + 0.25 * self.head2(z / 45.0)

    def curvature(self, z: np.ndarray) -> np.ndarray:
        return 0.5 * (self.heading(z + 1.0) - self.heading(z - 1.0))

    def wall_distance(self, z: np.ndarray, side: int) -> np.ndarray:
        """Lateral distance of the forest edge; large where the view opens up."""
        op, nr = (self.open_r, self.near_r) if side > 0 else (self.open_l, self.near_l)
        openness = _clip01(1.6 * op(z / 40.0) + 0.25)
        return 3.2 + 3.0 * (nr(z / 9.0) + 1.0) + 40.0 * openness * openness

    def wall_height(self, z: np.ndarray, side: int) -> np.ndarray:
        wh = self.wall_h_r if side > 0 else self.wall_h_l
        return 4.2 + 1.8 * wh(z / 14.0 + 7.0 * side)

    def objects(self, z_lo: float, z_hi: float) -> _Objects:
        s0, s1 = int(np.floor(z_lo / _SEG)), int(np.floor(z_hi / _SEG))
        parts = [self._segment(s) for s in range(s0, s1 + 1)]
        return _Objects._make(np.concatenate(p) for p in zip(*parts, strict=True))

    def _segment(self, s: int) -> _Objects:
        if s in self._segments:
            return self._segments[s]
        rng = np.random.default_rng([self.seed, 0x5EED, 2, s + (1 << 40)])
        z0 = s * _SEG
        n = rng.poisson(_SEG * 0.28)
        z = z0 + rng.uniform(0.0, _SEG, n)
        side = np.where(rng.uniform(size=n) < 0.5, -1.0, 1.0)
        kind = rng.choice(
            np.array([_SPRUCE, _BIRCH, _HOUSE, _BUSH]), size=n, p=[0.42, 0.30, 0.10, 0.18]
        )
        lat = 2.4 + rng.exponential(3.5, n)
        height = np.select(
            [kind == _SPRUCE, kind == _BIRCH, kind == _HOUSE],
            [rng.uniform(2.5, 6.0, n), rng.uniform(2.5, 5.0, n), rng.uniform(2.6, 4.2, n)],
            rng.uniform(0.5, 1.3, n),
        )
        width = np.select(
            [kind == _SPRUCE, kind == _BIRCH, kind == _HOUSE],
            [
                height * rng.uniform(0.35, 0.5, n),
                height * rng.uniform(0.5, 0.8, n),
                rng.uniform(3.0, 7.0, n),
            ],
            rng.uniform(1.0, 2.5, n),
        )
        lat = np.where(kind == _HOUSE, lat + 3.0, lat)
        tone = rng.uniform(size=n)
        # Utility poles: a line on one side where self.poles is positive, every ~14 units.
        pz = z0 + np.arange(0.0, _SEG, 14.0) + rng.uniform(0.0, 14.0)
        pz = pz[pz < z0 + _SEG]
        pole_val = self.poles(pz / 120.0)
        pz = pz[pole_val > -0.1]
        pside = np.where(self.poles(pz / 120.0 + 17.0) > 0, 1.0, -1.0)
        m = len(pz)
        z = np.concatenate([z, pz])
        x = np.concatenate([side * lat, pside * 3.0])
        kind = np.concatenate([kind, np.full(m, _POLE)])
        height = np.concatenate([height, np.full(m, 6.5)])
        width = np.concatenate([width, np.full(m, 0.16)])
        tone = np.concatenate([tone, rng.uniform(size=m)])
        # Only what stands in front of the forest edge is visible.
        wall = np.where(x > 0, self.wall_distance(z, 1), self.wall_distance(z, -1))
        keep = np.abs(x) + 0.5 * width < wall
        order = np.argsort(z[keep], kind="stable")
        objs = _Objects(
            z=z[keep][order],
            x=x[keep][order],
            kind=kind.astype(np.int64)[keep][order],
            height=height[keep][order],
            width=width[keep][order],
            tone=tone[keep][order],
        )
        if len(self._segments) > 4096:
            self._segments.clear()
        self._segments[s] = objs
        return objs


@functools.lru_cache(maxsize=2)
def _world(seed: int) -> _World:
    return _World(seed)


def _camera_view(world: _World, cond: _Conditions, frame_ids: np.ndarray) -> _View:
    """The camera of one ride at ``frame_ids`` (int64): where it is and where pixels look."""
    fid = frame_ids.astype(np.float64)
    z = fid + cond.drift("jitter", fid)  # imperfect synchronisation of the videos
    theta = world.heading(z)
    kappa = world.curvature(z)
    cx = 32.0 + cond.drift("shift", fid)  # lateral camera offset, pixels
    yh = _HORIZON + cond.drift("pitch", fid)
    du = _U[None, :] - cx[:, None]  # (B, W) column offset from the optical axis, pixels
    dy = _Y[None, :] - yh[:, None]  # (B, H) row offset below the horizon, pixels
    ep = -dy  # pixels above the horizon
    ept = ep[:, :_TOP_ROWS].astype(np.float32)  # (B, R) sky rows only
    return _View(
        ids=frame_ids, fid=fid, z=z, theta=theta, kappa=kappa, cx=cx, yh=yh, du=du, dy=dy, ept=ept
    )
