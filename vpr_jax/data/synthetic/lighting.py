"""Weather and lighting of one ride: slow drift of illumination, exposure and camera pose
along the route, the sun side, auto-exposure, vignetting and sensor noise.

Exposure, illumination (sun side, ground and sky brightness, gradients) drift slowly along
the route: global, low-frequency patterns, mostly shared by the rides of one season (same
time of year and of day), a little different on every ride; a partial auto-exposure pulls
every frame towards one mean brightness. Per ride, the camera sits up to a pixel or so to
the side and the frames are not perfectly synchronised (both varying slowly), the sky and
clouds differ, and there is sensor noise.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vpr_jax.data.synthetic.camera import _H, _U, _W, _Y, _View
from vpr_jax.data.synthetic.noise import _Noise1D, _texture, _tri
from vpr_jax.data.synthetic.season import _LOOKS, SEASONS

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
_VIGNETTE = (
    1.0 - 0.10 * ((_U[None, :] - 32.0) / 32.0) ** 2 - 0.06 * ((_Y[:, None] - 16.0) / 16.0) ** 2
).astype(np.float32)


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


class _Light(NamedTuple):
    """Illumination of a block of frames along the route (per traversal), each (B,)."""

    sun_side: np.ndarray  # -1..1: sun from the left .. right
    light: np.ndarray  # illumination of the ground and everything on it
    sky_gain: np.ndarray  # relative sky brightness


def _illumination(cond: _Conditions, view: _View) -> _Light:
    sun_side = _tri(view.theta - cond.sun_az)
    light = cond.look.light * (1.0 + cond.drift("light", view.fid))
    sky_gain = 1.0 + cond.drift("sky", view.fid)
    return _Light(sun_side, light, sky_gain)


def _expose(cond: _Conditions, img: np.ndarray, view: _View, light: _Light) -> np.ndarray:
    """Auto-exposure, exposure drift, side light, gradients and vignetting of (B, H, W)."""
    look, fid = cond.look, view.fid
    # Auto-exposure pulls each frame's mean part of the way towards a target level.
    # (float64 row sums of a contiguous array: the same bits whatever the batch.)
    mean = img.reshape(len(img), -1).astype(np.float64).sum(axis=1) / (_H * _W)
    auto = 1.0 + _AUTO_EXPOSURE * (_AE_TARGET / np.maximum(mean, 0.05) - 1.0)
    gain = auto * look.exposure * (1.0 + cond.drift("gain", fid))
    offset = cond.drift("offset", fid)
    hg = cond.drift("hgrad", fid) + look.sun * light.sun_side
    vg = cond.drift("vgrad", fid)
    img = img * gain[:, None, None].astype(np.float32)
    img += (
        offset[:, None, None]
        + hg[:, None, None] * ((_U - 32.0) / 32.0)[None, None, :]
        + vg[:, None, None] * ((_Y - 16.0) / 16.0)[None, :, None]
    ).astype(np.float32)
    img *= _VIGNETTE
    return img


def _add_sensor_noise(cond: _Conditions, img: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Add the traversal's sensor noise of frames ``ids`` to ``img`` and clip to [0, 1]."""
    ids = ids.astype(np.int64)
    noise = cond.noise_a[ids % 509] + cond.noise_b[ids % 503]
    if cond.look.noise != 1.0:
        noise *= np.float32(cond.look.noise)
    img += noise
    return np.clip(img, 0.0, 1.0, out=img)
