"""Patch normalisation: patch statistics, invariance to brightness, and the [0, 1] map."""

import numpy as np
import pytest

from vpr_jax.data.preprocess import Z_SPAN, patch_normalize, patch_zscores


def images(n=5, seed=0):
    return np.random.default_rng(seed).uniform(0.1, 0.9, (n, 32, 64)).astype(np.float32)


@pytest.mark.parametrize("size", [4, 8, 16])
def test_every_patch_has_zero_mean_and_unit_variance(size):
    z = patch_zscores(images(), size)
    for top in range(0, 32, size):  # patch by patch, the way openSeqSLAM loops
        for left in range(0, 64, size):
            patch = z[:, top : top + size, left : left + size].reshape(len(z), -1)
            np.testing.assert_allclose(patch.mean(axis=1), 0, atol=1e-12)
            np.testing.assert_allclose(patch.std(axis=1), 1, atol=1e-12)


def test_flat_patches_become_zero_not_nan():
    x = images()
    x[0, :8, :8] = 0.0  # a black corner
    x[1] = 1.0  # an over-exposed frame
    z = patch_zscores(x, 8)
    assert np.isfinite(z).all()
    assert not z[0, :8, :8].any() and not z[1].any()
    assert np.all(patch_normalize(x, 8)[1] == 0.5)


def test_brightness_and_contrast_leave_patch_normalised_images_unchanged():
    x = images()
    for changed in (x + 0.08, 0.6 * x + 0.2, np.float32(1.3) * x - 0.1):
        np.testing.assert_allclose(patch_normalize(changed, 8), patch_normalize(x, 8), atol=2e-6)
        np.testing.assert_array_equal(
            patch_normalize(changed, 8, rounded=True), patch_normalize(x, 8, rounded=True)
        )


def test_the_map_into_the_grey_range():
    x = images()
    z = patch_zscores(x, 8)
    out = patch_normalize(x, 8)
    assert out.dtype == np.float32 and out.min() >= 0 and out.max() <= 1
    inside = np.abs(z) < Z_SPAN
    np.testing.assert_allclose(out[inside], 0.5 + z[inside] / (2 * Z_SPAN), atol=1e-6)
    assert np.all(out[z >= Z_SPAN] == 1) and np.all(out[z <= -Z_SPAN] == 0)
    rounded = patch_normalize(x, 8, rounded=True)
    levels = (rounded - 0.5) * 2 * Z_SPAN  # whole z-scores, as openSeqSLAM stores them
    np.testing.assert_allclose(levels, np.round(levels), atol=1e-5)
    np.testing.assert_allclose(levels, np.clip(np.round(z), -Z_SPAN, Z_SPAN), atol=1e-5)


def test_patches_that_do_not_tile_the_image_are_refused():
    with pytest.raises(ValueError, match="does not tile"):
        patch_zscores(images(), 5)
