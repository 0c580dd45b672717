"""PCA on training sets that are not of full rank, as real routes are (a train standing at a
station repeats a frame; tunnels are black): every solver against scikit-learn's PCA in
float64, orthonormal components, only as many as the data's numerical rank, and PCA with no
component removed ranking exactly as raw pixels."""

import numpy as np
import pytest
from sklearn.decomposition import PCA

from vpr_jax.encoders import pca
from vpr_jax.evaluation.matching import cosine_similarity

D = 160  # pixels: more than most sets below have images, so auto picks the Gram solver


def _distinct(n: int, seed: int) -> np.ndarray:
    """``n`` images with a decaying spectrum (distinct eigenvalues: unique components)."""
    rng = np.random.default_rng(seed)
    return (rng.normal(size=(n, D)) * np.linspace(3.0, 0.3, D) + 0.5).astype(np.float32)


def _repeated() -> np.ndarray:
    """40 places, the first standing for 50 frames more (a station stop)."""
    x = _distinct(40, 1)
    return np.concatenate([x, np.repeat(x[:1], 50, axis=0)])


def _constant() -> np.ndarray:
    """45 images, 20 black frames (a tunnel) and 10 over-exposed ones; a pixel that never
    changes (the broadcaster's logo)."""
    x = np.concatenate([_distinct(45, 2), np.zeros((20, D)), np.ones((10, D))])
    x[:, 7] = 0.9
    return x.astype(np.float32)


def _fewer_than_pixels() -> np.ndarray:
    return _distinct(60, 3)


def _near_duplicates() -> np.ndarray:
    """30 images and each again with noise at float32's rounding level."""
    x = _distinct(30, 4)
    noise = np.random.default_rng(5).normal(size=x.shape) * 1e-7
    return np.concatenate([x, (x + noise).astype(np.float32)])


EXACT_RANK = {"repeated": _repeated, "constant": _constant, "fewer": _fewer_than_pixels}
SETS = {**EXACT_RANK, "near_duplicates": _near_duplicates}
SOLVERS = ("covariance", "gram", "auto")


def _oracle(x: np.ndarray) -> tuple[int, PCA]:
    """numpy's rank of the centred float32 data, and scikit-learn's PCA in float64."""
    rank = int(np.linalg.matrix_rank(x - x.mean(axis=0)))
    return rank, PCA(svd_solver="full").fit(x.astype(np.float64))


def _sines(a, b) -> np.ndarray:
    cosines = np.linalg.svd(np.asarray(a, np.float64) @ np.asarray(b).T, compute_uv=False)
    return np.sqrt(np.clip(1 - cosines**2, 0, None))


@pytest.mark.parametrize("solver", SOLVERS)
@pytest.mark.parametrize("name", sorted(EXACT_RANK))
def test_every_solver_holds_the_numerical_rank_in_orthonormal_components(name, solver):
    x = EXACT_RANK[name]()
    rank, sk = _oracle(x)
    if name != "fewer":
        assert rank < pca.rank_limit(*x.shape)  # the data are rank-deficient
    state = pca.fit_pca(x, solver=solver)
    assert len(state.components) == rank
    assert float(pca.orthonormality_error(state.components)) < 1e-4
    np.testing.assert_allclose(state.mean, sk.mean_, atol=1e-5)
    ev = sk.explained_variance_[:rank]
    np.testing.assert_allclose(state.explained_variance, ev, rtol=2e-3, atol=1e-5 * ev[0])
    # The components span the same space, and the well-separated leading ones agree.
    assert _sines(state.components, sk.components_[:rank]).max() < 1e-2
    np.testing.assert_allclose(state.components[:10], sk.components_[:10], atol=2e-3)


@pytest.mark.parametrize("name", sorted(SETS))
def test_the_subspace_solver_is_orthonormal_however_many_components_are_asked(name):
    x = SETS[name]()
    _, sk = _oracle(x)
    few = pca.fit_pca(x, 5, solver="subspace")
    assert _sines(few.components, sk.components_[:5]).max() < 1e-2
    np.testing.assert_allclose(few.explained_variance, sk.explained_variance_[:5], rtol=1e-3)
    # Every component the shape allows: beyond the rank the power iterations' Cholesky
    # factor used to break down and every component came out NaN.
    every = pca.fit_pca(x, solver="subspace")
    assert np.isfinite(np.asarray(every.components)).all()
    assert float(pca.orthonormality_error(every.components)) < 1e-4
    assert len(every.components) <= np.linalg.matrix_rank(x - x.mean(axis=0)) + 1


def test_near_duplicates_give_orthonormal_components_of_the_distinct_images():
    x = _near_duplicates()
    _, sk = _oracle(x)
    for solver in SOLVERS:
        state = pca.fit_pca(x, solver=solver)
        assert float(pca.orthonormality_error(state.components)) < 1e-4
        # 30 distinct images hold 29 components; the float32 noise is below the floor.
        assert len(state.components) == 29, solver
        assert _sines(state.components, sk.components_[:29]).max() < 1e-2


@pytest.mark.parametrize("solver", SOLVERS)
def test_a_variance_just_above_the_floor_is_kept_and_one_below_it_dropped(solver):
    """Images with known variances along orthonormal directions: the floor,
    ``rank_tolerance`` of the largest, is where components end, for every solver."""
    n = 200
    floor = pca.rank_tolerance(n, D)
    variances = np.array([1.0, 1e-2, 1e-4, 3 * floor, floor / 3, 0.0])
    rng = np.random.default_rng(8)
    scores = rng.normal(size=(n, len(variances)))
    scores, _ = np.linalg.qr(scores - scores.mean(axis=0))  # orthonormal, centred columns
    directions, _ = np.linalg.qr(rng.normal(size=(D, len(variances))))
    x = (scores * np.sqrt(variances * (n - 1))) @ directions.T + 0.5
    state = pca.fit_pca(x.astype(np.float32), solver=solver)
    assert len(state.components) == 4
    np.testing.assert_allclose(state.explained_variance, variances[:4], rtol=0.05)
    assert _sines(state.components, directions.T[:4]).max() < 1e-2


@pytest.mark.parametrize("solver", SOLVERS)
def test_no_component_removed_ranks_exactly_as_raw_pixels(solver):
    """k = 0 is the centred image in an orthonormal basis plus its residual: cosine, and so
    every ranking, equals raw pixels' (the training mean subtracted, as raw does)."""
    train = _repeated()
    rng = np.random.default_rng(7)
    db = np.concatenate([train[:40], train[:5]]) + rng.normal(size=(45, D)).astype(np.float32)
    queries = db[::-1] + 0.5 * rng.normal(size=db.shape).astype(np.float32)
    state = pca.fit_pca(train, solver=solver)
    mean = train.mean(axis=0)
    raw = cosine_similarity(queries - mean, db - mean)
    ours = cosine_similarity(pca.encode(state, queries, 0), pca.encode(state, db, 0))
    np.testing.assert_allclose(ours, raw, atol=1e-5)
    np.testing.assert_array_equal(np.argsort(-np.asarray(ours), 1), np.argsort(-raw, 1))


def test_a_fit_that_is_not_orthonormal_is_refused():
    state = pca.fit_pca(_fewer_than_pixels())
    broken = state._replace(components=state.components.at[1].set(state.components[0]))
    with pytest.raises(pca.NotOrthonormal, match="not orthonormal"):
        pca.check_orthonormal(broken, "gram")
    pca.check_orthonormal(state, "gram")


def test_a_full_solve_below_the_rank_writes_the_residual_on_its_other_eigenvectors():
    """The covariance solver keeps the eigenvectors beyond the rank as the complement: the
    descriptors are D wide (not rank + D), and the cosine on every suffix [k:] is the
    cosine of the k-removed images in pixels (numpy's)."""
    train = _repeated()
    state = pca.fit_pca(train, solver="covariance")
    assert len(state.components) < D and len(state.components) + len(state.complement) == D
    rng = np.random.default_rng(8)
    images = train[:30] + rng.normal(size=(30, D)).astype(np.float32)
    described = np.asarray(pca.suffix_descriptors(state, images), np.float64)
    assert described.shape == (30, D)
    x, comps = images - np.asarray(state.mean), np.asarray(state.components, np.float64)
    for k in (0, 3, 10):
        removed = x - (x @ comps[:k].T) @ comps[:k]
        np.testing.assert_allclose(
            cosine_similarity(described[:, k:], described[:, k:]),
            cosine_similarity(removed, removed),
            atol=1e-5,
        )
