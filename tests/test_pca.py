"""PCA change removal against scikit-learn, under jit, vmap and both output forms."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from sklearn.decomposition import PCA

from tests.conftest import suffix_cosine
from vpr_jax.encoders import pca
from vpr_jax.evaluation.matching import cosine_similarity


def _data(n, d, seed=0):
    rng = np.random.default_rng(seed)
    # Decaying spectrum so components are well separated (eigenvectors are then unique).
    return (rng.normal(size=(n, d)) * np.linspace(3.0, 0.2, d)).astype(np.float32) + 0.5


@pytest.mark.parametrize(
    "n,d,solver", [(400, 40, "covariance"), (30, 60, "gram"), (400, 40, "auto"), (30, 60, "auto")]
)
def test_fit_matches_sklearn(n, d, solver):
    x = _data(n, d)
    state = pca.fit_pca(x, solver=solver)
    sk = PCA(svd_solver="full").fit(x.astype(np.float64))
    c = min(n - 1, d)
    assert state.components.shape == (c, d)
    np.testing.assert_allclose(state.mean, sk.mean_, atol=1e-5)
    np.testing.assert_allclose(
        state.explained_variance, sk.explained_variance_[:c], rtol=2e-3, atol=1e-4
    )
    # Same signs too: both use svd_flip's convention (largest |entry| of a row positive).
    np.testing.assert_allclose(state.components, sk.components_[:c], atol=2e-3)
    np.testing.assert_allclose(pca.project(state, x[:7]), sk.transform(x[:7])[:, :c], atol=2e-3)


def test_solvers_agree_and_components_orthonormal():
    x = _data(50, 40, seed=1)
    a = pca.fit_pca(x, solver="covariance")
    b = pca.fit_pca(x, solver="gram")
    np.testing.assert_allclose(a.components, b.components, atol=2e-3)
    gram = np.asarray(a.components @ a.components.T)
    np.testing.assert_allclose(gram, np.eye(len(gram)), atol=1e-4)
    assert np.all(np.diff(np.asarray(a.explained_variance)) <= 1e-6)  # descending


def test_images_are_flattened_and_test_data_uses_training_mean():
    x = _data(60, 32 * 4).reshape(60, 4, 32)
    state = pca.fit_pca(x)
    shifted = x[:5] + 10.0  # a test image far from the training mean
    expected = (shifted.reshape(5, -1) - x.reshape(60, -1).mean(0)) @ np.asarray(state.components).T
    np.testing.assert_allclose(pca.project(state, shifted), expected, rtol=1e-4, atol=1e-3)


def test_encode_jit_equals_eager_and_vmap_over_removed_counts():
    x = _data(120, 30)
    state = pca.fit_pca(x)
    ks = jnp.array([0, 3, 10])
    with jax.disable_jit():
        eager = [np.asarray(pca.encode(state, x[:9], int(k))) for k in ks]
    batched = jax.vmap(lambda k: pca.encode(state, x[:9], k))(ks)
    for k, e, b in zip(ks, eager, batched, strict=True):
        np.testing.assert_allclose(b, e, atol=1e-5)
        assert np.all(np.asarray(b)[:, :k] == 0)
        np.testing.assert_allclose(b[:, k:], pca.project(state, x[:9])[:, k:], atol=1e-5)


def test_pixels_and_coefficients_give_same_cosine():
    x = _data(80, 50)
    state = pca.fit_pca(x)
    q, d = x[:10] + 0.1, x[10:30]
    for k in (0, 4, 20):
        coeff = cosine_similarity(pca.encode(state, q, k), pca.encode(state, d, k))
        pixel = cosine_similarity(
            pca.encode(state, q, k, "pixels"), pca.encode(state, d, k, "pixels")
        )
        np.testing.assert_allclose(coeff, pixel, atol=1e-4)


def test_one_pass_over_removed_counts_equals_encoding_each():
    x = _data(200, 40)
    state = pca.fit_pca(x)
    q, d = pca.project(state, x[:15] * 0.9), pca.project(state, x[15:60])
    ks = (0, 2, 7, 30)
    one_pass = suffix_cosine(q, d, ks)
    for i, k in enumerate(ks):
        each = cosine_similarity(pca.encode(state, x[:15] * 0.9, k), pca.encode(state, x[15:60], k))
        np.testing.assert_allclose(one_pass[i], each, atol=2e-5)


def test_bad_arguments():
    x = _data(10, 5)
    with pytest.raises(ValueError, match="n_components"):
        pca.fit_pca(x, n_components=6)
    with pytest.raises(ValueError, match="at least 2"):
        pca.fit_pca(x[:1])
    with pytest.raises(ValueError, match="solver"):
        pca.fit_pca(x, solver="svd")


def _principal_sines(a, b):
    """Sines of the principal angles between the row spaces of a and b (orthonormal rows)."""
    cosines = np.linalg.svd(
        np.asarray(a, np.float64) @ np.asarray(b, np.float64).T, compute_uv=False
    )
    return np.sqrt(np.clip(1 - cosines**2, 0, None))


def _assert_leading_50_agree(fast, full):
    """The subspace fit's leading 50 components span the full fit's (principal-angle sines
    below 1e-2) with their variances, and all its components are orthonormal."""
    assert _principal_sines(fast.components[:50], full.components[:50]).max() < 1e-2
    np.testing.assert_allclose(
        fast.explained_variance[:50], full.explained_variance[:50], rtol=1e-3
    )
    gram = np.asarray(fast.components @ fast.components.T)
    np.testing.assert_allclose(gram, np.eye(len(gram)), atol=1e-4)


def test_subspace_solver_finds_the_leading_components_of_route_images():
    from vpr_jax.data.synthetic import synthetic_route

    route = synthetic_route(1500, ("summer", "winter"), seed=3)
    x = np.concatenate([route.images["summer"], route.images["winter"]]).reshape(3000, -1)
    full = pca.fit_pca(x, solver="covariance")
    assert pca.choose_solver(*x.shape, "auto", 100) == "subspace"
    fast = pca.fit_pca(x, 100)  # auto: the subspace solver for 100 of 2,048
    assert fast.components.shape == (100, x.shape[1])
    _assert_leading_50_agree(fast, full)


def test_subspace_solver_survives_a_steep_spectrum():
    """Real Nordland frames' spectrum falls by more than 1e4 over 400 components; plain
    Cholesky QR in the power iterations then squared the block's condition number past
    float32's reach and every component came out NaN. Data with singular values falling
    geometrically from 1 to 1e-6 over 600 directions, 396 of them asked for."""
    rng = np.random.default_rng(0)
    n, d, r = 1800, 2048, 600
    left = np.linalg.qr(rng.normal(size=(n, r)))[0]
    right = np.linalg.qr(rng.normal(size=(d, r)))[0]
    x = ((left * np.geomspace(1.0, 1e-6, r)) @ right.T * 100).astype(np.float32)
    assert pca.choose_solver(n, d, "auto", 356) == "subspace"
    fast = pca.fit_pca(x, 356)
    assert np.isfinite(np.asarray(fast.components)).all()
    full = pca.fit_pca(x, 356, solver="covariance")
    _assert_leading_50_agree(fast, full)


def test_removal_keeps_what_training_never_spanned():
    """Fewer training images than pixels: k = 0 is raw centred pixels exactly, and every
    k's descriptor is the image minus its projection on the first k components."""
    rng = np.random.default_rng(4)
    x = _data(20, 60)  # 20 images of 60 pixels: the components span 19 dimensions
    queries = rng.normal(size=(6, 60)).astype(np.float32)  # mostly outside that span
    state = pca.fit_pca(x, 8)
    centred = queries - x.mean(0)
    np.testing.assert_allclose(pca.encode(state, queries, 0, "pixels"), centred, atol=1e-5)
    raw = cosine_similarity(centred, centred[::-1])
    for output in ("coefficients", "pixels"):
        ours = cosine_similarity(
            pca.encode(state, queries, 0, output), pca.encode(state, queries[::-1], 0, output)
        )
        np.testing.assert_allclose(ours, raw, atol=1e-5)
    v = np.asarray(state.components[:5], np.float64)
    expected = centred - centred @ v.T @ v
    np.testing.assert_allclose(pca.encode(state, queries, 5, "pixels"), expected, atol=1e-4)
    one_pass = suffix_cosine(
        pca.suffix_descriptors(state, queries),
        pca.suffix_descriptors(state, queries[::-1]),
        (0, 5, 8),
    )
    for i, k in enumerate((0, 5, 8)):
        each = cosine_similarity(
            pca.encode(state, queries, k, "pixels"), pca.encode(state, queries[::-1], k, "pixels")
        )
        np.testing.assert_allclose(one_pass[i], each, atol=2e-5)
