"""Float32 where the math needs it, on any device (DESIGN.md, "Any device").

Accelerators compute float32 matrix products at lower precision unless told: TF32 (a 10-bit
mantissa, a relative rounding near 5e-4 a product) on recent NVIDIA GPUs, bfloat16 passes on
TPUs; a CPU computes float32 whatever it is told. Every product whose result the suite needs
at float32 accuracy says so where it is written, not through a global flag, so a program that
imports vpr_jax and sets its own default still gets the numbers the suite scored:

- ``f32_matmul(a, b)``: ``a @ b`` at float32 on every device. The fits (scatter, Gram and
  Rayleigh-Ritz products, projections, whitening, FastICA's updates, on which its
  elementwise convergence test is taken), the checks on them (orthonormality) and every
  built-in encoder use it.
- ``float32_products()``: float32 as the default of the products traced inside it that
  state none, for code that takes no precision argument: the auto-encoders' Flax layers
  when they make codes (not when they train), and a user's method (its fit and encode), so
  a method of one's own is scored and handed out (``load_encoder``) as a built-in is.
- ``MATCHING``: the matcher's one choice (``matching.precision``): float32, or
  the platform's fastest, where speed on a GPU matters most (docs/speed.md, "Any device").

The auto-encoders' training steps state nothing and keep the platform's default
(``vpr_jax.encoders.train_programs.PLATFORM_PRECISION``): their rounding is noise next to
SGD's, and nothing is chosen by it (a model's epoch is kept by recall on codes made at
float32).
tests/test_precision.py reads every program a fit, an encoder and the matcher compile and
fails on a product that states no precision.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Float

from vpr_jax.compute_config import MATCHING_PRECISIONS

FLOAT32 = lax.Precision.HIGHEST  # float32 products on every device (TF32 and bf16 passes: no)

# matching.precision -> the precision of the matcher's products. "default" is the platform's
# fastest: TF32 on recent NVIDIA GPUs, bfloat16 passes on TPUs, float32 on a CPU.
MATCHING = dict(zip(MATCHING_PRECISIONS, (FLOAT32, lax.Precision.DEFAULT), strict=True))


def f32_matmul(a: Float[Array, "..."], b: Float[Array, "..."]) -> Float[Array, "..."]:
    """``a @ b`` computed at float32 on every device."""
    return jnp.matmul(a, b, precision=FLOAT32)


def float32_products():
    """A context in which products traced without a stated precision are computed at
    float32 (``jax.default_matmul_precision``; a product that states one keeps it). It
    acts where a function is traced, so it goes inside the jitted function, around the
    code whose products it pins."""
    return jax.default_matmul_precision("float32")


def with_float32_products(fn: Callable) -> Callable:
    """``fn`` run inside ``float32_products()``: jit the result, and the products ``fn``
    traces without a stated precision are float32."""

    @functools.wraps(fn)
    def pinned(*args, **kwargs):
        with float32_products():
            return fn(*args, **kwargs)

    return pinned


def matching_precision(name: str) -> lax.Precision:
    """The precision ``matching.precision`` names."""
    if name not in MATCHING:
        raise ValueError(f"unknown matching precision {name!r}: use {' or '.join(MATCHING)}")
    return MATCHING[name]
