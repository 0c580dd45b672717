"""FAE and CAE behind the functional boundary: shapes, sizes and JAX transformations."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from vpr_jax.encoders import autoencoders as ae

SMALL_CAE = ae.CAESpec(channels=(4, 8), kernel_sizes=(3, 3), code_channels=2)


def _images(n=6, seed=0):
    return jnp.asarray(np.random.default_rng(seed).random((n, 32, 64), dtype=np.float32))


@pytest.mark.parametrize(
    "spec, code",
    [
        (ae.FAESpec(hidden=32), 32),
        (SMALL_CAE, 8 * 16 * 2),
        (ae.CAESpec(channels=(4,), kernel_sizes=(3,), code_channels=3), 16 * 32 * 3),
    ],
)
def test_shapes_of_codes_and_reconstructions(spec, code):
    graphdef, params = ae.build(spec, jax.random.key(0))
    x = _images()
    assert ae.make_encode(graphdef)(params, x).shape == (6, code)
    recon = ae.make_reconstruct(graphdef)(params, x)
    assert recon.shape == x.shape and float(recon.min()) >= 0 and float(recon.max()) <= 1
    # The CAE takes (n, 32, 64, 1) as well and gives the same code.
    if isinstance(spec, ae.CAESpec):
        np.testing.assert_allclose(
            ae.make_encode(graphdef)(params, x[..., None]), ae.make_encode(graphdef)(params, x)
        )
    # params is a plain nested dict of arrays: what orbax and optax take as it is.
    assert all(isinstance(leaf, jax.Array) for leaf in jax.tree.leaves(params))


def test_default_sizes_follow_the_seed_and_calc():
    _, fae = ae.build(ae.FAESpec(), jax.random.key(0))
    assert fae["encoder"]["kernel"].shape == (2048, 256)
    _, cae = ae.build(ae.CAESpec(), jax.random.key(0))
    encoder = sum(int(x.size) for k in ("down", "to_code") for x in jax.tree.leaves(cae[k]))
    assert 120_000 < encoder < 160_000  # CALC's encoder: about 137k parameters
    graphdef, params = ae.build(ae.CAESpec(), jax.random.key(0))
    assert ae.make_encode(graphdef)(params, _images(1)).shape == (1, 1024)  # about 1k values


@pytest.mark.parametrize("centre", [0.5, 0.0])  # ours; the paper's plain layer
def test_fae_code_is_relu_of_the_first_layer_on_centred_pixels(centre):
    graphdef, params = ae.build(ae.FAESpec(hidden=16, centre=centre), jax.random.key(1))
    x = _images(3)
    w, b = np.asarray(params["encoder"]["kernel"]), np.asarray(params["encoder"]["bias"])
    expected = np.maximum((np.asarray(x).reshape(3, -1) - centre) @ w + b, 0.0)
    np.testing.assert_allclose(ae.make_encode(graphdef)(params, x), expected, rtol=1e-5, atol=1e-6)


def test_build_refuses_images_the_levels_cannot_halve():
    with pytest.raises(ValueError, match="divisible by 8"):
        ae.build(
            ae.CAESpec(channels=(4, 4, 4), kernel_sizes=(3, 3, 3), code_channels=2),
            jax.random.key(0),
            image_shape=(36, 64),
        )


@pytest.mark.parametrize("spec", [ae.FAESpec(hidden=16), SMALL_CAE])
def test_encode_under_jit_eager_vmap_grad_and_inside_other_jitted_code(spec):
    graphdef, params = ae.build(spec, jax.random.key(2))
    encode = ae.make_encode(graphdef)
    x = _images(8)
    codes = encode(params, x)
    with jax.disable_jit():
        eager = encode(params, x)
    np.testing.assert_allclose(eager, codes, atol=1e-5)

    batched = jax.vmap(encode, in_axes=(None, 0))(params, x.reshape(2, 4, 32, 64))
    np.testing.assert_allclose(batched.reshape(codes.shape), codes, atol=1e-5)

    @jax.jit
    def similarity(p, a, b):  # a user's own jitted function around encode
        ea, eb = encode(p, a), encode(p, b)
        return jnp.sum(ea * eb, axis=1) / (
            jnp.linalg.norm(ea, axis=1) * jnp.linalg.norm(eb, axis=1) + 1e-9
        )

    assert similarity(params, x, x).shape == (8,)

    # Gradients flow to the parameters and to the images; reverse mode agrees with forward
    # mode along a random direction (finite differences would cross ReLU and max-pool kinks).
    def energy(p, images):
        return jnp.sum(encode(p, images) ** 2)

    g_params, g_images = jax.grad(energy, argnums=(0, 1))(params, x)
    assert jax.tree.structure(g_params) == jax.tree.structure(params)
    assert float(sum(jnp.sum(jnp.abs(g)) for g in jax.tree.leaves(g_params))) > 0
    direction = jnp.asarray(np.random.default_rng(3).normal(size=x.shape), jnp.float32)
    _, forward = jax.jvp(lambda images: energy(params, images), (x,), (direction,))
    assert float(forward) == pytest.approx(float(jnp.sum(g_images * direction)), rel=1e-3)


def test_same_key_same_weights_different_key_different_weights():
    _, a = ae.build(SMALL_CAE, jax.random.key(0))
    _, b = ae.build(SMALL_CAE, jax.random.key(0))
    _, c = ae.build(SMALL_CAE, jax.random.key(1))
    leaves = list(zip(jax.tree.leaves(a), jax.tree.leaves(b), jax.tree.leaves(c), strict=True))
    assert all(np.array_equal(x, y) for x, y, _ in leaves)
    assert any(not np.array_equal(x, z) for x, _, z in leaves)


def test_max_pool_2x2_equals_flax_max_pool_and_its_gradient_picks_the_maximum():
    from flax import nnx

    x = jnp.asarray(np.random.default_rng(0).normal(size=(3, 8, 12, 5)).astype(np.float32))
    np.testing.assert_array_equal(ae.max_pool_2x2(x), nnx.max_pool(x, (2, 2), strides=(2, 2)))
    grad = jax.grad(lambda x: ae.max_pool_2x2(x).sum())(x)
    want = jax.grad(lambda x: nnx.max_pool(x, (2, 2), strides=(2, 2)).sum())(x)
    np.testing.assert_array_equal(grad, want)  # continuous data: no ties


def test_augment_auto_is_the_axis_of_both_values_and_training_settings_default_to_train():
    """``train.augment=auto`` is shorthand for the axis ``augment=[true,false]`` of every
    trained method (a fit per value, the runner's rule chooses); a training setting the
    method is not given takes ``train.*``'s value, one it is given wins."""
    from experiments.resolve import resolve
    from vpr_jax.command_line import parse_config
    from vpr_jax.method_table import METHODS

    cfg = parse_config(["train.augment=auto", "train.learning_rate=0.01", "cae.learning_rate=0.1"])
    fae = resolve(METHODS["fae"], cfg)
    assert [c.values["augment"] for c in fae.combinations] == [True, False]
    assert [c.label for c in fae.combinations] == ["augment=True", "augment=False"]
    assert {c.values["learning_rate"] for c in fae.combinations} == {0.01}
    cae = resolve(METHODS["cae"], cfg)
    assert {c.values["learning_rate"] for c in cae.combinations} == {0.1}
    assert resolve(METHODS["fae"], parse_config([])).combinations[0].values["augment"] is True
