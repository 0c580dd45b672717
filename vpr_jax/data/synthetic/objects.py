"""Standalone objects between the track and the forest: spruces, birches, houses, utility
poles and bushes.

``world._World`` decides what stands where (:class:`_Objects`, from the seed alone); this
layer turns every (frame, object) view into per-row profiles (half-width and tone, with
the season's foliage, paint and snow) and paints them into the frames, farthest first,
behind any forest wall that juts out in front of them.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vpr_jax.data.synthetic.camera import _CAM_H, _F, _H, _U, _W, _Y, _View
from vpr_jax.data.synthetic.season import _Look

_D_NEAR, _D_FAR = 1.2, 34.0  # depth range in which standalone objects are drawn

# Object types
_SPRUCE, _BIRCH, _HOUSE, _POLE, _BUSH = range(5)


class _Objects(NamedTuple):
    z: np.ndarray  # position along the route, sorted
    x: np.ndarray  # signed lateral offset from the track centre (right positive)
    kind: np.ndarray  # _SPRUCE ...
    height: np.ndarray
    width: np.ndarray
    tone: np.ndarray  # per-object uniform [0, 1): species, paint, fall colour


class _ObjectViews(NamedTuple):
    """Every visible (frame, object) pair, P of them, grouped by object, each (P,)."""

    pb: np.ndarray  # frame in the block
    po: np.ndarray  # object index into _Objects
    d: np.ndarray  # depth
    scale: np.ndarray  # pixels per unit at the object's depth
    xc: np.ndarray  # column of the object's axis
    base: np.ndarray  # row of the object's foot


class _Sprites(NamedTuple):
    """How each view paints, per image row, each (P, H) float32."""

    val: np.ndarray  # tone, lit and faded into the haze
    amax: np.ndarray  # opacity at the axis
    hwp: np.ndarray  # half-width in pixels, plus half a pixel of anti-aliasing


def _object_window(z: np.ndarray) -> tuple[float, float]:
    """Range along the route of the objects a block of frames at ``z`` can see."""
    return float(z.min()) + _D_NEAR, float(z.max()) + _D_FAR


def _object_profiles(
    look: _Look,
    kind: np.ndarray,
    oh: np.ndarray,
    ow: np.ndarray,
    otone: np.ndarray,
    base: np.ndarray,
    scale: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-row half-width (units) and tone of P object views, shape (P, H) each.

    Two vertical samples per row give soft top and bottom edges.
    """
    hw = np.zeros((len(kind), _H))
    val = np.zeros((len(kind), _H))
    k = kind[:, None]
    oh, ow, t = oh[:, None], ow[:, None], otone[:, None]
    is_spruce, is_birch, is_house, is_pole = k == _SPRUCE, k == _BIRCH, k == _HOUSE, k == _POLE
    ry = 0.36 * oh  # birch crown: ellipse of this vertical radius ...
    yc = oh - ry  # ... centred here
    wall_h = 0.6 * oh  # house walls, then a gable roof
    birch_leaf = look.birch + look.birch_var * (2.0 * t - 1.0)
    birch_trunk = 0.55 if look.ground_snow else 0.6
    house_wall = np.where(t > 0.65, 0.78, 0.30)  # white or red painted
    spruce_t = look.spruce + 0.03 * (2.0 * t - 1.0)
    bush_t = look.bush + 0.04 * (2.0 * t - 1.0)
    for sub in (-0.25, 0.25):
        hgt = (base[:, None] - (_Y + sub)[None, :]) / scale[:, None]  # height above ground
        inside = (hgt >= 0.0) & (hgt <= oh)
        spruce = np.where(hgt < 0.25, 0.07, 0.5 * ow * (oh - hgt) / np.maximum(oh - 0.25, 1e-3))
        crown = 0.5 * ow * np.sqrt(np.maximum(1.0 - ((hgt - yc) / ry) ** 2, 0.0))
        birch = np.maximum(crown, np.where(hgt < yc, 0.06, 0.0))
        house = np.where(
            hgt < wall_h, 0.5 * ow, 0.5 * ow * (1.05 - 0.95 * (hgt - wall_h) / (oh - wall_h))
        )
        pole = np.where((hgt > 5.9) & (hgt < 6.1), 0.55, 0.5 * ow)
        bush = 0.5 * ow * np.sqrt(np.maximum(1.0 - (hgt / oh) ** 2, 0.0))
        w = np.select([is_spruce, is_birch, is_house, is_pole], [spruce, birch, house, pole], bush)
        hw += 0.5 * np.where(inside, w, 0.0)
        v = np.select(
            [is_spruce, is_birch, is_house, is_pole],
            [
                np.broadcast_to(spruce_t, hgt.shape),
                np.where(hgt < yc - 0.3 * ry, birch_trunk, birch_leaf),
                np.where(hgt < wall_h, house_wall, look.house_roof),
                np.full(hgt.shape, 0.16),
            ],
            np.broadcast_to(bush_t, hgt.shape),
        )
        val += 0.5 * v
    return hw, val


def _object_views(
    objs: _Objects, view: _View, wall_d: np.ndarray, wall_hit: np.ndarray
) -> _ObjectViews | None:
    """Every (frame, object) view in depth range, in the picture and in front of the forest
    wall of its column (``wall_d``, ``wall_hit``: (B, W)); None if there are none."""
    z = view.z
    if len(objs.z) == 0:
        return None
    lo = np.searchsorted(objs.z, z + _D_NEAR, side="left")
    hi = np.searchsorted(objs.z, z + _D_FAR, side="left")
    count = hi - lo
    if count.sum() == 0:
        return None
    # Every (frame, object) view, grouped by object.
    pb = np.repeat(np.arange(len(z)), count)
    po = np.repeat(lo - np.cumsum(count) + count, count) + np.arange(count.sum())
    order = np.lexsort((pb, po))
    pb, po = pb[order], po[order]
    d = objs.z[po] - z[pb]  # depth
    scale = _F / d  # pixels per unit at the object's depth
    xc = view.cx[pb] + _F * (objs.x[po] / d + 0.5 * view.kappa[pb] * d)
    base = view.yh[pb] + _CAM_H * scale  # row of the object's foot
    # Hidden behind a forest wall that juts out in front of it?
    col = np.clip(np.floor(xc), 0, _W - 1).astype(np.int64)
    wd = np.where(wall_hit, wall_d, np.inf)[pb, col]
    keep = (d < wd) & (xc > -20.0) & (xc < _W + 20.0)
    if not keep.any():
        return None
    return _ObjectViews(
        pb=pb[keep], po=po[keep], d=d[keep], scale=scale[keep], xc=xc[keep], base=base[keep]
    )


def _object_sprites(
    look: _Look, objs: _Objects, views: _ObjectViews, light: np.ndarray
) -> _Sprites:
    """Profiles of the views, lit by ``light`` (B,) and faded with depth."""
    po, scale = views.po, views.scale
    kind = objs.kind[po]
    hw, val = _object_profiles(
        look, kind, objs.height[po], objs.width[po], objs.tone[po], views.base, scale
    )
    fog = (views.d / (views.d + look.visibility))[:, None]
    lit = light[views.pb]
    val = ((val + (look.sky_hor * 0.8 - val) * fog) * lit[:, None]).astype(np.float32)
    hw_px = hw * scale[:, None]  # (P, H) half-width, pixels
    alpha = np.where(kind == _BIRCH, look.birch_alpha, 1.0)[:, None]
    amax = (np.minimum(1.0, 2.0 * hw_px) * alpha).astype(np.float32)
    hwp = (hw_px + 0.5).astype(np.float32)
    return _Sprites(val, amax, hwp)


def _paint_far_to_near(img: np.ndarray, views: _ObjectViews, sprites: _Sprites) -> np.ndarray:
    """Paint the views into ``img`` (B, H, W) in place, one object at a time, farthest first."""
    pb, po, xc = views.pb, views.po, views.xc
    val, amax, hwp = sprites
    xc32 = xc.astype(np.float32)
    u32 = _U.astype(np.float32)
    # Objects are sorted by z, which is depth order in every frame: paint farthest first.
    starts = np.flatnonzero(np.r_[True, po[1:] != po[:-1]])
    ends = np.r_[starts[1:], len(po)]
    for s, e in zip(starts[::-1], ends[::-1], strict=True):
        rows = np.flatnonzero((amax[s:e] > 0).any(axis=0))
        if not len(rows):
            continue
        r0, r1 = int(rows[0]), int(rows[-1]) + 1
        reach = hwp[s:e, r0:r1].max(axis=1)
        c0 = max(int(np.floor((xc[s:e] - reach).min())), 0)
        c1 = min(int(np.ceil((xc[s:e] + reach).max())) + 1, _W)
        if c1 <= c0:
            continue
        a = hwp[s:e, r0:r1, None] - np.abs(u32[None, None, c0:c1] - xc32[s:e, None, None])
        np.maximum(a, 0.0, out=a)
        np.minimum(a, amax[s:e, r0:r1, None], out=a)
        frames = pb[s:e]
        f0, f1 = int(frames[0]), int(frames[-1]) + 1
        if f1 - f0 == e - s:  # consecutive frames: work on a view
            part = img[f0:f1, r0:r1, c0:c1]
            part += a * (val[s:e, r0:r1, None] - part)
        else:
            part = img[frames, r0:r1, c0:c1]
            part += a * (val[s:e, r0:r1, None] - part)
            img[frames, r0:r1, c0:c1] = part
    return img


def _draw_objects(
    objs: _Objects,
    look: _Look,
    img: np.ndarray,
    view: _View,
    light: np.ndarray,
    wall_d: np.ndarray,
    wall_hit: np.ndarray,
) -> np.ndarray:
    """Paint the standalone objects ``objs`` into ``img`` (B, H, W), farthest object first."""
    views = _object_views(objs, view, wall_d, wall_hit)
    if views is None:
        return img
    return _paint_far_to_near(img, views, _object_sprites(look, objs, views, light))
