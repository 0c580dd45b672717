"""Histograms of gradient orientations (``vpr_jax.encoders.gradients``) against
scikit-image's ``skimage.feature.hog`` on the same cells, bins and block normalisation.

The images hold grey levels k / 256: their gradients are exact in float32 and float64, so a
gradient that lies on a bin edge (a smooth ramp has many at 0, 45, 90 and 135 degrees) lies
exactly on it for both, and the comparison is to float rounding (scikit-image sums a cell
in float32)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from vpr_jax.encoders.gradients import gradient_histograms, n_features, orientation_bins

skimage_feature = pytest.importorskip("skimage.feature")

CASES = [  # cell, bins, block, norm
    (4, 9, 3, "L2"),  # the suite's default (gradients.*)
    (4, 9, 2, "L2-Hys"),
    (8, 9, 3, "L2-Hys"),  # scikit-image's default
    (4, 8, 2, "L1"),  # edges at 45 and 90 degrees
    (5, 7, 2, "L1-sqrt"),  # cells that do not tile 32 x 64: the remainder dropped
    (4, 12, 1, "L2"),
    (4, 4, 2, "L2"),
]


@pytest.fixture(scope="module")
def images():
    rng = np.random.default_rng(0)
    out = rng.integers(0, 256, (4, 32, 64)).astype(np.float64) / 256
    out[0, 10:20, 10:30] = 0.5  # flat: no gradient at all
    ramp = np.linspace(0, 1, 64)[None, :] * np.linspace(0, 1, 32)[:, None]
    out[1] = np.round(ramp * 255) / 256  # smooth: many equal gradients, on bin edges
    out[2, :, ::2] = 0  # stripes: gradients along the columns only
    return out


@pytest.mark.parametrize(("cell", "bins", "block", "norm"), CASES)
def test_gradient_histograms_are_scikit_images_hog(images, cell, bins, block, norm):
    expected = np.stack(
        [
            skimage_feature.hog(
                image,
                orientations=bins,
                pixels_per_cell=(cell, cell),
                cells_per_block=(block, block),
                block_norm=norm,
                transform_sqrt=False,
                feature_vector=True,
            )
            for image in images
        ]
    )
    assert expected.shape == (len(images), n_features(32, 64, cell, bins, block))
    hog = jax.jit(gradient_histograms, static_argnums=(1, 2, 3, 4))
    ours = np.asarray(hog(jnp.asarray(images, jnp.float32), cell, bins, block, norm))
    np.testing.assert_allclose(ours, expected, rtol=0, atol=1e-6)
    with jax.enable_x64(True):
        ours64 = np.asarray(gradient_histograms(jnp.asarray(images), cell, bins, block, norm))
    np.testing.assert_allclose(ours64, expected, rtol=0, atol=1e-6)


def test_orientation_bins_are_atan2s_on_and_off_the_edges():
    """Every gradient of small integers (many on an edge) gets the bin numpy's float64
    atan2 puts it in, for edges at multiples of 15, 20 and 45 degrees."""
    g = np.arange(-6, 7, dtype=np.float64)
    g_row, g_col = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    degrees = np.rad2deg(np.arctan2(g_row, g_col)) % 180
    for bins in (4, 9, 12):
        expected = np.minimum((degrees // (180 / bins)).astype(int), bins - 1)
        ours = orientation_bins(
            jnp.asarray(g_row, jnp.float32), jnp.asarray(g_col, jnp.float32), bins
        )
        np.testing.assert_array_equal(np.asarray(ours), expected)


def test_gradient_histograms_differentiate_and_vmap(images):
    x = jnp.asarray(images[:2], jnp.float32)
    batched = jax.vmap(lambda one: gradient_histograms(one[None])[0])(x)
    np.testing.assert_allclose(np.asarray(batched), np.asarray(gradient_histograms(x)), atol=1e-7)
    grad = jax.grad(lambda y: jnp.sum(gradient_histograms(y) ** 2))(x)
    assert grad.shape == x.shape and bool(jnp.all(jnp.isfinite(grad)))


def test_too_small_an_image_or_an_unknown_norm_is_refused():
    with pytest.raises(ValueError, match="fewer than a block"):
        gradient_histograms(jnp.zeros((1, 8, 8)), cell=8, block=2)
    with pytest.raises(ValueError, match="L2-Hys"):
        gradient_histograms(jnp.zeros((1, 32, 64)), norm="L3")
