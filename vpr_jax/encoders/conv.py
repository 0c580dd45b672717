"""A stride-1 NHWC convolution whose kernel gradient is k*k matrix products, for CPU training.

XLA's CPU backend computes a convolution's kernel gradient as one more convolution, and
that one runs far below the machine's matrix-product speed (docs/speed.md,
"Auto-encoders"). The kernel gradient of a stride-1 convolution is a sum over the k*k
kernel taps of one product each,

    dW[i, j] = x_padded[:, i : i + H, j : j + W, :]^T  @  dY        ((C, N H W) @ (N H W, O)),

which runs near the product speed when both channel counts are large. The input gradient is
XLA's forward convolution of dY with the flipped kernel, as fast here as XLA's own
transposed convolution, which returns garbage on this backend when a side's padding exceeds
k - 1 (the tests check the odd paddings against numpy).

``conv_general_dilated`` has ``jax.lax.conv_general_dilated``'s signature so that
``flax.nnx.Conv(..., conv_general_dilated=conv_general_dilated)`` uses it. Anything other
than a stride-1, undilated, ungrouped NHWC/HWIO 2-D convolution on the CPU backend goes to
``lax.conv_general_dilated`` unchanged (GPUs' convolution libraries do this well), and so
do layers with fewer than ``MIN_CHANNELS`` input or output channels.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Float

__all__ = ["conv_general_dilated", "conv_stride1", "input_gradient", "kernel_gradient"]

_NHWC = ("NHWC", "HWIO", "NHWC")
Pads = tuple[tuple[int, int], tuple[int, int]]
# The per-tap products pay only when both channel counts are this large: with few input or
# output channels each product is a thin matrix-vector pass over a copied window, and XLA's
# own kernel gradient wins (docs/speed.md, "Auto-encoders").
MIN_CHANNELS = 32


def _lax_conv(x: Array, w: Array, pads: Pads) -> Array:
    return lax.conv_general_dilated(x, w, (1, 1), pads, dimension_numbers=_NHWC)


def kernel_gradient(
    x: Float[Array, "n h w c"],
    dy: Float[Array, "n ho wo o"],
    kernel_hw: tuple[int, int],
    pads: Pads,
) -> Float[Array, "kh kw c o"]:
    """d(sum(dy * conv(x, W))) / dW of a stride-1 convolution: one product per kernel tap."""
    (kh, kw), (ho, wo) = kernel_hw, dy.shape[1:3]
    xp = jnp.pad(x, ((0, 0), *pads, (0, 0)))
    dy_rows = dy.reshape(-1, dy.shape[-1])  # (N Ho Wo, O)
    taps = [
        xp[:, i : i + ho, j : j + wo, :].reshape(-1, x.shape[-1]).T @ dy_rows
        for i in range(kh)
        for j in range(kw)
    ]
    return jnp.stack(taps).reshape(kh, kw, x.shape[-1], dy.shape[-1])


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def conv_stride1(x: Float[Array, "n h w c"], w: Float[Array, "kh kw c o"], pads: Pads):
    """``lax.conv_general_dilated`` (stride 1, NHWC/HWIO, explicit pads), kernel gradient
    by ``kernel_gradient``."""
    return _lax_conv(x, w, pads)


def _forward(x, w, pads):
    return _lax_conv(x, w, pads), (x, w)


def input_gradient(
    dy: Float[Array, "n ho wo o"], w: Float[Array, "kh kw c o"], pads: Pads
) -> Float[Array, "n h w c"]:
    """d(sum(dy * conv(x, w))) / dx of a stride-1 convolution, as a forward convolution of
    ``dy`` with the flipped kernel: ``dy`` padded by k - 1 - pad on each side (a negative
    amount crops), VALID."""
    k = w.shape[:2]
    spatial = [(k[d] - 1 - pads[d][0], k[d] - 1 - pads[d][1], 0) for d in range(2)]
    dy = lax.pad(dy, jnp.zeros((), dy.dtype), [(0, 0, 0), *spatial, (0, 0, 0)])
    w_flipped = jnp.swapaxes(w[::-1, ::-1], 2, 3)  # (kh, kw, o, c)
    return _lax_conv(dy, w_flipped, ((0, 0), (0, 0)))


def _backward(pads, residuals, dy):
    x, w = residuals
    dx = input_gradient(dy, w, pads)
    return dx.astype(x.dtype), kernel_gradient(x, dy, w.shape[:2], pads).astype(w.dtype)


conv_stride1.defvjp(_forward, _backward)


def _is_nhwc(dimension_numbers, lhs_shape, rhs_shape) -> bool:
    if dimension_numbers is None:
        return False
    want = lax.conv_dimension_numbers(lhs_shape, rhs_shape, _NHWC)
    got = lax.conv_dimension_numbers(lhs_shape, rhs_shape, dimension_numbers)
    return got == want


def conv_general_dilated(
    lhs,
    rhs,
    window_strides,
    padding,
    lhs_dilation=None,
    rhs_dilation=None,
    dimension_numbers=None,
    feature_group_count=1,
    precision=None,
    **kwargs,
):
    """``jax.lax.conv_general_dilated``, taking the fast kernel gradient where it applies."""
    ones = (1,) * (lhs.ndim - 2)
    fast = (
        jax.default_backend() == "cpu"
        and lhs.ndim == 4
        and tuple(window_strides) == ones
        and tuple(lhs_dilation or ones) == ones
        and tuple(rhs_dilation or ones) == ones
        and feature_group_count == 1
        and precision is None
        and all(v is None for v in kwargs.values())
        and _is_nhwc(dimension_numbers, lhs.shape, rhs.shape)
        and min(rhs.shape[2:]) >= MIN_CHANNELS
    )
    if not fast:
        return lax.conv_general_dilated(
            lhs,
            rhs,
            window_strides,
            padding,
            lhs_dilation,
            rhs_dilation,
            dimension_numbers,
            feature_group_count,
            precision=precision,
            **kwargs,
        )
    if isinstance(padding, str):
        pads = lax.padtype_to_pads(lhs.shape[1:3], rhs.shape[:2], (1, 1), padding)
    else:
        pads = padding
    pads = tuple((int(lo), int(hi)) for lo, hi in pads)
    return conv_stride1(lhs, rhs, pads)
