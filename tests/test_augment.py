"""Auto-encoder augmentation (Table 2): flips and shifts checked against numpy references."""

import functools

import jax
import numpy as np
import pytest

from vpr_jax.data.augment import (
    PLACE,
    AugmentConfig,
    augment_batch,
    augment_one,
    flip_image,
    max_shift,
    shift_image,
)

H, W = 32, 64
OFF = AugmentConfig(horizontal_flip=False, width_shift=0.0, height_shift=0.0)
FLIP_ONLY = AugmentConfig(horizontal_flip=True, width_shift=0.0, height_shift=0.0)
SHIFT_ONLY = AugmentConfig(horizontal_flip=False, width_shift=0.2, height_shift=0.2)
jit_augment = jax.jit(augment_batch, static_argnames="cfg")


def gradient(h=H, w=W):
    """A gradient in both directions with every pixel distinct: no flip or shift is a no-op,
    and different shifts (within half the image) give different images."""
    y, x = np.mgrid[:h, :w]
    return ((y * w + x) / (h * w - 1)).astype(np.float32)


def np_shift(image, dy, dx):
    """Reference: content moves dy down, dx right; uncovered pixels repeat the edge."""
    h, w = image.shape[:2]
    p, q = abs(dy), abs(dx)
    pad = [(p, p), (q, q)] + [(0, 0)] * (image.ndim - 2)
    padded = np.pad(image, pad, mode="edge")
    return padded[p - dy : p - dy + h, q - dx : q - dx + w]


@functools.cache
def _candidates(h, w, flips, dys, dxs):
    image = gradient(h, w)
    table = {}
    for flip in flips:
        for dy in dys:
            for dx in dxs:
                cand = np_shift(image, dy, dx)
                table[(cand[:, ::-1] if flip else cand).tobytes()] = (flip, dy, dx)
    assert len(table) == len(flips) * len(dys) * len(dxs), "candidates must be distinct"
    return table


def identify(
    out,
    h=H,
    w=W,
    flips=(False, True),
    dys=range(-H // 2, H // 2 + 1),
    dxs=range(-W // 2, W // 2 + 1),
):
    """The (flip, dy, dx) that turn ``gradient(h, w)`` into ``out`` (searching wider than
    allowed, so an out-of-range shift is found and reported rather than missed), or None."""
    table = _candidates(h, w, tuple(flips), tuple(dys), tuple(dxs))
    return table.get(np.ascontiguousarray(out, dtype=np.float32).tobytes())


@pytest.fixture(scope="module")
def batch():
    rng = np.random.default_rng(0)
    return rng.random((8, H, W), dtype=np.float32)


@pytest.mark.parametrize("channel", [False, True])
def test_shape_and_dtype_kept(batch, channel):
    images = batch[..., None] if channel else batch
    out = jit_augment(jax.random.PRNGKey(0), images, AugmentConfig())
    assert out.shape == images.shape and out.dtype == np.float32


def test_channel_axis_changes_nothing_but_shape(batch):
    key = jax.random.PRNGKey(3)
    flat = jit_augment(key, batch, AugmentConfig())
    chan = jit_augment(key, batch[..., None], AugmentConfig())
    np.testing.assert_array_equal(np.asarray(chan)[..., 0], np.asarray(flat))
    assert not np.array_equal(np.asarray(flat), batch)


@pytest.mark.parametrize(
    "dy,dx", [(0, 0), (3, 0), (0, -5), (-4, 7), (6, -12), (-6, 12), (1, 1), (-31, 40), (35, -70)]
)
def test_shift_image_matches_numpy(dy, dx):
    image = gradient()
    np.testing.assert_array_equal(np.asarray(shift_image(image, dy, dx)), np_shift(image, dy, dx))
    chan = image[..., None]
    np.testing.assert_array_equal(np.asarray(shift_image(chan, dy, dx)), np_shift(chan, dy, dx))


def test_shift_image_traced_shifts_under_jit():
    image = gradient()
    out = jax.jit(shift_image)(image, np.int32(-3), np.int32(9))
    np.testing.assert_array_equal(np.asarray(out), np_shift(image, -3, 9))


def test_flip_image_is_left_right_mirror():
    image = gradient()
    np.testing.assert_array_equal(np.asarray(flip_image(image)), image[:, ::-1])
    chan = image[..., None]
    np.testing.assert_array_equal(np.asarray(flip_image(chan)), chan[:, ::-1])


def test_flip_only_mirrors_about_half_never_up_down():
    image = gradient()
    n = 200
    out = np.asarray(jit_augment(jax.random.PRNGKey(1), np.stack([image] * n), FLIP_ONLY))
    same = np.all(out == image, axis=(1, 2))
    mirrored = np.all(out == image[:, ::-1], axis=(1, 2))
    upside_down = np.all(out == image[::-1], axis=(1, 2))
    assert np.all(same ^ mirrored), "every output is the input or its left-right mirror"
    assert not upside_down.any()
    assert 0.3 <= mirrored.mean() <= 0.7, mirrored.mean()


def test_shift_only_within_range_both_signs_and_wide():
    image = gradient()
    n = 200
    out = np.asarray(jit_augment(jax.random.PRNGKey(2), np.stack([image] * n), SHIFT_ONLY))
    found = [identify(o, flips=(False,)) for o in out]
    assert all(f is not None for f in found), "every output is a nearest-edge shift"
    dys = np.array([f[1] for f in found])
    dxs = np.array([f[2] for f in found])
    max_dy, max_dx = 0.2 * H, 0.2 * W
    assert np.abs(dys).max() <= max_dy and np.abs(dxs).max() <= max_dx
    assert dys.min() <= -0.6 * max_dy and dys.max() >= 0.6 * max_dy, (dys.min(), dys.max())
    assert dxs.min() <= -0.6 * max_dx and dxs.max() >= 0.6 * max_dx, (dxs.min(), dxs.max())
    # Uniform, not piled at the limits (as clipping a too-wide draw would do): the extreme
    # whole-pixel shifts are ~14% of dy (6 of 6.4) and ~6% of dx (12 of 12.8).
    assert np.mean(np.abs(dys) == max_shift(0.2, H)) < 0.3
    assert np.mean(np.abs(dxs) == max_shift(0.2, W)) < 0.3
    # The two axes are drawn independently.
    assert abs(np.corrcoef(dys, dxs)[0, 1]) < 0.3


def test_default_config_is_shift_then_optional_mirror():
    image = gradient()
    n = 40
    out = np.asarray(jit_augment(jax.random.PRNGKey(4), np.stack([image] * n), AugmentConfig()))
    found = [identify(o) for o in out]
    assert all(f is not None for f in found)
    assert all(abs(dy) <= 0.2 * H and abs(dx) <= 0.2 * W for _, dy, dx in found)
    assert {flip for flip, _, _ in found} == {False, True}


def test_the_place_keeping_augmentation_never_flips_and_shifts_a_few_pixels():
    """train.augment=place: every output is an unflipped nearest-edge shift of at most
    3 pixels across and 1 down (0.05 of 64 and of 32), and both bounds are reached."""
    from vpr_jax.encoders.train_programs import augment_config

    assert augment_config("place") is PLACE and augment_config(True) == AugmentConfig()
    assert augment_config(False) is None
    image = gradient()
    out = np.asarray(jit_augment(jax.random.PRNGKey(6), np.stack([image] * 200), PLACE))
    found = [identify(o) for o in out]
    assert all(f is not None and not f[0] for f in found), "an unflipped shift each"
    dys, dxs = (np.array([f[i] for f in found]) for i in (1, 2))
    assert np.abs(dys).max() == 1 and np.abs(dxs).max() == 3


@pytest.mark.parametrize("channel", [False, True])
def test_disabled_config_is_identity(batch, channel):
    images = batch[..., None] if channel else batch
    out = jit_augment(jax.random.PRNGKey(5), images, OFF)
    np.testing.assert_array_equal(np.asarray(out), images)


def test_jit_equals_eager(batch):
    key, images = jax.random.PRNGKey(6), batch[:3]  # eager is op by op: keep it small
    jitted = np.asarray(jit_augment(key, images, AugmentConfig()))
    with jax.disable_jit():
        eager = np.asarray(augment_batch(key, images, AugmentConfig()))
    np.testing.assert_array_equal(jitted, eager)
    assert not np.array_equal(jitted, images)


def test_same_key_same_output_different_key_different(batch):
    a = np.asarray(jit_augment(jax.random.PRNGKey(7), batch, AugmentConfig()))
    b = np.asarray(jit_augment(jax.random.PRNGKey(7), batch, AugmentConfig()))
    c = np.asarray(jit_augment(jax.random.PRNGKey(8), batch, AugmentConfig()))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_images_of_a_batch_get_different_draws():
    image = gradient()
    out = np.asarray(jit_augment(jax.random.PRNGKey(9), np.stack([image] * 16), AugmentConfig()))
    assert len({o.tobytes() for o in out}) > 8


def test_values_stay_within_input_range(batch):
    images = batch * 0.5 + 0.25  # [0.25, 0.75]: a fill of 0 or 1 would leave the range
    out = np.asarray(jit_augment(jax.random.PRNGKey(10), images, AugmentConfig()))
    assert out.min() >= images.min() and out.max() <= images.max()


def test_augment_one_single_image_and_other_sizes():
    image = gradient(7, 11)
    out = np.asarray(
        jax.jit(functools.partial(augment_one, cfg=AugmentConfig()))(jax.random.PRNGKey(11), image)
    )
    found = identify(out, 7, 11, dys=range(-3, 4), dxs=range(-5, 6))
    assert found is not None
    _, dy, dx = found
    assert abs(dy) <= max_shift(0.2, 7) == 1 and abs(dx) <= max_shift(0.2, 11) == 2


def test_max_shift_floors_and_rejects_bad_fractions():
    assert max_shift(0.2, 64) == 12 and max_shift(0.2, 32) == 6 and max_shift(0.29, 100) == 29
    assert max_shift(0.0, 64) == 0
    with pytest.raises(ValueError):
        max_shift(-0.1, 64)


def test_a_change_of_conditions_stays_in_range_follows_its_key_and_keeps_the_place():
    """Two views of an image (augment_contrastive's positive pair): within [0, 1], each the
    change of its own key (the batched views as one image's), other for another key, and
    nearer their own image than another image is (the place kept: small shifts, no flip)."""
    from vpr_jax.data.augment import condition_change, condition_views

    rng = np.random.default_rng(3)
    # smooth random images, each its own: a random walk down and across
    smooth = np.cumsum(np.cumsum(rng.standard_normal((4, 32, 64)), axis=1), axis=2)
    low, high = smooth.min(axis=(1, 2), keepdims=True), smooth.max(axis=(1, 2), keepdims=True)
    images = ((smooth - low) / (high - low)).astype(np.float32)
    key = jax.random.key(5)
    views = np.asarray(condition_views(key, images))
    assert views.shape == (4, 2, 32, 64) and views.min() >= 0.0 and views.max() <= 1.0
    one = jax.jit(condition_change)
    first = jax.random.split(key, (4, 2))[0, 0]  # the key of image 0's first view
    np.testing.assert_allclose(np.asarray(one(first, images[0])), views[0, 0], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(condition_views(key, images)), views)
    assert not np.allclose(views[:, 0], views[:, 1])  # two draws per image
    for i in range(4):
        own = np.corrcoef(views[i, 0].ravel(), images[i].ravel())[0, 1]
        other = np.corrcoef(views[i, 0].ravel(), images[(i + 1) % 4].ravel())[0, 1]
        assert own > other
