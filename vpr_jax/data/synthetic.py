"""Built-in seasonal route: a deterministic stand-in for Nordland, so the suite runs offline.

A train's forward camera moves along one route, one place per frame, rendered at 32 x 64
(height x width) grayscale float32 in [0, 1]. The scene is a small pseudo-3D world:

- far mountains (slow parallax, they turn with the track's heading), nearer forested hills;
- the ground plane (fields, meadows, land-use patches) sampled in world coordinates, with
  the ballast and two rails converging to the vanishing point, bending with the curvature;
- forest walls on either side whose distance, height and tree-line change along the route
  (near walls fill the side of the image; far ones are a strip on the horizon);
- standalone objects between track and forest: spruces, birches, houses, poles, bushes.

Everything the world contains depends only on ``seed``; the season and the traversal only
change appearance, the way they do on the Nordland line:

- sky and clouds differ per traversal (clear summer sky, overcast fall and winter; in
  winter the overcast sky is darker than the snow);
- exposure, illumination (sun side, ground and sky brightness, gradients) drift slowly
  along the route: global, low-frequency patterns, mostly shared by the rides of one season
  (same time of year and of day), a little different on every ride; a partial
  auto-exposure pulls every frame towards one mean brightness;
- vegetation: summer dark uniform green; fall patchy orange/yellow/brown (in grayscale
  brighter and mottled); spring fresh light green, sparse foliage, brown fields, snow on
  the mountains; winter snow on ground, roofs and mountains, bare birches, dark spruces;
- fields change with the season in ways that do not stay the same from place to place
  (green crops, harvested stubble, ploughed soil, lingering snow in hollows);
- per ride, the camera sits up to a pixel or so to the side and the frames are not
  perfectly synchronised (both varying slowly), and there is sensor noise.

Rendering is vectorised numpy (plus ``cv2.remap`` for texture look-ups) over blocks of
frames; every pixel of a frame depends only on (seed, season, traversal, frame id), so a
subset of frames, in any order, gives exactly the rows of rendering them all. Per-frame
values go through elementwise IEEE arithmetic only (no transcendental functions, whose SIMD
and scalar paths may differ in the last bit) and per-row reductions, so the result does not
depend on how frames are batched.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable
from typing import NamedTuple

import cv2
import numpy as np

from vpr_jax.data.route import IMAGE_SHAPE, Route
from vpr_jax.errors import UserError

__all__ = ["DEFAULT_N_FRAMES", "SEASONS", "render_season", "synthetic_route"]

DEFAULT_N_FRAMES = 3600
SEASONS = ("spring", "summer", "fall", "winter")

_H, _W = IMAGE_SHAPE
_F = 36.0  # focal length, pixels (about 83 degrees horizontal field of view)
_HORIZON = 12.5  # image row (continuous, row r spans [r, r + 1)) of the horizon
_CAM_H = 1.0  # camera height above the ground, world units (1 unit = 1 frame of travel)
_D_NEAR, _D_FAR = 1.2, 34.0  # depth range in which standalone objects are drawn
_CHUNK = 256  # frames rendered at once: bounds the working memory
_SEG = 32.0  # world generation segment length (objects come from one RNG per segment)
_TEX_Z = 8192  # ground/wall texture length in texels along the route (0.5 unit each)
_WALL_J = 40  # depth samples per image column when ray-marching the forest walls
_WALL_D = 1.0 * (90.0 / 1.0) ** (np.arange(_WALL_J) / (_WALL_J - 1))

_U = np.arange(_W, dtype=np.float64) + 0.5  # pixel-centre columns
_Y = np.arange(_H, dtype=np.float64) + 0.5  # pixel-centre rows
# Slow drift along the route: amplitude of each nuisance, shared by every traversal of a
# season (same time of year and of day: sun height, typical weather, camera settings) ...
_SEASON_DRIFT = {
    "light": 0.08,  # relative illumination of the ground and everything on it
    "sky": 0.08,  # relative sky brightness
    "gain": 0.08,  # relative exposure
    "offset": 0.03,  # black level
    "hgrad": 0.05,  # left-right brightness gradient (on top of the seasonal sun side)
    "vgrad": 0.04,  # top-bottom brightness gradient
}
# ... and specific to one traversal (another ride in the same season).
_TRAVERSAL_DRIFT = {
    "jitter": 0.25,  # frames: imperfect synchronisation of the videos
    "shift": 0.7,  # pixels: lateral camera offset
    "pitch": 0.35,  # pixels: vertical camera offset
    "light": 0.02,
    "sky": 0.03,
    "gain": 0.02,
    "offset": 0.008,
    "hgrad": 0.015,
    "vgrad": 0.015,
    "clouds": 0.15,  # cloud cover
}
_DRIFT_SCALE = {  # frames over which each nuisance changes
    "jitter": 20.0,
    "shift": 90.0,
    "pitch": 70.0,
    "light": 35.0,
    "sky": 50.0,
    "gain": 45.0,
    "offset": 30.0,
    "hgrad": 40.0,
    "vgrad": 40.0,
    "clouds": 60.0,
}
_AUTO_EXPOSURE, _AE_TARGET = 0.7, 0.45  # share of the way to the target mean brightness
_NOISE = 0.018  # sensor noise per table (two tables add up)
_BALLAST, _RAIL_X, _RAIL_W = 0.62, 0.36, 0.035  # ballast half-width, rail offset, half-width
_VIGNETTE = (
    1.0 - 0.10 * ((_U[None, :] - 32.0) / 32.0) ** 2 - 0.06 * ((_Y[:, None] - 16.0) / 16.0) ** 2
).astype(np.float32)

# Object types
_SPRUCE, _BIRCH, _HOUSE, _POLE, _BUSH = range(5)


# ------------------------------------------------------------------------------ noise


class _Noise1D:
    """Smooth 1D value noise (Catmull-Rom through random knots), periodic with a long period.

    Evaluated with + and * only, so it is bit-identical however the input is batched.
    """

    def __init__(self, rng: np.random.Generator, size: int = 4093):
        self.table = rng.uniform(-1.0, 1.0, size)
        self.size = size

    def __call__(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, np.float64)
        i0 = np.floor(t)
        f = t - i0
        i = i0.astype(np.int64) % self.size
        n, tb = self.size, self.table
        p0, p1, p2, p3 = tb[(i - 1) % n], tb[i], tb[(i + 1) % n], tb[(i + 2) % n]
        # Catmull-Rom spline: C1, passes through the knots.
        a = -0.5 * p0 + 1.5 * p1 - 1.5 * p2 + 0.5 * p3
        b = p0 - 2.5 * p1 + 2.0 * p2 - 0.5 * p3
        c = -0.5 * p0 + 0.5 * p2
        return ((a * f + b) * f + c) * f + p1


def _tileable_noise(
    rng: np.random.Generator, shape: tuple[int, int], cell: tuple[int, int]
) -> np.ndarray:
    """Smooth random texture of ``shape`` that wraps in both directions; features ~``cell``."""
    h, w = shape
    gh, gw = h // cell[0], w // cell[1]
    grid = rng.standard_normal((gh, gw)).astype(np.float32)
    pad = 2
    grid = np.pad(grid, pad, mode="wrap")
    big = cv2.resize(
        grid, ((gw + 2 * pad) * cell[1], (gh + 2 * pad) * cell[0]), interpolation=cv2.INTER_CUBIC
    )
    out = big[pad * cell[0] : pad * cell[0] + h, pad * cell[1] : pad * cell[1] + w]
    return np.ascontiguousarray(out / max(float(out.std()), 1e-6))


def _texture(
    rng: np.random.Generator,
    shape: tuple[int, int],
    octaves: Iterable[tuple[tuple[int, int], float]],
) -> np.ndarray:
    out = np.zeros(shape, np.float32)
    for cell, amp in octaves:
        out += amp * _tileable_noise(rng, shape, cell)
    return np.ascontiguousarray(out / max(float(out.std()), 1e-6))


def _sample(tex: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    """Bilinear, wrapping texture look-up at float texel coordinates of any shape."""
    shape = map_x.shape
    mx = np.ascontiguousarray(map_x, np.float32).reshape(-1, shape[-1])
    my = np.ascontiguousarray(np.broadcast_to(map_y, shape), np.float32).reshape(-1, shape[-1])
    out = np.empty_like(mx)
    rows = 16384  # cv2.remap maps must stay below 32767 rows
    for s in range(0, mx.shape[0], rows):
        cv2.remap(
            tex,
            mx[s : s + rows],
            my[s : s + rows],
            cv2.INTER_LINEAR,
            dst=out[s : s + rows],
            borderMode=cv2.BORDER_WRAP,
        )
    return out.reshape(shape)


def _tri(x: np.ndarray) -> np.ndarray:
    """Cosine-like triangle wave of period 2*pi in [-1, 1] (arithmetic only)."""
    p = np.mod(x / (2.0 * np.pi), 1.0)
    return 4.0 * np.abs(p - 0.5) - 1.0


def _clip01(x: np.ndarray) -> np.ndarray:
    return np.minimum(np.maximum(x, 0.0), 1.0)


# ------------------------------------------------------------------------------ world


class _Objects(NamedTuple):
    z: np.ndarray  # position along the route, sorted
    x: np.ndarray  # signed lateral offset from the track centre (right positive)
    kind: np.ndarray  # _SPRUCE ...
    height: np.ndarray
    width: np.ndarray
    tone: np.ndarray  # per-object uniform [0, 1): species, paint, fall colour


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
        return _Objects(*(np.concatenate(p) for p in zip(*parts, strict=True)))

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
            *(a[keep][order] for a in (z, x, kind.astype(np.int64), height, width, tone))
        )
        if len(self._segments) > 4096:
            self._segments.clear()
        self._segments[s] = objs
        return objs


@functools.lru_cache(maxsize=2)
def _world(seed: int) -> _World:
    return _World(seed)


# ------------------------------------------------------------------------------ appearance


class _Look(NamedTuple):
    """How a season looks (tones are grayscale reflectances in [0, 1])."""

    sky_top: float
    sky_hor: float
    cloud_cover: float  # typical fraction of sky covered
    cloud_tone: float
    cloud_contrast: float
    visibility: float  # haze distance, world units: far things fade into the horizon tone
    mtn_rock: float
    mtn_snow: float
    snowline: float  # pixels above the horizon where mountain snow starts
    hill: float
    ground: float  # mean ground tone
    ground_a: float  # contrast of land-use pattern A (meadows vs fields)
    ground_b: float  # contrast of land-use pattern B (crops: green, harvested, ploughed)
    ground_c: float  # contrast of land-use pattern C (fields harvested / mown this season)
    ground_fine: float  # grass / stubble texture contrast
    ground_mottle: float  # patchy high-contrast texture (fall colours, melting snow)
    ground_snow: float  # 0..1: snow cover of the whole ground
    snow_patches: float  # 0..1: lingering snow in hollows (spring)
    ballast: float
    rail: float
    spruce: float
    birch: float  # foliage tone
    birch_var: float  # per-tree spread of the foliage tone (fall: yellow ... brown)
    birch_alpha: float  # foliage density (bare in winter, sparse in spring)
    bush: float
    house_roof: float
    wall_spruce: float
    wall_birch: float
    wall_tex: float  # forest texture contrast
    wall_patch: float  # patches of changed deciduous foliage (fall colours, spring leaves)
    wall_snow: float  # snow caught in the spruces
    light: float  # overall illumination of the scene below the sky
    exposure: float
    sun: float  # strength of the side-lighting gradient (sunny seasons)
    noise: float  # sensor noise relative to the default (dim winter light is noisier)
    treeline: float  # how jagged the forest's tree-line looks (snow rounds it off)


_LOOKS = {
    "summer": _Look(
        sky_top=0.56,
        sky_hor=0.74,
        cloud_cover=0.30,
        cloud_tone=0.92,
        cloud_contrast=0.5,
        visibility=80.0,
        mtn_rock=0.40,
        mtn_snow=0.80,
        snowline=8.5,
        hill=0.24,
        ground=0.30,
        ground_a=0.07,
        ground_b=-0.06,
        ground_c=0.03,
        ground_fine=0.05,
        ground_mottle=0.0,
        ground_snow=0.0,
        snow_patches=0.0,
        ballast=0.45,
        rail=0.15,
        spruce=0.16,
        birch=0.22,
        birch_var=0.04,
        birch_alpha=1.0,
        bush=0.22,
        house_roof=0.22,
        wall_spruce=0.17,
        wall_birch=0.23,
        wall_tex=0.05,
        wall_patch=0.0,
        wall_snow=0.0,
        light=1.0,
        exposure=1.0,
        sun=0.06,
        noise=1.0,
        treeline=1.0,
    ),
    "spring": _Look(
        sky_top=0.60,
        sky_hor=0.76,
        cloud_cover=0.45,
        cloud_tone=0.88,
        cloud_contrast=0.45,
        visibility=60.0,
        mtn_rock=0.42,
        mtn_snow=0.86,
        snowline=3.5,
        hill=0.32,
        ground=0.34,
        ground_a=0.05,
        ground_b=-0.04,
        ground_c=-0.10,
        ground_fine=0.06,
        ground_mottle=0.05,
        ground_snow=0.0,
        snow_patches=0.7,
        ballast=0.47,
        rail=0.17,
        spruce=0.19,
        birch=0.42,
        birch_var=0.06,
        birch_alpha=0.55,
        bush=0.33,
        house_roof=0.25,
        wall_spruce=0.20,
        wall_birch=0.36,
        wall_tex=0.08,
        wall_patch=0.12,
        wall_snow=0.0,
        light=1.0,
        exposure=1.0,
        sun=0.04,
        noise=1.0,
        treeline=1.0,
    ),
    "fall": _Look(
        sky_top=0.66,
        sky_hor=0.78,
        cloud_cover=0.75,
        cloud_tone=0.80,
        cloud_contrast=0.4,
        visibility=45.0,
        mtn_rock=0.38,
        mtn_snow=0.80,
        snowline=6.0,
        hill=0.36,
        ground=0.34,
        ground_a=0.04,
        ground_b=0.12,
        ground_c=0.06,
        ground_fine=0.05,
        ground_mottle=0.20,
        ground_snow=0.0,
        snow_patches=0.0,
        ballast=0.44,
        rail=0.16,
        spruce=0.18,
        birch=0.50,
        birch_var=0.35,
        birch_alpha=0.95,
        bush=0.42,
        house_roof=0.24,
        wall_spruce=0.19,
        wall_birch=0.42,
        wall_tex=0.15,
        wall_patch=0.40,
        wall_snow=0.0,
        light=0.92,
        exposure=1.0,
        sun=0.02,
        noise=1.0,
        treeline=1.0,
    ),
    "winter": _Look(
        sky_top=0.5,
        sky_hor=0.68,
        cloud_cover=0.90,
        cloud_tone=0.7,
        cloud_contrast=0.25,
        visibility=35.0,
        mtn_rock=0.55,
        mtn_snow=0.90,
        snowline=0.0,
        hill=0.55,
        ground=0.9,
        ground_a=0.04,
        ground_b=0.0,
        ground_c=0.0,
        ground_fine=0.03,
        ground_mottle=0.02,
        ground_snow=1.0,
        snow_patches=0.0,
        ballast=0.80,
        rail=0.45,
        spruce=0.2,
        birch=0.40,
        birch_var=0.05,
        birch_alpha=0.40,
        bush=0.84,
        house_roof=0.90,
        wall_spruce=0.3,
        wall_birch=0.46,
        wall_tex=0.08,
        wall_patch=0.0,
        wall_snow=0.35,
        light=0.95,
        exposure=0.97,
        sun=0.015,
        noise=1.0,
        treeline=0.4,
    ),
}


class _Conditions:
    """One traversal of one season: weather, exposure drift, camera offset, sensor noise.

    Season-level conditions come from a generator seeded with (seed, season), the rest from
    one seeded with (seed, season, traversal).
    """

    def __init__(self, seed: int, season: str, traversal: int):
        self.look = _LOOKS[season]
        index = SEASONS.index(season)
        srng = np.random.default_rng([seed, 0x5EA5, index])
        trng = np.random.default_rng([seed, 0x5EA5, index, traversal, 1])
        self._season = {k: _Noise1D(srng, 1021 - 2 * i) for i, k in enumerate(_SEASON_DRIFT)}
        self._traversal = {k: _Noise1D(trng, 1019 - 2 * i) for i, k in enumerate(_TRAVERSAL_DRIFT)}
        self.sun_az = srng.uniform(0.0, 2.0 * np.pi)  # the season's time of day
        cover = self.look.cloud_cover + trng.normal(0, 0.1)
        self.cloud_cover = float(np.clip(cover, 0.05, 0.97))
        self.cloud_tex = _texture(trng, (32, 2048), [((8, 64), 1.0), ((4, 16), 0.6), ((2, 8), 0.3)])
        self.cloud_speed = trng.uniform(0.2, 0.6)
        # Sensor noise: two tables of co-prime lengths, so a frame's pattern repeats only
        # after ~10^6 frames; drawn from this traversal's own generator.
        self.noise_a = trng.standard_normal((509, _H, _W), np.float32) * np.float32(_NOISE)
        self.noise_b = trng.standard_normal((503, _H, _W), np.float32) * np.float32(_NOISE)

    def drift(self, name: str, fid: np.ndarray) -> np.ndarray:
        """Value of one slowly drifting nuisance at frames ``fid`` (season + traversal part)."""
        t = fid / _DRIFT_SCALE[name]
        out = np.zeros_like(t)
        if name in _SEASON_DRIFT:
            out += _SEASON_DRIFT[name] * self._season[name](t)
        if name in _TRAVERSAL_DRIFT:
            out += _TRAVERSAL_DRIFT[name] * self._traversal[name](t)
        return out


# ------------------------------------------------------------------------------ rendering


def _render_block(world: _World, cond: _Conditions, frame_ids: np.ndarray) -> np.ndarray:
    look = cond.look
    fid = frame_ids.astype(np.float64)
    b = len(fid)
    z = fid + cond.drift("jitter", fid)  # imperfect synchronisation of the videos
    theta = world.heading(z)
    kappa = world.curvature(z)
    cx = 32.0 + cond.drift("shift", fid)  # lateral camera offset, pixels
    yh = _HORIZON + cond.drift("pitch", fid)
    du = _U[None, :] - cx[:, None]  # (B, W) column offset from the optical axis, pixels
    dy = _Y[None, :] - yh[:, None]  # (B, H) row offset below the horizon, pixels
    ep = -dy  # pixels above the horizon

    # Illumination drift along the route (per traversal) -----------------------------------
    sun_side = _tri(theta - cond.sun_az)  # -1..1: sun from the left .. right
    light = look.light * (1.0 + cond.drift("light", fid))  # (B,)
    sky_gain = 1.0 + cond.drift("sky", fid)

    # Sky, mountains and hills: rows above the horizon only (the horizon stays in row 12).
    top_rows = int(np.ceil(_HORIZON + 0.4))  # rows [0, top_rows) can show sky
    ept = ep[:, :top_rows].astype(np.float32)  # (B, R) pixels above the horizon
    e = _clip01(ept / _HORIZON)  # 0 at the horizon, 1 at the top row
    sky = look.sky_hor + (look.sky_top - look.sky_hor) * e  # (B, R)
    az_px = (theta * _F)[:, None] + du  # (B, W) world azimuth in pixels
    cmx = np.mod(az_px * 0.5 + (cond.cloud_speed * fid)[:, None], 2048.0).astype(np.float32)
    cmx = np.broadcast_to(cmx[:, None, :], (b, top_rows, _W))
    cmy = np.maximum(ept, 0.0)[:, :, None] * np.float32(1.2)
    clouds = _sample(cond.cloud_tex, cmx, cmy)
    cover = cond.cloud_cover + cond.drift("clouds", fid)
    thresh = (1.0 - 2.0 * cover).astype(np.float32)[:, None, None]
    cl = _clip01((clouds - thresh) * np.float32(1.5 * look.cloud_contrast))
    np.minimum(cl, np.float32(look.cloud_contrast), out=cl)
    sky3 = sky[:, :, None]
    top = (sky3 + (np.float32(look.cloud_tone) - sky3) * cl) * sky_gain.astype(np.float32)[
        :, None, None
    ]

    # Far mountains: turn with the heading, slow parallax, snow above the snowline -------------
    ang = theta[:, None] + du / _F  # radians
    a = ang * 7.0 + (z * 0.006)[:, None]
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
    mtn = (np.float32(rock) + np.float32(snowt - rock) * snow) * sky_gain.astype(np.float32)[
        :, None, None
    ]
    top += cov * (mtn - top)

    # Forested hills, middle distance ------------------------------------------------------
    c = ang * 3.0 + (z * 0.035)[:, None]
    hh = (2.8 * _clip01(world.hill_amp(z / 150.0) + 0.6))[:, None] * (
        0.55 + 0.45 * world.hill1(c) + 0.12 * world.hill2(c * 6.0)
    )
    cov = _clip01(hh.astype(np.float32)[:, None, :] - ept[:, :, None] + np.float32(0.5))
    haze = 30.0 / (30.0 + look.visibility)
    hill = ((look.hill * (1 - haze) + look.sky_hor * haze) * light).astype(np.float32)
    top += cov * (hill[:, None, None] - top)

    # Ground plane: rows from the one holding the horizon down --------------------------------
    g0 = top_rows - 1
    img = np.empty((b, _H, _W), np.float32)
    img[:, :g0] = top[:, :g0]
    dyg = dy[:, g0:]
    d_row = _CAM_H * _F / np.maximum(dyg, 0.35)  # (B, R) depth of each row's ground point
    d3 = d_row.astype(np.float32)[:, :, None]
    duf = du.astype(np.float32)[:, None, :]
    xg = duf * (d3 / np.float32(_F)) - (0.5 * kappa).astype(np.float32)[:, None, None] * d3 * d3
    zg = z[:, None] + d_row  # (B, R)
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
    fine_fade = (1.0 / (1.0 + d_row / 6.0)).astype(np.float32)[:, :, None]
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
    # Track: ballast bed and two rails (anti-aliased by the pixel footprint).
    inv_foot = _F / d3  # pixels per ground unit
    ax = np.abs(xg)
    ballast = _clip01((np.float32(_BALLAST) - ax) * inv_foot + np.float32(0.5))
    g += (np.float32(look.ballast) - g) * ballast
    rail = _clip01(
        (np.float32(_RAIL_W) - np.abs(ax - np.float32(_RAIL_X))) * inv_foot + np.float32(0.5)
    )
    np.minimum(rail, np.float32(2.0 * _RAIL_W) * inv_foot, out=rail)
    g += (np.float32(look.rail) - g) * rail
    fog = (d_row / (d_row + look.visibility)).astype(np.float32)[:, :, None]
    g += (np.float32(look.sky_hor * 0.85) - g) * fog
    g *= light.astype(np.float32)[:, None, None]
    cov = _clip01(dyg + 0.5).astype(np.float32)[:, :, None]
    hz = top[:, g0:]  # the horizon row: sky above the line, ground below
    img[:, g0 : g0 + 1] = hz + cov[:, :1] * (g[:, :1] - hz)
    img[:, g0 + 1 :] = g[:, 1:]

    # Forest walls: ray-march every column against the left and right forest edges -------------
    dj = _WALL_D[None, None, :]  # (1, 1, J)
    slope = (du / _F)[:, :, None]  # (B, W, 1)
    xr = slope * dj - 0.5 * kappa[:, None, None] * dj * dj  # ray lateral at each depth
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
    h_top = np.where(right, world.wall_height(z_hit, 1), world.wall_height(z_hit, -1))
    jag_fade = _clip01(1.6 - d_hit / 25.0)
    jag = np.abs(world.jag(z_hit * 1.3 + 50.0 * right)) - 0.5  # spruce tips
    h_top = h_top + 1.1 * look.treeline * jag_fade * jag
    top = (yh[:, None] + _F * (_CAM_H - h_top) / d_hit).astype(np.float32)  # (B, W)
    bot = (yh[:, None] + _F * _CAM_H / d_hit).astype(np.float32)
    y3 = _Y.astype(np.float32)[None, :, None]
    cov = _clip01(y3 - top[:, None, :] + np.float32(0.5))
    cov *= _clip01(bot[:, None, :] - y3 + np.float32(0.5))
    cov *= any_hit[:, None, :]
    mix = _clip01(0.5 + 0.8 * world.mix(z_hit / 30.0 + 11.0 * right))  # birch share
    tone = look.wall_spruce + (look.wall_birch - look.wall_spruce) * mix
    hgt = (
        _CAM_H
        - (y3 - yh.astype(np.float32)[:, None, None]) * (d_hit / _F).astype(np.float32)[:, None, :]
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
    img += cov * (wall - img)

    # Standalone objects, painted far to near ----------------------------------------------------
    img = _draw_objects(world, cond, img, z, kappa, cx, yh, light, d_hit, any_hit)

    # Exposure, side light, gradients, vignetting, noise --------------------------------------
    # Auto-exposure pulls each frame's mean part of the way towards a target level.
    # (float64 row sums of a contiguous array: the same bits whatever the batch.)
    mean = img.reshape(b, -1).astype(np.float64).sum(axis=1) / (_H * _W)
    auto = 1.0 + _AUTO_EXPOSURE * (_AE_TARGET / np.maximum(mean, 0.05) - 1.0)
    gain = auto * look.exposure * (1.0 + cond.drift("gain", fid))
    offset = cond.drift("offset", fid)
    hg = cond.drift("hgrad", fid) + look.sun * sun_side
    vg = cond.drift("vgrad", fid)
    img = img * gain[:, None, None].astype(np.float32)
    img += (
        offset[:, None, None]
        + hg[:, None, None] * ((_U - 32.0) / 32.0)[None, None, :]
        + vg[:, None, None] * ((_Y - 16.0) / 16.0)[None, :, None]
    ).astype(np.float32)
    img *= _VIGNETTE
    ids = frame_ids.astype(np.int64)
    noise = cond.noise_a[ids % 509] + cond.noise_b[ids % 503]
    if look.noise != 1.0:
        noise *= np.float32(look.noise)
    img += noise
    return np.clip(img, 0.0, 1.0, out=img)


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


def _draw_objects(
    world: _World,
    cond: _Conditions,
    img: np.ndarray,
    z: np.ndarray,
    kappa: np.ndarray,
    cx: np.ndarray,
    yh: np.ndarray,
    light: np.ndarray,
    wall_d: np.ndarray,
    wall_hit: np.ndarray,
) -> np.ndarray:
    """Paint the standalone objects into ``img`` (B, H, W), farthest object first."""
    look = cond.look
    objs = world.objects(float(z.min()) + _D_NEAR, float(z.max()) + _D_FAR)
    if len(objs.z) == 0:
        return img
    lo = np.searchsorted(objs.z, z + _D_NEAR, side="left")
    hi = np.searchsorted(objs.z, z + _D_FAR, side="left")
    count = hi - lo
    if count.sum() == 0:
        return img
    # Every (frame, object) view, grouped by object.
    pb = np.repeat(np.arange(len(z)), count)
    po = np.repeat(lo - np.cumsum(count) + count, count) + np.arange(count.sum())
    order = np.lexsort((pb, po))
    pb, po = pb[order], po[order]
    d = objs.z[po] - z[pb]  # depth
    scale = _F / d  # pixels per unit at the object's depth
    xc = cx[pb] + _F * (objs.x[po] / d + 0.5 * kappa[pb] * d)  # column of the object's axis
    base = yh[pb] + _CAM_H * scale  # row of the object's foot
    # Hidden behind a forest wall that juts out in front of it?
    col = np.clip(np.floor(xc), 0, _W - 1).astype(np.int64)
    wd = np.where(wall_hit, wall_d, np.inf)[pb, col]
    keep = (d < wd) & (xc > -20.0) & (xc < _W + 20.0)
    pb, po, d, scale, xc, base = pb[keep], po[keep], d[keep], scale[keep], xc[keep], base[keep]
    if not len(pb):
        return img
    kind = objs.kind[po]
    hw, val = _object_profiles(
        look, kind, objs.height[po], objs.width[po], objs.tone[po], base, scale
    )
    fog = (d / (d + look.visibility))[:, None]
    lit = light[pb]
    val = ((val + (look.sky_hor * 0.8 - val) * fog) * lit[:, None]).astype(np.float32)
    hw_px = hw * scale[:, None]  # (P, H) half-width, pixels
    alpha = np.where(kind == _BIRCH, look.birch_alpha, 1.0)[:, None]
    amax = (np.minimum(1.0, 2.0 * hw_px) * alpha).astype(np.float32)
    hwp = (hw_px + 0.5).astype(np.float32)
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


# ------------------------------------------------------------------------------ public API


def _check_season(season: str) -> None:
    if season not in SEASONS:
        raise UserError(
            f"unknown season {season!r} for the synthetic route: use one of {', '.join(SEASONS)}"
        )


def _check_int(value, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise UserError(
            f"{name} must be an integer >= {minimum}, got {value!r}: "
            f"set {name} to a whole number of at least {minimum}"
        )
    return int(value)


def render_season(
    frame_ids: np.ndarray, season: str, seed: int = 0, traversal: int = 0
) -> np.ndarray:
    """Render the places ``frame_ids`` of the route in ``season``: (N, 32, 64) float32 in [0,1].

    ``frame_ids`` are place indices along the route (any subset, any order, repeats allowed);
    rendering a subset gives exactly the same pixels as those rows of rendering everything.
    The world (what stands where) depends only on ``seed``; ``season`` and ``traversal``
    (another ride in the same season: other clouds, exposure drift, camera offset, noise)
    change only the appearance.
    """
    _check_season(season)
    seed = _check_int(seed, "seed", 0)
    traversal = _check_int(traversal, "traversal", 0)
    ids = np.asarray(frame_ids)
    if ids.ndim != 1 or (ids.size and not np.issubdtype(ids.dtype, np.integer)):
        raise UserError(
            f"frame_ids must be a 1-D array of integers, got shape {ids.shape} "
            f"dtype {ids.dtype}: pass e.g. np.arange(n_frames)"
        )
    ids = ids.astype(np.int64)
    if ids.size and ids.min() < 0:
        raise UserError("frame_ids must be >= 0: pass place indices along the route")
    out = np.empty((len(ids), _H, _W), np.float32)
    if not len(ids):
        return out
    world = _world(seed)
    cond = _Conditions(seed, season, traversal)
    order = np.argsort(ids, kind="stable")  # nearby frames share objects: render in order
    for s in range(0, len(ids), _CHUNK):
        sel = order[s : s + _CHUNK]
        out[sel] = _render_block(world, cond, ids[sel])
    return out


def synthetic_route(
    n_frames: int = DEFAULT_N_FRAMES,
    seasons: Iterable[str] = ("spring", "summer", "fall"),
    seed: int = 0,
    frame_step: int = 1,
) -> Route:
    """The built-in route: ``frame_ids = arange(0, n_frames, frame_step)``, traversal 0 of
    every season, as a frame-aligned :class:`Route`."""
    n_frames = _check_int(n_frames, "n_frames", 1)
    frame_step = _check_int(frame_step, "frame_step", 1)
    seasons = (seasons,) if isinstance(seasons, str) else tuple(seasons)
    if not seasons:
        raise UserError(f"no seasons asked for: name at least one of {', '.join(SEASONS)}")
    for season in seasons:
        _check_season(season)
    if len(set(seasons)) != len(seasons):
        raise UserError(f"season listed twice in {', '.join(seasons)}: name each season once")
    frame_ids = np.arange(0, n_frames, frame_step, dtype=np.int64)
    images = {season: render_season(frame_ids, season, seed=seed) for season in seasons}
    return Route(frame_ids, images)
