"""The landscape behind and under everything: sky and clouds, far mountains, forested
hills, and the ground plane with the track.

- far mountains (slow parallax, they turn with the track's heading, snow above the
  season's snowline) and nearer forested hills, both fading into the horizon haze;
- sky and clouds, which differ per traversal and drift across the sky during a ride;
- the ground plane sampled in world coordinates (:class:`_Ground`, on which the season's
  fields are painted by ``vegetation._fields``), with the ballast and two rails converging
  to the vanishing point, bending with the curvature.

Rows above the horizon (``camera._TOP_ROWS``) hold sky, mountains and hills; the ground
starts at the row that holds the horizon, which blends the two.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vpr_jax.data.synthetic.camera import _CAM_H, _F, _H, _HORIZON, _TOP_ROWS, _W, _View
from vpr_jax.data.synthetic.lighting import _Conditions, _Light
from vpr_jax.data.synthetic.noise import _clip01, _sample
from vpr_jax.data.synthetic.season import _Look
from vpr_jax.data.synthetic.world import _World

_BALLAST, _RAIL_X, _RAIL_W = 0.62, 0.36, 0.035  # ballast half-width, rail offset, half-width
_G0 = _TOP_ROWS - 1  # first ground row: the one that holds the horizon


class _Ground(NamedTuple):
    """Where each ground row's pixels hit the ground plane, rows [_G0, H) of B frames."""

    dyg: np.ndarray  # (B, R) row offset below the horizon, pixels
    d_row: np.ndarray  # (B, R) depth of each row's ground point
    d3: np.ndarray  # (B, R, 1) the same, float32
    xg: np.ndarray  # (B, R, W) float32 lateral position on the ground
    zg: np.ndarray  # (B, R) position along the route


def _sky(cond: _Conditions, view: _View, light: _Light) -> np.ndarray:
    """Sky and clouds of the rows above the horizon: (B, _TOP_ROWS, W) float32."""
    look, ept = cond.look, view.ept
    e = _clip01(ept / _HORIZON)  # 0 at the horizon, 1 at the top row
    sky = look.sky_hor + (look.sky_top - look.sky_hor) * e  # (B, R)
    az_px = (view.theta * _F)[:, None] + view.du  # (B, W) world azimuth in pixels
    cmx = np.mod(az_px * 0.5 + (cond.cloud_speed * view.fid)[:, None], 2048.0).astype(np.float32)
    cmx = np.broadcast_to(cmx[:, None, :], (len(view.fid), _TOP_ROWS, _W))
    cmy = np.maximum(ept, 0.0)[:, :, None] * np.float32(1.2)
    clouds = _sample(cond.cloud_tex, cmx, cmy)
    cover = cond.cloud_cover + cond.drift("clouds", view.fid)
    thresh = (1.0 - 2.0 * cover).astype(np.float32)[:, None, None]
    cl = _clip01((clouds - thresh) * np.float32(1.5 * look.cloud_contrast))
    np.minimum(cl, np.float32(look.cloud_contrast), out=cl)
    sky3 = sky[:, :, None]
    return (sky3 + (np.float32(look.cloud_tone) - sky3) * cl) * light.sky_gain.astype(np.float32)[
        :, None, None
    ]


def _azimuth(view: _View) -> np.ndarray:
    """(B, W) world azimuth of every column, radians."""
    return view.theta[:, None] + view.du / _F


def _mountains(
    world: _World, look: _Look, view: _View, light: _Light, top: np.ndarray
) -> np.ndarray:
    """Far mountains over ``top`` (in place): turn with the heading, slow parallax, snow
    above the snowline."""
    z, ept = view.z, view.ept
    a = _azimuth(view) * 7.0 + (z * 0.006)[:, None]
    ridge = 1.0 - np.abs(world.mtn1(a))  # sharp peaks
    prof = 0.65 * ridge + 0.35 * (0.5 + 0.5 * world.mtn2(a * 3.1)) + 0.12 * world.mtn3(a * 9.0)
    amp = 9.0 * _clip01(0.9 * world.mtn_amp(z / 400.0) + 0.55)
    hm = (amp[:, None] * prof).astype(np.float32)  # (B, W) ridge height, pixels
    cov = _clip01(hm[:, None, :] - ept[:, :, None] + np.float32(0.5))
    snow_off = (0.8 * world.mtn3(a * 4.0) - look.snowline).astype(np.float32)
    snow = _clip01(ept[:, :, None] + snow_off[:, None, :])
    haze = 60.0 / (60.0 + look.visibility)  # aerial perspective: far rock fades to the sky
    rock = look.mtn_rock * (1 - haze) + look.sky_hor * haze
    snowt = look.mtn_snow * (1 - 0.6 * haze) + look.sky_hor * 0.6 * haze
    mtn = (np.float32(rock) + np.float32(snowt - rock) * snow) * light.sky_gain.astype(np.float32)[
        :, None, None
    ]
    top += cov * (mtn - top)
    return top


def _hills(world: _World, look: _Look, view: _View, light: _Light, top: np.ndarray) -> np.ndarray:
    """Forested hills in the middle distance over ``top`` (in place)."""
    z = view.z
    c = _azimuth(view) * 3.0 + (z * 0.035)[:, None]
    hh = (2.8 * _clip01(world.hill_amp(z / 150.0) + 0.6))[:, None] * (
        0.55 + 0.45 * world.hill1(c) + 0.12 * world.hill2(c * 6.0)
    )
    cov = _clip01(hh.astype(np.float32)[:, None, :] - view.ept[:, :, None] + np.float32(0.5))
    haze = 30.0 / (30.0 + look.visibility)
    hill = ((look.hill * (1 - haze) + look.sky_hor * haze) * light.light).astype(np.float32)
    top += cov * (hill[:, None, None] - top)
    return top


def _ground_points(view: _View) -> _Ground:
    """Intersect the rays of the ground rows with the (curving) ground plane."""
    dyg = view.dy[:, _G0:]
    d_row = _CAM_H * _F / np.maximum(dyg, 0.35)  # (B, R) depth of each row's ground point
    d3 = d_row.astype(np.float32)[:, :, None]
    duf = view.du.astype(np.float32)[:, None, :]
    kappa = view.kappa
    xg = duf * (d3 / np.float32(_F)) - (0.5 * kappa).astype(np.float32)[:, None, None] * d3 * d3
    zg = view.z[:, None] + d_row  # (B, R)
    return _Ground(dyg=dyg, d_row=d_row, d3=d3, xg=xg, zg=zg)


def _track(look: _Look, ground: _Ground, g: np.ndarray) -> np.ndarray:
    """Ballast bed and two rails over the ground tone ``g`` (in place), anti-aliased by the
    pixel footprint."""
    inv_foot = _F / ground.d3  # pixels per ground unit
    ax = np.abs(ground.xg)
    ballast = _clip01((np.float32(_BALLAST) - ax) * inv_foot + np.float32(0.5))
    g += (np.float32(look.ballast) - g) * ballast
    rail = _clip01(
        (np.float32(_RAIL_W) - np.abs(ax - np.float32(_RAIL_X))) * inv_foot + np.float32(0.5)
    )
    np.minimum(rail, np.float32(2.0 * _RAIL_W) * inv_foot, out=rail)
    g += (np.float32(look.rail) - g) * rail
    return g


def _landscape(
    look: _Look, light: _Light, top: np.ndarray, ground: _Ground, g: np.ndarray
) -> np.ndarray:
    """The frame (B, H, W): ``top`` above the horizon row, the ground ``g`` (hazed and lit
    in place) below it, the horizon row blending the two."""
    fog = (ground.d_row / (ground.d_row + look.visibility)).astype(np.float32)[:, :, None]
    g += (np.float32(look.sky_hor * 0.85) - g) * fog
    g *= light.light.astype(np.float32)[:, None, None]
    img = np.empty((len(g), _H, _W), np.float32)
    img[:, :_G0] = top[:, :_G0]
    cov = _clip01(ground.dyg + 0.5).astype(np.float32)[:, :, None]
    hz = top[:, _G0:]  # the horizon row: sky above the line, ground below
    img[:, _G0 : _G0 + 1] = hz + cov[:, :1] * (g[:, :1] - hz)
    img[:, _G0 + 1 :] = g[:, 1:]
    return img
