"""Symmetric FastICA against scikit-learn's FastICA(algorithm="parallel") as the oracle."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment
from sklearn.decomposition import FastICA

from vpr_jax.data.synthetic import synthetic_route
from vpr_jax.encoders import ica, pca
from vpr_jax.evaluation.matching import cosine_similarity


def _sources(kind: str, n: int, c: int, rng) -> np.ndarray:
    if kind == "laplace":  # super-Gaussian
        return rng.laplace(size=(n, c))
    if kind == "uniform":  # sub-Gaussian
        return rng.uniform(-1, 1, size=(n, c))
    half = c // 2  # a mix of both
    return np.concatenate([rng.laplace(size=(n, half)), rng.uniform(-1, 1, (n, c - half))], 1)


def _mixture(kind: str, n=3000, c=6, d=6, seed=0, noise=0.0):
    rng = np.random.default_rng(seed)
    mixing = rng.normal(size=(d, c))
    x = _sources(kind, n, c, rng) @ mixing.T + noise * rng.normal(size=(n, d))
    return x.astype(np.float32), mixing


def _sklearn(x, c, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # its ConvergenceWarning; we compare results
        kw.setdefault("random_state", 0)
        return FastICA(c, algorithm="parallel", whiten="unit-variance", **kw).fit(
            x.astype(np.float64)
        )


def _total_unmixing(state: ica.ICAState) -> np.ndarray:
    return np.asarray(state.unmixing @ state.whitening)


# ---------------------------------------------------------------------------- the metric


def test_amari_distance_is_zero_for_scaled_permutations_and_known_on_a_hand_example():
    perm = np.eye(4)[[2, 0, 3, 1]] * np.array([3.0, -0.5, 2.0, -7.0])[:, None]
    assert ica.amari_distance(perm, np.eye(4)) == 0.0
    assert ica.amari_distance(np.linalg.inv(perm), perm) == pytest.approx(0.0, abs=1e-12)
    # |P| = [[1, .5], [.5, 1]]: each row and column sums to 1.5 its max -> (2*.5 + 2*.5) / 4.
    assert ica.amari_distance(np.array([[1.0, -0.5], [0.5, 1.0]]), np.eye(2)) == 0.5
    assert ica.amari_distance(np.ones((3, 3)), np.eye(3)) == 1.0


# ------------------------------------------------------------- separation vs scikit-learn


@pytest.mark.parametrize("kind", ["laplace", "uniform", "mixed"])
@pytest.mark.parametrize("fun", ["logcosh", "exp", "cube"])
def test_separates_known_sources_no_worse_than_scikit_learn(kind, fun):
    x, mixing = _mixture(kind)
    kw = dict(fun=fun, max_iter=200, tol=1e-4)
    ours = ica.fit_ica(x, jax.random.key(0), n_components=6, **kw)
    theirs = _sklearn(x, 6, **kw)
    d_ours = ica.amari_distance(_total_unmixing(ours), mixing)
    d_theirs = ica.amari_distance(theirs.components_, mixing)
    assert d_ours <= d_theirs * 1.05 + 1e-3, (d_ours, d_theirs)
    assert d_ours < 0.1
    assert bool(ours.converged) and 1 <= int(ours.n_iter) < 200


def test_logcosh_alpha_and_a_tall_noisy_mixture_match_scikit_learn():
    x, mixing = _mixture("mixed", n=4000, c=6, d=40, seed=3, noise=0.01)
    kw = dict(fun="logcosh", max_iter=300, tol=1e-4)
    ours = ica.fit_ica(x, jax.random.key(1), n_components=6, alpha=1.5, **kw)
    theirs = _sklearn(x, 6, fun_args={"alpha": 1.5}, **kw)
    d_ours = ica.amari_distance(_total_unmixing(ours), mixing)
    d_theirs = ica.amari_distance(theirs.components_, mixing)
    assert d_ours <= d_theirs * 1.05 + 1e-3, (d_ours, d_theirs)


def test_on_images_recovers_scikit_learns_components_up_to_sign_and_order():
    # Image ICA has several near-equal local optima, and which one a fit reaches depends on
    # its initial W (scikit-learn draws its own from random_state, and how it draws has
    # changed between releases), so both start from the same w_init: the fixed-point
    # iterations must then arrive at the same components.
    route = synthetic_route(400, ("summer", "fall"), 0)
    x = np.concatenate([route.images["summer"], route.images["fall"]]).reshape(800, -1)
    kw = dict(fun="logcosh", max_iter=1000, tol=1e-5)
    w_init = np.random.default_rng(0).normal(size=(16, 16))
    ours = ica.fit_ica(x, None, n_components=16, w_init=jnp.asarray(w_init, jnp.float32), **kw)
    theirs = _sklearn(x, 16, w_init=w_init, **kw)
    assert bool(ours.converged) and theirs.n_iter_ < 1000
    a = np.asarray(ica.encode(ours, x))
    b = theirs.transform(x.astype(np.float64))
    corr = np.abs(np.corrcoef(a.T, b.T)[:16, 16:])
    rows, cols = linear_sum_assignment(-corr)
    assert corr[rows, cols].min() > 0.99, np.sort(corr[rows, cols])


# ----------------------------------------------------------------------- the fitted state


def test_sources_are_white_on_training_data_and_components_are_canonical():
    x, _ = _mixture("mixed", n=2000, c=5, d=12, seed=1, noise=0.05)
    state = ica.fit_ica(x, jax.random.key(0), n_components=5)
    s = np.asarray(ica.encode(state, x), np.float64)
    np.testing.assert_allclose(np.cov(s.T, ddof=0), np.eye(5), atol=1e-4)
    np.testing.assert_allclose(np.asarray(state.unmixing @ state.unmixing.T), np.eye(5), atol=1e-5)
    a = np.asarray(ica.mixing(state))
    energy = (a**2).sum(0)
    assert np.all(np.diff(energy) <= 1e-6 * energy[0])  # decreasing energy
    assert np.all(a[np.abs(a).argmax(0), np.arange(5)] > 0)  # peaks positive
    # The mixing columns reconstruct the centred training data from the sources.
    np.testing.assert_allclose(s @ a.T, x - x.mean(0), atol=0.02 * np.abs(x).max())


def test_whitening_reuses_the_pca_fit_after_removing_components():
    x, _ = _mixture("laplace", n=1500, c=10, d=10, seed=2)
    p = pca.fit_pca(x)
    state = ica.fit_ica(x, jax.random.key(0), n_components=4, removed_pcs=3, pca_state=p)
    comps = np.asarray(p.components)
    # Whitening rows are PCA components 3..6, each over its population standard deviation.
    var = np.asarray(p.explained_variance[3:7]) * (1500 - 1) / 1500
    np.testing.assert_allclose(
        np.asarray(state.whitening), comps[3:7] / np.sqrt(var)[:, None], rtol=1e-6
    )
    # An image along a removed component has no independent-component coefficients.
    removed = np.asarray(p.mean) + 5.0 * comps[:3]
    np.testing.assert_allclose(np.asarray(ica.encode(state, removed)), 0.0, atol=1e-4)
    # Passing the PCA fit or letting fit_ica make its own gives the same model.
    again = ica.fit_ica(x, jax.random.key(0), n_components=4, removed_pcs=3)
    np.testing.assert_allclose(np.asarray(again.unmixing), np.asarray(state.unmixing), atol=1e-5)


def test_all_components_means_the_rank_left_after_removal():
    x, _ = _mixture("uniform", n=50, c=8, d=100, seed=0, noise=0.1)  # rank 49 < 100 pixels
    state = ica.fit_ica(x, jax.random.key(0), n_components="all", removed_pcs=9, max_iter=5)
    assert state.unmixing.shape == (40, 40) and state.whitening.shape == (40, 100)
    with pytest.raises(ValueError, match="ica.n_components=41 with removed_pcs=9"):
        ica.fit_ica(x, jax.random.key(0), n_components=41, removed_pcs=9)


def test_stopping_at_max_iter_is_reported_as_not_converged():
    x, _ = _mixture("mixed")
    state = ica.fit_ica(x, jax.random.key(0), n_components=6, max_iter=2, tol=1e-9)
    assert int(state.n_iter) == 2 and not bool(state.converged)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(fun="tanh"), "fun='tanh'"),
        (dict(alpha=3.0), "alpha=3.0"),
        (dict(max_iter=0), "max_iter"),
        (dict(n_init=2, w_init=np.eye(6)), "n_init=2"),
        (dict(key=None), "exactly one of key"),
        (dict(w_init=np.eye(6)), "exactly one of key"),
        (dict(key=None, w_init=np.eye(5)), r"w_init has shape \(5, 5\)"),
    ],
)
def test_bad_arguments_raise_clear_errors(kwargs, message):
    x, _ = _mixture("mixed")
    kwargs = {"key": jax.random.key(0), **kwargs}
    with pytest.raises(ValueError, match=message):
        ica.fit_ica(x, n_components=6, **kwargs)


# ------------------------------------------------------------- JAX transformations


def _whitened(x, c):
    p = pca.fit_pca(x)
    return (jnp.asarray(x) - p.mean) @ ica.whitening_matrix(p, x.shape[0], 0, c).T


def test_jit_equals_eager():
    x, _ = _mixture("mixed", n=1000)
    z = _whitened(x, 6)
    w0 = jax.random.normal(jax.random.key(3), (6, 6))
    w_jit, n_jit, _ = ica.fastica(z, w0, "logcosh", 1.0, 200, 1e-4)
    with jax.disable_jit():
        w_eager, n_eager, _ = ica.fastica(z, w0, "logcosh", 1.0, 200, 1e-4)
    assert int(n_jit) == int(n_eager)
    np.testing.assert_allclose(np.asarray(w_jit), np.asarray(w_eager), atol=1e-5)


def test_vmap_over_initialisations_equals_one_at_a_time_and_n_init_keeps_the_best():
    x, _ = _mixture("mixed", n=1500, c=6, d=6, seed=4)
    z = _whitened(x, 6)
    keys = jax.random.split(jax.random.key(7), 4)
    inits = jax.vmap(lambda k: jax.random.normal(k, (6, 6)))(keys)
    ws, iters, _ = jax.vmap(ica.fastica, in_axes=(None, 0, None, None, None, None))(
        z, inits, "exp", 1.0, 200, 1e-4
    )
    for i in range(4):
        w, n_iter, _ = ica.fastica(z, inits[i], "exp", 1.0, 200, 1e-4)
        assert int(iters[i]) == int(n_iter)
        np.testing.assert_allclose(np.asarray(ws[i]), np.asarray(w), atol=1e-5)

    best = ica.fit_ica(x, jax.random.key(7), n_components=6, fun="exp", n_init=4)
    singles = [ica.fit_ica(x, n_components=6, fun="exp", w_init=w) for w in inits]
    # Negentropy ignores the order and signs of rows, which the canonical form changes.
    scores = [float(ica.negentropy(s.unmixing, z, "exp", 1.0)) for s in singles]
    assert float(ica.negentropy(best.unmixing, z, "exp", 1.0)) >= max(scores) - 1e-6
    # It is one of the single runs (batched products round differently: tol-sized gaps).
    gaps = [np.abs(np.asarray(best.unmixing - s.unmixing)).max() for s in singles]
    assert min(gaps) < 5e-3


def test_negentropy_uses_the_gaussian_reference_value():
    # For a standard normal v: E[log cosh v] = 0.3745672..., E[-exp(-v^2/2)] = -1/sqrt(2),
    # E[v^4 / 4] = 3/4 (closed forms / tables).
    assert ica._gaussian_contrast("logcosh", 1.0) == pytest.approx(0.3745672, abs=1e-6)
    assert ica._gaussian_contrast("exp", 1.0) == pytest.approx(-1 / np.sqrt(2), abs=1e-7)
    assert ica._gaussian_contrast("cube", 1.0) == pytest.approx(0.75, abs=1e-7)


def test_encode_is_pure_under_jit_vmap_and_inside_other_jitted_code():
    x, _ = _mixture("mixed", n=600, c=6, d=32, seed=5, noise=0.01)
    state = ica.fit_ica(x, jax.random.key(0), n_components=6)
    images = x[:60].reshape(60, 4, 8)  # any trailing image shape is flattened
    direct = np.asarray(ica.encode(state, images))
    batched = jax.vmap(ica.encode, in_axes=(None, 0))(state, images.reshape(3, 20, 4, 8))
    np.testing.assert_allclose(np.asarray(batched).reshape(60, 6), direct, atol=1e-5)

    @jax.jit
    def user_similarity(st, a, b):
        ea, eb = ica.encode(st, a), ica.encode(st, b)
        ea = ea / jnp.linalg.norm(ea, axis=1, keepdims=True)
        eb = eb / jnp.linalg.norm(eb, axis=1, keepdims=True)
        return ea @ eb.T

    sim = np.asarray(user_similarity(state, images[:10], images[:10]))
    np.testing.assert_allclose(np.diag(sim), 1.0, atol=1e-5)
    with jax.disable_jit():
        eager = np.asarray(ica.encode(state, images))
    np.testing.assert_allclose(eager, direct, atol=1e-4)


# ------------------------------------------------------------------------ in the sweep


def test_sweep_cells_whiten_from_the_pairs_one_pca_fit():
    """pca and ica, as the sweep calls them, work from the PCA fit they are handed (the
    pair's shared one), not from one of their own."""
    from vpr_jax.methods import ica as ica_method
    from vpr_jax.methods import pca as pca_method
    from vpr_jax.methods.contract import PCAFit

    route = synthetic_route(300, ("summer", "fall"), 0)
    s, f = route.images["summer"], route.images["fall"]
    train, query, db = np.concatenate([s[:200], f[:200]]), f[250:], s[250:]
    fit = PCAFit(state=pca.fit_pca(train, 16), seconds=0.0)
    state = pca_method.method.fit(
        train, None, None, pca_fit=fit, solver="auto", output="pixels", whiten=0
    )
    np.testing.assert_array_equal(
        pca_method.method.encode(state, query, removed_pcs=4),
        pca.encode(fit.state, query, 4, "pixels"),
    )
    settings = {"n_components": 12, "fun": "logcosh", "alpha": 1.0, "max_iter": 200, "tol": 1e-4}
    key = jax.random.key(0)
    mine = ica_method.fit(train, None, key, pca_fit=fit, removed_pcs=4, n_init=1, **settings)
    other = PCAFit(state=pca.fit_pca(train[::-1][:300], 16), seconds=0.0)
    elsewhere = ica_method.fit(train, None, key, pca_fit=other, removed_pcs=4, n_init=1, **settings)
    assert not np.allclose(ica.encode(elsewhere, query), ica.encode(mine, query))
    direct = ica.fit_ica(train, key, n_components=12, removed_pcs=4)

    def top1(state):
        q, d = (np.asarray(ica.encode(state, x)) for x in (query, db))
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        return np.argmax(q @ d.T, axis=1)

    np.testing.assert_array_equal(top1(mine), top1(direct))
    report = ica_method.method.report(mine, {**settings, "removed_pcs": 4, "max_iter": 200})
    assert report.basis.shape == (12, 32 * 64) and report.n_iter == int(direct.n_iter)


def test_ica_ranks_exactly_as_pca_whitened_to_its_components():
    """FastICA's unmixing is orthogonal on whitened data, a rotation: under cosine, ICA of c
    components after k removed ranks every database image exactly as PCA whitened to the
    same c components does (``pca.whiten=c``), whatever its seed."""
    from vpr_jax.methods import pca as pca_method

    rng = np.random.default_rng(0)
    sources = rng.laplace(size=(300, 6)) @ rng.normal(size=(6, 128))
    x = (sources + 0.1 * rng.normal(size=(300, 128))).astype(np.float32)
    fit = pca.fit_pca(x)
    queries, db = x[:40] + 0.05, x[40:200]
    for k, c, seed in ((0, 5, 1), (2, 4, 7)):
        state = ica.fit_ica(x, jax.random.key(seed), n_components=c, removed_pcs=k, pca_state=fit)
        with_ica = cosine_similarity(ica.encode(state, queries), ica.encode(state, db))
        whitened = pca_method.Whitened(fit, jnp.arange(c, dtype=jnp.int32))
        described = pca_method.encode(whitened, queries, k)
        assert described.shape == (len(queries), c)  # the whitened components, nothing else
        with_pca = cosine_similarity(described, pca_method.encode(whitened, db, k))
        np.testing.assert_allclose(with_ica, with_pca, atol=1e-5)
        np.testing.assert_array_equal(
            np.argmax(np.asarray(with_ica), axis=1), np.argmax(np.asarray(with_pca), axis=1)
        )
