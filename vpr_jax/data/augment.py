"""Jittable image augmentation for auto-encoder training.

Matches Table 2 of the study: random horizontal flip, width shift 0.2, height shift 0.2, no
rotation and no vertical flip, with Keras ``ImageDataGenerator`` semantics: each shift is drawn
uniformly in ``[-frac * size, +frac * size]`` and the pixels it uncovers repeat the nearest edge
pixel (``fill_mode="nearest"``). Shifts are whole pixels, so every output pixel is a copy of an
input pixel (no interpolation): values never leave the input's range.

Images are float32 ``(H, W)`` or ``(H, W, 1)``; batches put a leading ``B`` axis in front. The
config holds Python scalars only and must be static under ``jax.jit``, e.g.
``jax.jit(augment_batch, static_argnames="cfg")``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

__all__ = [
    "PLACE",
    "TABLE2",
    "AugmentConfig",
    "augment_batch",
    "augment_one",
    "flip_image",
    "max_shift",
    "shift_image",
]


class AugmentConfig(NamedTuple):
    """Table 2 of the study; shifts are fractions of the image width / height."""

    horizontal_flip: bool = True
    width_shift: float = 0.2
    height_shift: float = 0.2


TABLE2 = AugmentConfig()  # the study's settings, the default of every function here
# Augmentation that keeps the place: no flip (it moves a building to the other side of the
# track) and small shifts (3 pixels of 64 across, 1 of 32 down: a train a little off its
# line or pitched), train.augment=place.
PLACE = AugmentConfig(horizontal_flip=False, width_shift=0.05, height_shift=0.05)


def max_shift(fraction: float, size: int) -> int:
    """The largest whole-pixel shift a ``fraction`` of ``size`` pixels allows.

    Floor, so a drawn shift never exceeds ``fraction * size`` (0.2 * 64 = 12.8 -> 12); the small
    epsilon keeps e.g. 0.29 * 100 = 28.999999999999996 at 29.
    """
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"shift fraction must be in [0, 1], got {fraction}")
    return math.floor(fraction * size + 1e-9)


def shift_image(
    image: Float[Array, "h w *c"], dy: Int[ArrayLike, ""], dx: Int[ArrayLike, ""]
) -> Float[Array, "h w *c"]:
    """Move the content ``dy`` pixels down and ``dx`` pixels right, repeating edge pixels.

    ``out[y, x] = image[clip(y - dy), clip(x - dx)]``: a gather with clipped indices is
    nearest-edge fill for any shift, traced or not, with no branching.
    """
    h, w = image.shape[0], image.shape[1]
    rows = jnp.clip(jnp.arange(h) - dy, 0, h - 1)
    cols = jnp.clip(jnp.arange(w) - dx, 0, w - 1)
    return jnp.take(jnp.take(image, rows, axis=0), cols, axis=1)


def flip_image(image: Float[Array, "h w *c"]) -> Float[Array, "h w *c"]:
    """Mirror left-right (the width axis)."""
    return image[:, ::-1]


def augment_one(
    key: PRNGKeyArray, image: Float[Array, "h w *c"], cfg: AugmentConfig = TABLE2
) -> Float[Array, "h w *c"]:
    """One random shift, then (with probability 0.5) a left-right flip, of one image.

    ``dy ~ round(uniform(-height_shift * H, height_shift * H))``, clipped to ``max_shift`` so
    rounding never overshoots the range; ``dx`` likewise with the width. Keras flips after the
    affine shift; the order only changes the sign of ``dx``, whose law is symmetric anyway.
    """
    h, w = image.shape[0], image.shape[1]
    k_flip, k_dy, k_dx = jax.random.split(key, 3)
    out = image
    # cfg is static: disabled parts are left out of the graph, so an all-off config is identity.
    if cfg.height_shift > 0 or cfg.width_shift > 0:
        dy = _draw_shift(k_dy, cfg.height_shift, h)
        dx = _draw_shift(k_dx, cfg.width_shift, w)
        out = shift_image(out, dy, dx)
    if cfg.horizontal_flip:
        out = jnp.where(jax.random.bernoulli(k_flip), flip_image(out), out)
    return out


def augment_batch(
    key: PRNGKeyArray, images: Float[Array, "b h w *c"], cfg: AugmentConfig = TABLE2
) -> Float[Array, "b h w *c"]:
    """Augment every image of a batch independently (one subkey per image)."""
    keys = jax.random.split(key, images.shape[0])
    # Close over cfg rather than vmapping it: its Python scalars must stay static.
    return jax.vmap(lambda k, im: augment_one(k, im, cfg))(keys, images)


def _draw_shift(key: PRNGKeyArray, fraction: float, size: int) -> Int[Array, ""]:
    """``round(uniform(-fraction * size, fraction * size))`` kept within ``max_shift``."""
    limit = max_shift(fraction, size)
    if limit == 0:
        return jnp.zeros((), jnp.int32)
    span = fraction * size
    shift = jnp.round(jax.random.uniform(key, (), minval=-span, maxval=span))
    return jnp.clip(shift, -limit, limit).astype(jnp.int32)


class ConditionConfig(NamedTuple):
    """A change of conditions that keeps the place (``condition_change``): what a season,
    the weather or the hour does to a frame, roughly. Ranges are uniform draws."""

    brightness: float = 0.2  # added to every pixel, in [-b, b]
    contrast: float = 0.4  # about the image's mean, a factor in [1 - c, 1 + c]
    gamma: float = 0.5  # pixels to the power g, log g uniform in [-log(1 + g), log(1 + g)]
    blur: float = 0.5  # chance of a 3x3 box blur (mist, motion)
    shadow: float = 0.5  # chance of a vertical band darkened to 40-80 % (a shadow, a pole)
    noise: float = 0.02  # standard deviation of added Gaussian noise
    shift: AugmentConfig = PLACE  # small shifts, no flip (they keep the place)


CONDITIONS = ConditionConfig()


def condition_change(
    key: PRNGKeyArray, image: Float[Array, "h w"], cfg: ConditionConfig = CONDITIONS
) -> Float[Array, "h w"]:
    """One random change of conditions of one image, clipped to [0, 1]: shift, gamma,
    contrast, brightness, then maybe a blur and a shadow band, then noise."""
    shift_key, draw_key, noise_key = jax.random.split(key, 3)
    h, w = image.shape
    # one draw of every random number the change needs (one generator call compiles and
    # runs far faster than eight): u in [0, 1) each
    u = jax.random.uniform(draw_key, (8,))
    between = lambda i, low, high: low + (high - low) * u[i]  # noqa: E731
    out = augment_one(shift_key, image, cfg.shift)
    log_g = jnp.log1p(cfg.gamma)
    out = jnp.clip(out, 0.0, 1.0) ** jnp.exp(between(0, -log_g, log_g))
    factor = between(1, 1 - cfg.contrast, 1 + cfg.contrast)
    out = (out - jnp.mean(out)) * factor + jnp.mean(out)
    out = out + between(2, -cfg.brightness, cfg.brightness)
    padded = jnp.pad(out, 1, mode="edge")
    blurred = sum(padded[dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3)) / 9
    out = jnp.where(u[3] < cfg.blur, blurred, out)
    start = jnp.floor(u[4] * w)
    width = jnp.floor(between(5, w // 16, w // 4 + 1))
    columns = jnp.arange(w)
    band = (columns >= start) & (columns < start + width)
    shadowed = jnp.where(band[None, :], out * between(6, 0.4, 0.8), out)
    out = jnp.where(u[7] < cfg.shadow, shadowed, out)
    out = out + cfg.noise * jax.random.normal(noise_key, out.shape)
    return jnp.clip(out, 0.0, 1.0)


def condition_views(
    key: PRNGKeyArray, images: Float[Array, "b h w"], cfg: ConditionConfig = CONDITIONS
) -> Float[Array, "b 2 h w"]:
    """Two independent changes of conditions of every image: a positive pair each."""
    keys = jax.random.split(key, (images.shape[0], 2))
    view = jax.vmap(jax.vmap(lambda k, im: condition_change(k, im, cfg), (0, None)), (0, 0))
    return view(keys, images)
