"""Histograms of gradient orientations (HOG: Dalal and Triggs 2005), a pure jittable function
of a batch of grey images: the gradient-histogram input of every method
(``vpr_jax.methods.inputs``).

Each image's gradient is the central difference along rows and along columns (0 on the
image's border rows and columns); each pixel votes its gradient's magnitude into one of
``bins`` unsigned orientation bins over [0, 180) degrees (hard binning: bin i holds
[i, i + 1) x 180 / bins); a cell of ``cell`` x ``cell`` pixels holds the mean of its pixels'
votes per bin, cells tiling the image from its top left (pixels past the last whole cell are
dropped). Every ``block`` x ``block`` neighbourhood of cells, overlapping by all but one cell,
is normalised as a whole (``norm``: L1, L1-sqrt, L2 or L2-Hys, which clips at 0.2 and
normalises again; eps 1e-5) and the blocks are laid end to end: (block row, block column,
cell row, cell column, bin), the order and the arithmetic of scikit-image's
``skimage.feature.hog`` with ``transform_sqrt=False``, its oracle in the tests.

A 32 x 64 image in 4 x 4 cells, 3 x 3 blocks and 9 bins (the suite's defaults,
``gradients.*``) gives 6 x 14 blocks of 81 values: 6,804. No products: nothing here
depends on a device's matmul precision.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

NORMS = ("L1", "L1-sqrt", "L2", "L2-Hys")
EPS = 1e-5  # scikit-image's
HYS_CLIP = 0.2  # L2-Hys: block values clipped here before the second normalisation


# Compiled as one program: op by op, its some 60 operations each dispatched (and compiled
# once) took 0.2 s a call in a sweep.
@functools.partial(jax.jit, static_argnames=("cell", "bins", "block", "norm"))
def gradient_histograms(
    images: Float[Array, "n h w"],
    cell: int = 4,
    bins: int = 9,
    block: int = 3,
    norm: str = "L2",
) -> Float[Array, "n f"]:
    """(n, h, w) -> (n, f), f = blocks x block^2 x bins (see the module docstring)."""
    n, h, w = images.shape
    rows, cols = h // cell, w // cell
    if min(rows, cols) < block:
        raise ValueError(f"{h}x{w} images hold {rows}x{cols} cells of {cell}: fewer than a block")
    if norm not in NORMS:
        raise ValueError(f"block normalisation {norm!r} is not one of {', '.join(NORMS)}")
    g_row = jnp.zeros_like(images).at[:, 1:-1, :].set(images[:, 2:, :] - images[:, :-2, :])
    g_col = jnp.zeros_like(images).at[:, :, 1:-1].set(images[:, :, 2:] - images[:, :, :-2])
    magnitude = jnp.hypot(g_col, g_row)[:, : rows * cell, : cols * cell]
    which = orientation_bins(g_row, g_col, bins)[:, : rows * cell, : cols * cell]
    cells = jnp.stack(
        [
            jnp.where(which == i, magnitude, 0.0)
            .reshape(n, rows, cell, cols, cell)
            .sum(axis=(2, 4))
            for i in range(bins)
        ],
        axis=-1,
    ) / (cell * cell)
    across, down = cols - block + 1, rows - block + 1
    blocks = jnp.stack(
        [
            jnp.stack([cells[:, r : r + down, c : c + across] for c in range(block)], axis=3)
            for r in range(block)
        ],
        axis=3,
    )  # (n, down, across, block row, block column, bins)
    return normalise_blocks(blocks, norm).reshape(n, -1)


def orientation_bins(g_row: Float[Array, "..."], g_col: Float[Array, "..."], bins: int):
    """Each gradient's unsigned orientation bin, 0 .. bins - 1: bin i holds the angles
    atan2(g_row, g_col) mod 180 in [i, i + 1) x 180 / bins.

    Without atan2, whose last bit differs between float32 and float64 and between devices:
    the gradient is turned into the upper half-plane (g_row >= 0; a gradient along -columns
    is at 0 degrees), where its angle is at least an edge t exactly when
    sin(t) g_col <= cos(t) g_row. Two products compared, never subtracted, with sin and cos
    of an edge at a multiple of 45 degrees made exact (0, or equal in size), so a gradient on
    an edge (an 8-bit image has many at 0, 45, 90 and 135 degrees) falls in the bin above
    it, as in float64 arithmetic, on any device and at any precision."""
    turn = (g_row < 0) | ((g_row == 0) & (g_col < 0))
    g_row, g_col = jnp.where(turn, -g_row, g_row), jnp.where(turn, -g_col, g_col)
    which = jnp.zeros(g_row.shape, jnp.int32)
    for i in range(1, bins):
        sin, cos = _edge(np.pi * i / bins)
        which += (sin * g_col <= cos * g_row).astype(jnp.int32)
    return jnp.where((g_row == 0) & (g_col == 0), 0, which)  # no gradient: 0 degrees


def _edge(angle: float) -> tuple[float, float]:
    """sin and cos of a bin edge, exact where they are 0 or equal in size."""
    sin, cos = float(np.sin(angle)), float(np.cos(angle))
    sin, cos = (0.0 if abs(v) < 1e-12 else v for v in (sin, cos))
    if abs(abs(sin) - abs(cos)) < 1e-12:
        sin, cos = np.copysign(np.sqrt(0.5), sin), np.copysign(np.sqrt(0.5), cos)
    return sin, cos


def normalise_blocks(blocks: Float[Array, "n a b r c k"], norm: str) -> Float[Array, "n a b r c k"]:
    """Each block (the last three axes) normalised as scikit-image does."""
    axes = (-3, -2, -1)
    if norm in ("L1", "L1-sqrt"):
        out = blocks / (jnp.sum(jnp.abs(blocks), axis=axes, keepdims=True) + EPS)
        return jnp.sqrt(out) if norm == "L1-sqrt" else out
    out = blocks / _l2(blocks, axes)
    if norm == "L2-Hys":
        out = jnp.minimum(out, HYS_CLIP)
        out = out / _l2(out, axes)
    return out


def _l2(x, axes):
    return jnp.sqrt(jnp.sum(x**2, axis=axes, keepdims=True) + EPS**2)


def n_features(h: int, w: int, cell: int = 4, bins: int = 9, block: int = 3) -> int:
    """The length of an (h, w) image's histograms."""
    return (h // cell - block + 1) * (w // cell - block + 1) * block * block * bins
