"""The CPU convolution with a product-based kernel gradient against XLA's own convolution."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx
from jax import lax

from vpr_jax.encoders.conv import MIN_CHANNELS, conv_general_dilated, conv_stride1

NHWC = ("NHWC", "HWIO", "NHWC")


def _data(shape_x, shape_w, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=shape_x).astype(np.float32)
    w = rng.normal(size=shape_w).astype(np.float32)
    return jnp.asarray(x), jnp.asarray(w)


def _loss(conv, padding):
    # A non-linear loss so the output cotangent differs at every position.
    def loss(x, w):
        y = conv(x, w, (1, 1), padding, dimension_numbers=NHWC)
        return jnp.sum(jnp.sin(y) * jnp.arange(y.size, dtype=y.dtype).reshape(y.shape) / y.size)

    return loss


def _numpy_conv_vjp(x, w, pads, dy):
    """y = conv(x, w) and its vjp (dx, dw) by summing over kernel taps in float64."""
    x, w, dy = (np.asarray(a, np.float64) for a in (x, w, dy))
    (kh, kw), (ho, wo) = w.shape[:2], dy.shape[1:3]
    xp = np.pad(x, ((0, 0), *pads, (0, 0)))
    y, dxp, dw = np.zeros(dy.shape), np.zeros(xp.shape), np.zeros(w.shape)
    for i in range(kh):
        for j in range(kw):
            window = xp[:, i : i + ho, j : j + wo]
            y += window @ w[i, j]
            dxp[:, i : i + ho, j : j + wo] += dy @ w[i, j].T
            dw[i, j] = np.einsum("nhwc,nhwo->co", window, dy)
    (top, _), (left, _) = pads
    return y, dxp[:, top : top + x.shape[1], left : left + x.shape[2]], dw


@pytest.mark.parametrize("k", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("pads", ["SAME", "VALID", ((2, 0), (1, 3)), ((0, 4), (3, 0))])
def test_value_and_gradients_equal_a_numpy_convolution(k, pads):
    x, w = _data((3, 9, 12, 4), (k, k, 4, 5), seed=k)
    if isinstance(pads, str):
        pads = lax.padtype_to_pads(x.shape[1:3], w.shape[:2], (1, 1), pads)
    pads = tuple(tuple(p) for p in pads)
    y, vjp = jax.vjp(jax.jit(conv_stride1, static_argnums=2), x, w, pads)
    dy = np.random.default_rng(k).normal(size=y.shape).astype(np.float32)
    dx, dw, _ = vjp(jnp.asarray(dy))
    y_np, dx_np, dw_np = _numpy_conv_vjp(x, w, pads, dy)
    np.testing.assert_allclose(y, y_np, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(dx, dx_np, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(dw, dw_np, rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("padding", ["SAME", "VALID"])
def test_gradients_equal_xlas_own_under_jit(padding):
    x, w = _data((4, 16, 32, MIN_CHANNELS), (4, 4, MIN_CHANNELS, MIN_CHANNELS + 8))
    ours = jax.jit(jax.value_and_grad(_loss(conv_general_dilated, padding), argnums=(0, 1)))
    theirs = jax.jit(jax.value_and_grad(_loss(lax.conv_general_dilated, padding), argnums=(0, 1)))
    (v1, (dx1, dw1)), (v2, (dx2, dw2)) = ours(x, w), theirs(x, w)
    np.testing.assert_allclose(v1, v2, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(dx1, dx2, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(dw1, dw2, rtol=1e-4, atol=1e-4)


def _jaxpr(conv, x, w, **kw):
    return str(jax.make_jaxpr(lambda x, w: conv(x, w, padding="SAME", **kw))(x, w))


def test_only_wide_stride_1_nhwc_convolutions_take_the_product_gradient():
    wide = _data((2, 8, 8, MIN_CHANNELS), (3, 3, MIN_CHANNELS, MIN_CHANNELS))
    narrow = _data((2, 8, 8, 3), (3, 3, 3, MIN_CHANNELS))  # XLA's kernel gradient is faster
    nhwc = {"window_strides": (1, 1), "dimension_numbers": NHWC}
    assert "custom_vjp" in _jaxpr(conv_general_dilated, *wide, **nhwc)
    others = [
        (narrow, nhwc),
        (wide, {**nhwc, "window_strides": (2, 2)}),
        (wide, {**nhwc, "rhs_dilation": (2, 2)}),
        (
            (jnp.moveaxis(wide[0], 3, 1), jnp.transpose(wide[1], (3, 2, 0, 1))),
            {"window_strides": (1, 1), "dimension_numbers": ("NCHW", "OIHW", "NCHW")},
        ),
    ]
    for (x, w), kw in others:  # these go to lax unchanged
        assert _jaxpr(conv_general_dilated, x, w, **kw) == _jaxpr(
            lax.conv_general_dilated, x, w, **kw
        )


def test_flax_conv_with_it_trains_like_flax_conv_with_lax():
    x, _ = _data((4, 8, 16, MIN_CHANNELS), (1, 1, 1, 1))
    grads = []
    for conv_fn in (conv_general_dilated, lax.conv_general_dilated):
        layer = nnx.Conv(
            MIN_CHANNELS,
            MIN_CHANNELS + 3,
            (4, 4),
            padding="SAME",
            conv_general_dilated=conv_fn,
            rngs=nnx.Rngs(0),
        )
        grads.append(nnx.grad(lambda m: jnp.mean(m(x) ** 2))(layer))
    np.testing.assert_allclose(
        grads[0]["kernel"][...], grads[1]["kernel"][...], rtol=1e-4, atol=1e-6
    )
    np.testing.assert_allclose(grads[0]["bias"][...], grads[1]["bias"][...], rtol=1e-4, atol=1e-6)
