"""Patch normalisation (openSeqSLAM's preprocessing), a stage between loading and the split.

Each image is cut into non-overlapping ``size`` x ``size`` patches and every patch is
z-scored on its own: (x - patch mean) / patch standard deviation. A global brightness or
contrast change (x -> a x + b, a > 0) leaves every z-score as it was, and so does any change
that is affine within each patch; what remains is local structure. A flat patch (standard
deviation at most 1e-6: sky, a black tunnel) becomes 0.

The suite's images live in [0, 1] and the auto-encoders reconstruct them through a sigmoid,
so the z-scores are mapped back there by one fixed map, the same for every image:
clip(0.5 + z / 6, 0, 1), i.e. +-3 standard deviations span the grey range and rarer values
are clipped. This keeps a pixel spread like a photograph's (std about 0.17); mapping the
largest possible z-score of a patch (sqrt(n - 1), 7.9 for 8x8) to the ends instead leaves a
spread of 0.06, on which the default FAE learns the constant image and every unit dies.
For raw, PCA and ICA, which centre and L2-normalise, the map is nearly a rescaling.
``rounded=True`` is openSeqSLAM's integer variant: it stores the grey level 127 + round(z),
so z is rounded to a whole number before the same map.

Computed in float64 with numpy, blockwise (the full route fits), so a brightness change of a
season changes the float32 result by at most a rounding step.
"""

from __future__ import annotations

import numpy as np

from vpr_jax import host_arrays
from vpr_jax.data.benchmark import Benchmark
from vpr_jax.data.route import Route
from vpr_jax.progress import Log

_FLAT = 1e-6
Z_SPAN = 3.0  # z-scores from -Z_SPAN to Z_SPAN fill [0, 1]
_BLOCK = 4096  # images per pass


def patch_zscores(images: np.ndarray, size: int) -> np.ndarray:
    """(N, H, W) -> (N, H, W) float64: every size x size patch z-scored (flat patches: 0)."""
    images = np.asarray(images, np.float64)
    n, h, w = images.shape
    if h % size or w % size:
        raise ValueError(f"patch size {size} does not tile {h}x{w} images")
    patches = images.reshape(n, h // size, size, w // size, size)
    mean = patches.mean(axis=(2, 4), keepdims=True)
    std = patches.std(axis=(2, 4), keepdims=True)
    z = np.where(std > _FLAT, (patches - mean) / np.maximum(std, _FLAT), 0.0)
    return z.reshape(n, h, w)


def patch_normalize(images: np.ndarray, size: int = 8, rounded: bool = False) -> np.ndarray:
    """Patch-normalised images as float32 in [0, 1] (see the module docstring)."""
    out = host_arrays.empty(np.shape(images))  # JAX reads it in place
    for i in range(0, len(out), _BLOCK):
        z = patch_zscores(images[i : i + _BLOCK], size)
        if rounded:
            z = np.round(z)
        out[i : i + _BLOCK] = np.clip(0.5 + z / (2.0 * Z_SPAN), 0.0, 1.0)
    return out


def patch_normalize_jax(images, size: int = 8, rounded: bool = False):
    """``patch_normalize`` in JAX, float32, jittable: what a saved encoder applies to the
    images it is given when the sweep used patch normalisation. Agrees with the float64
    numpy version to about 1e-6 (``rounded``: except where float32 rounding moves a z-score
    across a half-integer, a pixel in tens of thousands)."""
    import jax.numpy as jnp  # here: loading data and validating must not start JAX

    n, h, w = images.shape
    patches = jnp.reshape(images, (n, h // size, size, w // size, size))
    mean = jnp.mean(patches, axis=(2, 4), keepdims=True)
    std = jnp.sqrt(jnp.mean((patches - mean) ** 2, axis=(2, 4), keepdims=True))
    z = jnp.where(std > _FLAT, (patches - mean) / jnp.maximum(std, _FLAT), 0.0)
    if rounded:
        z = jnp.round(z)
    return jnp.reshape(jnp.clip(0.5 + z / (2.0 * Z_SPAN), 0.0, 1.0), (n, h, w))


def describe_preprocessing(preprocess: str, size: int, rounded: bool) -> dict:
    """What happens to an image between the file and an encoder, as a saved encoder's
    description records it."""
    return {
        "image": "grey, resized to 64x32 (OpenCV area interpolation), float32 in [0, 1] (/255)",
        "image_shape": [32, 64],
        "patchnorm": {"size": size, "rounded": rounded} if preprocess == "patchnorm" else None,
    }


def preprocess_route(
    route: Route, preprocess: str, size: int, rounded: bool, log: Log = print
) -> Route:
    """The route every method sees: as loaded (``none``) or patch-normalised."""
    if not _announce(preprocess, size, rounded, log):
        return route
    images = {s: patch_normalize(im, size, rounded) for s, im in route.images.items()}
    return Route(route.frame_ids, images, route.files)  # not _replace: Route has its own len


def preprocess_benchmark(
    bench: Benchmark, preprocess: str, size: int, rounded: bool, log: Log = print
) -> Benchmark:
    """A benchmark's database and queries, preprocessed as ``preprocess_route`` does."""
    if not _announce(preprocess, size, rounded, log):
        return bench
    return bench._replace(
        db=patch_normalize(bench.db, size, rounded),
        query=patch_normalize(bench.query, size, rounded),
    )


def _announce(preprocess: str, size: int, rounded: bool, log: Log) -> bool:
    """Whether images change (``patchnorm``), logged; ``none`` leaves them as loaded."""
    if preprocess == "none":
        return False
    if preprocess != "patchnorm":
        raise ValueError(f"unknown preprocess {preprocess!r}")
    variant = "rounded to grey levels like openSeqSLAM" if rounded else "float z-scores"
    log(f"preprocess: patch normalisation, {size}x{size} patches, {variant}")
    return True
