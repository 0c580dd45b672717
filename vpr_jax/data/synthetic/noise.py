"""Shared low-level helpers of every layer: smooth value noise, tileable textures, wrapping
texture look-ups, and arithmetic-only stand-ins for transcendental functions.

Per-frame values go through elementwise IEEE arithmetic only (no transcendental functions,
whose SIMD and scalar paths may differ in the last bit), so the helpers here give the same
bits however the frames are batched.
"""

from __future__ import annotations

from collections.abc import Iterable

import cv2
import numpy as np


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
