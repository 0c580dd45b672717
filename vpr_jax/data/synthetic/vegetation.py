"""What grows along the route, as the season has it: the fields on the ground plane and the
forest walls on either side of the track.

- fields, meadows and land-use patches, sampled in world coordinates; they change with the
  season in ways that do not stay the same from place to place (green crops, harvested
  stubble, ploughed soil, fall mottle, snow cover, lingering snow in hollows);
- forest walls whose distance, height and tree-line change along the route (near walls
  fill the side of the image, far ones are a strip on the horizon): every column is
  ray-marched against the left and right forest edges (:class:`_Walls`), then painted
  with the season's mix of spruce and birch, fall patches and snow in the spruces.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vpr_jax.data.synthetic.camera import _CAM_H, _F, _Y, _View
from vpr_jax.data.synthetic.noise import _clip01, _sample
from vpr_jax.data.synthetic.season import _Look
from vpr_jax.data.synthetic.terrain import _Ground
from vpr_jax.data.synthetic.world import _TEX_Z, _World

_WALL_J = 40  # depth samples per image column when ray-marching the forest walls
_WALL_D = 1.0 * (90.0 / 1.0) ** (np.arange(_WALL_J) / (_WALL_J - 1))


class _Walls(NamedTuple):
    """Where each column's ray first meets a forest edge, each (B, W)."""

    d_hit: np.ndarray  # depth of the hit
    any_hit: np.ndarray  # whether the ray meets a wall within the marched depths
    right: np.ndarray  # whether it is the right-hand wall
    z_hit: np.ndarray  # position along the route of the hit


def _fields(world: _World, look: _Look, ground: _Ground) -> np.ndarray:
    """The season's ground tone at the ground points: (B, R, W) float32."""
    xg, zg = ground.xg, ground.zg
    xa = xg * np.float32(0.5) + np.float32(64.0)
    za = np.mod(zg * 0.5, _TEX_Z).astype(np.float32)[:, :, None]
    ga = _sample(world.ground_a, xa, za)
    g = np.float32(look.ground) + np.float32(look.ground_a) * ga
    if look.ground_b:
        g += np.float32(look.ground_b) * _sample(world.ground_b, xa, za)
    if look.ground_c:
        g += np.float32(look.ground_c) * _sample(world.ground_c, xa, za)
    gf = _sample(
        world.ground_fine,
        xg * np.float32(2.0) + np.float32(64.0),
        np.mod(zg * 2.0, _TEX_Z).astype(np.float32)[:, :, None],
    )
    fine_fade = (1.0 / (1.0 + ground.d_row / 6.0)).astype(np.float32)[:, :, None]
    g += np.float32(look.ground_fine) * fine_fade * gf
    if look.ground_mottle:
        g += np.float32(look.ground_mottle) * fine_fade * (np.abs(gf) - np.float32(0.8))
    if look.ground_snow:
        # Snow covers the fields; bushes and rocks (high land-use values) stay dark.
        g -= np.float32(look.ground_snow * 0.45) * _clip01((ga - np.float32(1.3)) * np.float32(2.0))
    if look.snow_patches:
        # Snow lingers in hollows (low land-use values) and melts first on the fields.
        patch = _clip01((np.float32(-1.4) - ga - np.float32(0.3) * gf) * np.float32(2.5))
        g += np.float32(look.snow_patches) * patch * (np.float32(0.85) - g)
    return g


def _wall_hits(world: _World, view: _View) -> _Walls:
    """Ray-march every column against the left and right forest edges."""
    z = view.z
    dj = _WALL_D[None, None, :]  # (1, 1, J)
    slope = (view.du / _F)[:, :, None]  # (B, W, 1)
    xr = slope * dj - 0.5 * view.kappa[:, None, None] * dj * dj  # ray lateral at each depth
    zj = z[:, None] + _WALL_D[None, :]  # (B, J)
    wr = world.wall_distance(zj, 1)[:, None, :]
    wl = world.wall_distance(zj, -1)[:, None, :]
    gr, gl_ = xr - wr, -wl - xr
    gmax = np.maximum(gr, gl_)
    hit = gmax >= 0.0
    any_hit = hit.any(axis=2)
    j = np.argmax(hit, axis=2)[:, :, None]
    jm = np.maximum(j - 1, 0)
    gm1 = np.take_along_axis(gmax, j, 2)[..., 0]
    gm0 = np.take_along_axis(gmax, jm, 2)[..., 0]
    d1, d0 = _WALL_D[j[..., 0]], _WALL_D[jm[..., 0]]
    frac = np.where(j[..., 0] > 0, _clip01(-gm0 / np.maximum(gm1 - gm0, 1e-9)), 1.0)
    d_hit = d0 + (d1 - d0) * frac  # (B, W)
    right = np.take_along_axis(gr, j, 2)[..., 0] >= np.take_along_axis(gl_, j, 2)[..., 0]
    z_hit = z[:, None] + d_hit
    return _Walls(d_hit=d_hit, any_hit=any_hit, right=right, z_hit=z_hit)


def _wall_cover(world: _World, look: _Look, view: _View, walls: _Walls) -> np.ndarray:
    """(B, H, W) float32 share of each pixel the forest covers, up to its jagged tree-line."""
    d_hit, right, z_hit, yh = walls.d_hit, walls.right, walls.z_hit, view.yh
    h_top = np.where(right, world.wall_height(z_hit, 1), world.wall_height(z_hit, -1))
    jag_fade = _clip01(1.6 - d_hit / 25.0)
    jag = np.abs(world.jag(z_hit * 1.3 + 50.0 * right)) - 0.5  # spruce tips
    h_top = h_top + 1.1 * look.treeline * jag_fade * jag
    top = (yh[:, None] + _F * (_CAM_H - h_top) / d_hit).astype(np.float32)  # (B, W)
    bot = (yh[:, None] + _F * _CAM_H / d_hit).astype(np.float32)
    y3 = _Y.astype(np.float32)[None, :, None]
    cov = _clip01(y3 - top[:, None, :] + np.float32(0.5))
    cov *= _clip01(bot[:, None, :] - y3 + np.float32(0.5))
    cov *= walls.any_hit[:, None, :]
    return cov


def _wall_tone(
    world: _World, look: _Look, view: _View, light: np.ndarray, walls: _Walls
) -> np.ndarray:
    """(B, H, W) tone of the forest wall seen in each pixel, lit by ``light`` (B,)."""
    d_hit, right, z_hit = walls.d_hit, walls.right, walls.z_hit
    mix = _clip01(0.5 + 0.8 * world.mix(z_hit / 30.0 + 11.0 * right))  # birch share
    tone = look.wall_spruce + (look.wall_birch - look.wall_spruce) * mix
    y3 = _Y.astype(np.float32)[None, :, None]
    hgt = (
        _CAM_H
        - (y3 - view.yh.astype(np.float32)[:, None, None])
        * (d_hit / _F).astype(np.float32)[:, None, :]
    )  # height on the wall, units
    wt = _sample(
        world.wall_tex,
        hgt * np.float32(2.0),
        np.mod(z_hit * 2.0 + 4096.0 * right, _TEX_Z).astype(np.float32)[:, None, :],
    )
    wfog = d_hit / (d_hit + look.visibility)
    near = (1.0 - wfog) / (1.0 + d_hit / 15.0)  # texture fades with distance
    lw = light[:, None]
    base = ((tone + (look.sky_hor * 0.8 - tone) * wfog) * lw).astype(np.float32)
    tex_amp = (look.wall_tex * (0.6 + 0.8 * mix) * near * lw).astype(np.float32)
    wall = base[:, None, :] + tex_amp[:, None, :] * wt
    if look.wall_patch or look.wall_snow:
        wp = _sample(
            world.wall_patch,
            hgt * np.float32(1.0),
            np.mod(z_hit + 2048.0 * right, _TEX_Z).astype(np.float32)[:, None, :],
        )
        if look.wall_patch:  # deciduous trees turning: patches of brighter foliage
            amp = (look.wall_patch * mix * near * lw).astype(np.float32)[:, None, :]
            wall += amp * _clip01(wp + np.float32(0.3))
        if look.wall_snow:  # snow caught in the spruces
            amp = (look.wall_snow * (1.0 - mix) * near * lw).astype(np.float32)[:, None, :]
            wall += amp * _clip01(wt - np.float32(0.5))
    return wall


def _forest_walls(
    world: _World, look: _Look, view: _View, light: np.ndarray, img: np.ndarray, walls: _Walls
) -> np.ndarray:
    """Paint the forest walls over ``img`` (B, H, W), in place."""
    cov = _wall_cover(world, look, view, walls)
    img += cov * (_wall_tone(world, look, view, light, walls) - img)
    return img
