"""Methods that learn from aligned places: supervised change removal (diff_pca) and
within-place whitening (lda), against numpy and scikit-learn references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from sklearn.decomposition import PCA

from tests.conftest import numpy_cosine, suffix_cosine
from vpr_jax.encoders import diff_pca, lda, pca

CHANGE_SCALES = np.array([8.0, 6.0, 4.5, 3.5, 2.5, 2.0])  # distinct: directions well defined


def _aligned(n: int, d: int = 96, seed: int = 0):
    """Two 'seasons' of n places: place content shared by both, a seasonal change that
    lives in six fixed directions (the same for every seed) and noise. Images are
    (n, 8, d // 8)."""
    change = np.random.default_rng(99).normal(size=(len(CHANGE_SCALES), d)) / np.sqrt(d)
    rng = np.random.default_rng(seed)
    places = rng.normal(size=(n, d))
    shift = rng.normal(size=(n, len(CHANGE_SCALES))) * CHANGE_SCALES @ change * np.sqrt(d)
    a = places + shift / 2 + 0.5 * rng.normal(size=(n, d))
    b = places - shift / 2 + 0.5 * rng.normal(size=(n, d))
    as_images = lambda x: x.reshape(n, 8, d // 8).astype(np.float32)  # noqa: E731
    return as_images(a), as_images(b)


def _flat(x):
    return np.asarray(x, np.float64).reshape(len(x), -1)


# ---------------------------------------------------------------------------------- diff_pca


@pytest.mark.parametrize("n", [300, 40])  # more places than pixels, and fewer
def test_diff_pca_directions_are_the_principal_directions_of_the_season_differences(n):
    a, b = _aligned(n)
    state = diff_pca.fit_diff_pca(a, b, 6)
    diff = _flat(a) - _flat(b)
    eigvals, eigvecs = np.linalg.eigh(diff.T @ diff / n)  # second moment: not centred
    eigvals, eigvecs = eigvals[::-1][:6], eigvecs[:, ::-1][:, :6]
    np.testing.assert_allclose(state.explained_variance, eigvals, rtol=2e-3)
    cosines = np.abs(np.sum(np.asarray(state.components, np.float64) * eigvecs.T, axis=1))
    np.testing.assert_allclose(cosines, 1.0, atol=2e-3)
    np.testing.assert_allclose(state.mean, np.concatenate([_flat(a), _flat(b)]).mean(0), atol=1e-5)


@pytest.mark.parametrize("n", [300, 40])
def test_diff_pca_keeps_what_it_does_not_remove(n):
    a, b = _aligned(n)
    state = diff_pca.fit_diff_pca(a, b, 6)
    x = _flat(a[:10]) - np.asarray(state.mean, np.float64)
    u = np.asarray(state.components, np.float64)
    for k in (0, 1, 4, 6):
        expected = x - x @ u[:k].T @ u[:k]
        np.testing.assert_allclose(diff_pca.encode(state, a[:10], k), expected, atol=1e-4)
    np.testing.assert_allclose(diff_pca.encode(state, a[:10], 0), x, atol=1e-5)  # raw pixels


def test_diff_pca_suffix_cosine_is_the_cosine_of_each_count():
    a, b = _aligned(200)
    state = diff_pca.fit_diff_pca(a, b, 6)
    starts = (0, 2, 4, 6)
    sims = suffix_cosine(
        diff_pca.suffix_descriptors(state, b[:30]),
        diff_pca.suffix_descriptors(state, a[:50]),
        starts,
    )
    for i, k in enumerate(starts):
        ref = numpy_cosine(
            np.asarray(diff_pca.encode(state, b[:30], k), np.float64),
            np.asarray(diff_pca.encode(state, a[:50], k), np.float64),
        )
        np.testing.assert_allclose(sims[i], ref, atol=1e-5)


def test_diff_pca_encode_works_under_jit_and_vmap():
    a, b = _aligned(100)
    state = diff_pca.fit_diff_pca(a, b, 6)
    counts = jnp.array([0, 3, 6])
    per_k = jax.vmap(lambda k: diff_pca.encode(state, a[:5], k))(counts)
    inside = jax.jit(lambda s, x: diff_pca.encode(s, x, 3) * 2.0)(state, a[:5])
    for i, k in enumerate((0, 3, 6)):
        np.testing.assert_allclose(per_k[i], diff_pca.encode(state, a[:5], k), atol=1e-6)
    np.testing.assert_allclose(inside, 2.0 * diff_pca.encode(state, a[:5], 3), atol=1e-6)


def test_diff_pca_removal_helps_where_the_change_is_strong():
    a, b = _aligned(300, seed=1)
    db, q = _aligned(100, seed=2)  # other places, the same kind of change
    state = diff_pca.fit_diff_pca(a, b, 6)
    recall = [
        np.mean(
            np.argmax(
                numpy_cosine(
                    np.asarray(diff_pca.encode(state, q, k)),
                    np.asarray(diff_pca.encode(state, db, k)),
                ),
                axis=1,
            )
            == np.arange(100)
        )
        for k in (0, 6)
    ]
    assert recall[1] > recall[0] + 0.2, recall


def test_diff_pca_refuses_more_directions_than_places():
    a, b = _aligned(5)
    with pytest.raises(ValueError, match="1..5"):
        diff_pca.fit_diff_pca(a, b, 6)


# --------------------------------------------------------------------------------------- lda


def numpy_lda(a, b, n_components, shrinkage):
    """The reference: scikit-learn's PCA of both seasons, the within-place scatter of the
    coordinates, shrunk towards trace/m x identity, and its inverse square root."""
    x = np.concatenate([_flat(a), _flat(b)])
    reference = PCA(n_components, svd_solver="full").fit(x)
    za, zb = reference.transform(_flat(a)), reference.transform(_flat(b))
    centre = (za + zb) / 2
    scatter = ((za - centre).T @ (za - centre) + (zb - centre).T @ (zb - centre)) / (2 * len(a))
    m = n_components
    shrunk = (1 - shrinkage) * scatter + shrinkage * np.trace(scatter) / m * np.eye(m)
    eigvals, eigvecs = np.linalg.eigh(shrunk)
    whiten = eigvecs / np.sqrt(eigvals)
    return lambda images: reference.transform(_flat(images)) @ whiten


@pytest.mark.parametrize("shrinkage", [0.0, 0.1, 1.0])
def test_lda_equals_the_numpy_reference(shrinkage):
    a, b = _aligned(300)
    state = lda.fit_lda(pca.fit_pca(np.concatenate([a, b])), a, b, 20, shrinkage)
    reference = numpy_lda(a, b, 20, shrinkage)
    ours_q, ours_d = np.asarray(lda.encode(state, b[:40])), np.asarray(lda.encode(state, a))
    # Signs and rotations inside equal eigenvalues are arbitrary; inner products are not.
    np.testing.assert_allclose(
        ours_q @ ours_d.T,
        reference(b[:40]) @ reference(a).T,
        rtol=2e-3,
        atol=2e-3 * np.abs(ours_q @ ours_d.T).max(),
    )
    assert ours_q.shape == (40, 20)


def test_lda_with_full_shrinkage_matches_like_the_pca_coordinates():
    a, b = _aligned(300)
    fit = pca.fit_pca(np.concatenate([a, b]))
    state = lda.fit_lda(fit, a, b, 20, 1.0)
    coords = lambda x: np.asarray(pca.project(fit, x))[:, :20]  # noqa: E731
    np.testing.assert_allclose(
        numpy_cosine(np.asarray(lda.encode(state, b)), np.asarray(lda.encode(state, a))),
        numpy_cosine(coords(b), coords(a)),
        atol=1e-4,
    )


def test_lda_whitening_makes_the_within_place_scatter_white():
    a, b = _aligned(300)
    state = lda.fit_lda(pca.fit_pca(np.concatenate([a, b])), a, b, 20, 0.0)
    za, zb = np.asarray(lda.encode(state, a), np.float64), np.asarray(lda.encode(state, b))
    scatter = np.asarray(lda.within_place_scatter(za, zb))
    np.testing.assert_allclose(scatter, np.eye(20), atol=2e-3)


def test_lda_encode_works_under_jit_and_vmap():
    a, b = _aligned(100)
    state = lda.fit_lda(pca.fit_pca(np.concatenate([a, b])), a, b, 10)
    batches = jnp.stack([a[:4], b[:4]])
    per_batch = jax.vmap(lambda x: lda.encode(state, x))(batches)
    np.testing.assert_allclose(per_batch[1], lda.encode(state, b[:4]), atol=1e-6)
    inside = jax.jit(lambda s, x: jnp.sum(lda.encode(s, x) ** 2))(state, a[:4])
    assert np.isclose(inside, np.sum(np.asarray(lda.encode(state, a[:4])) ** 2), rtol=1e-5)
