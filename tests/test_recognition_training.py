"""Auto-encoders trained for recognition: epochs selected by the validation places' recall@1,
the contrastive objective and the residual input, each against an oracle (numpy,
scikit-learn), and interrupted training that resumes to the same selection."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx
from sklearn.decomposition import PCA

from tests.conftest import numpy_cosine, read_run, tail_validation
from vpr_jax.config import TrainConfig
from vpr_jax.data.synthetic import synthetic_route
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import objectives
from vpr_jax.encoders.train import (
    SELECT_RECALL,
    NoLog,
    TrainingData,
    TrainOptions,
    fit_autoencoder,
)
from vpr_jax.methods.loading import load_encoder
from vpr_jax.outputs.tb import TrainingRun


def _numpy_recall_at_1(db, query, tolerance: int = 1) -> float:
    """The oracle: query i's nearest database row by cosine is correct within the
    tolerance (row i of the database is query i's place)."""
    query, db = (np.asarray(x, np.float64) + 1e-12 for x in (query, db))  # zero codes: ties
    best = np.argmax(numpy_cosine(query, db), axis=1)
    return float(np.mean(np.abs(best - np.arange(len(query))) <= tolerance))


def _validate_on(val_db, val_query):
    """``fit_autoencoder``'s validate: the validation places' recall@1 of a model's codes."""
    return lambda encode: _numpy_recall_at_1(encode(val_db), encode(val_query))


@pytest.fixture(scope="module")
def seasons():
    route = synthetic_route(160, ("summer", "winter"), 3)
    return route.images["summer"], route.images["winter"]


def test_contrastive_loss_is_infonce_both_ways():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(6, 5)), rng.normal(size=(6, 5))
    got = np.asarray(objectives.contrastive_loss(a, b, 0.2))
    sims = numpy_cosine(a, b) / 0.2

    def cross_entropy(logits):  # row i's right column is i
        logits = logits - logits.max(axis=1, keepdims=True)
        log_p = logits - np.log(np.exp(logits).sum(axis=1, keepdims=True))
        return -np.diagonal(log_p)

    np.testing.assert_allclose(got, (cross_entropy(sims) + cross_entropy(sims.T)) / 2, rtol=1e-5)
    # A batch whose places match their other season exactly scores far lower.
    assert np.mean(objectives.contrastive_loss(a, a, 0.2)) < np.mean(got)


@pytest.mark.parametrize("radius", [1, 3])
def test_the_route_mask_leaves_neighbouring_places_out_of_the_wrong_ones(radius):
    """With positions along the route, a place's neighbours within ``radius`` (correct
    matches within the tolerance) are not its negatives: numpy's InfoNCE over the columns
    that are left, both ways."""
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(8, 5)), rng.normal(size=(8, 5))
    places = np.array([0, 1, 2, 10, 11, 30, 33, 50])
    got = np.asarray(objectives.contrastive_loss(a, b, 0.2, jnp.asarray(places), radius))
    sims = numpy_cosine(a, b) / 0.2
    near = np.abs(places[:, None] - places[None, :]) <= radius
    kept = ~near | np.eye(len(places), dtype=bool)

    def cross_entropy(logits, keep):  # row i's right column is i; dropped columns absent
        rows = enumerate(zip(logits, keep, strict=True))
        return np.array([np.log(np.exp(row[k]).sum()) - row[i] for i, (row, k) in rows])

    want = (cross_entropy(sims, kept) + cross_entropy(sims.T, kept.T)) / 2
    np.testing.assert_allclose(got, want, rtol=1e-5)
    unmasked = np.asarray(objectives.contrastive_loss(a, b, 0.2))
    assert np.all(got <= unmasked + 1e-6) and np.any(got < unmasked - 1e-3)
    # Without positions, or at radius 0, every other place stays a wrong one.
    zero = objectives.contrastive_loss(a, b, 0.2, jnp.asarray(places), 0)
    np.testing.assert_array_equal(np.asarray(zero), unmasked)


@pytest.mark.parametrize(
    "spec",
    [
        ae.FAESpec(hidden=8, standardise=True, removed=4),
        ae.CAESpec(
            channels=(4, 8), kernel_sizes=(3, 3), code_channels=2, space_to_depth=2, removed=4
        ),
    ],
)
def test_residual_input_is_pca_change_removal(spec, seasons):
    images = np.concatenate(seasons)[:200]
    fit = PCA(n_components=4, svd_solver="full").fit(images.reshape(len(images), -1))
    graphdef, params = ae.build(spec, jax.random.key(0))
    params = ae.with_removal(params, fit.mean_, fit.components_)
    model = nnx.merge(graphdef, params)
    # scikit-learn's change removal: the centred image less its projection, at mid-grey
    flat = images.reshape(len(images), -1)
    expected = flat - fit.mean_ - fit.inverse_transform(fit.transform(flat)) + fit.mean_ + 0.5
    np.testing.assert_allclose(
        np.asarray(model.residual(images)).reshape(len(images), -1), expected, atol=2e-5
    )
    # The code is the plain model's code of the residual image.
    plain_graphdef, _ = ae.build(spec._replace(removed=0), jax.random.key(0))
    plain, _ = ae.split_fixed(params)
    np.testing.assert_allclose(
        ae.make_encode(graphdef)(params, images[:8]),
        ae.make_encode(plain_graphdef)(plain, np.asarray(model.residual(images[:8]))),
        atol=1e-5,
    )


def test_training_never_moves_the_removal_and_the_saved_encoder_keeps_it(seasons, tmp_path):
    images = np.concatenate(seasons)
    train, val = tail_validation(images, 2, 0.1)
    fit = PCA(n_components=3, svd_solver="full").fit(train.reshape(len(train), -1))
    fixed = {"removal_mean": fit.mean_, "removal_basis": fit.components_}
    spec = ae.FAESpec(hidden=8, standardise=True, removed=3)
    settings = TrainConfig(epochs=2, batch_size=32, optimizer="adamw", checkpoint_every_s=0)
    result = fit_autoencoder(
        spec,
        TrainingData(train, val),
        TrainOptions(
            key=jax.random.key(0), settings=settings, checkpoint_dir=tmp_path / "m", fixed=fixed
        ),
    )
    for name, value in fixed.items():  # adamw's weight decay would move any trained array
        np.testing.assert_array_equal(result.params[name], np.float32(value))
    encode, params = load_encoder(tmp_path / "m")
    np.testing.assert_array_equal(
        encode(params, val[:5]), ae.make_encode(result.graphdef)(result.params, val[:5])
    )
    again = fit_autoencoder(
        spec,
        TrainingData(train, val),
        TrainOptions(
            key=jax.random.key(0), settings=settings, checkpoint_dir=tmp_path / "m", fixed=fixed
        ),
    )  # a finished model is restored, its removal with it
    assert again.restored
    for a, b in zip(jax.tree.leaves(again.params), jax.tree.leaves(result.params), strict=True):
        np.testing.assert_array_equal(a, b)


def _curves(run_dir) -> tuple[list[float], list[float]]:
    """(validation loss, validation recall@1) per epoch, epoch 0 first, as TensorBoard
    reads them back."""
    ea = read_run(run_dir)
    loss = [e.value for e in ea.Scalars("loss/validation")]
    return loss, [e.value for e in ea.Scalars("validation/recall_at_1")]


def test_the_epoch_kept_is_the_best_validation_recall_not_the_least_loss(seasons, tmp_path):
    """Reconstructing raw pixels: the loss falls every epoch while the code learns the
    seasons' appearance, and recall on the validation places peaks elsewhere."""
    summer, winter = seasons
    n_val = 30
    train = np.concatenate([summer[:-n_val], winter[:-n_val]])
    val = np.concatenate([summer[-n_val:], winter[-n_val:]])
    validate = _validate_on(summer[-n_val:], winter[-n_val:])
    settings = TrainConfig(epochs=8, batch_size=32, patience=20, augment=False)
    log = TrainingRun(tmp_path / "tb", lambda line: None)
    try:
        result = fit_autoencoder(
            ae.FAESpec(hidden=16),
            TrainingData(train, val),
            TrainOptions(key=jax.random.key(0), settings=settings, validate=validate, log=log),
        )
    finally:
        log.close()
    loss, recall = _curves(tmp_path / "tb")
    assert len(loss) == len(recall) == 9  # the starting weights, then every epoch
    assert int(np.argmin(loss)) != int(np.argmax(recall))  # they disagree here
    assert result.selected_by == SELECT_RECALL
    assert result.best_epoch == int(np.argmax(recall))  # the first of equals
    assert result.best_score == pytest.approx(max(recall))
    encode = ae.make_encode(result.graphdef)
    assert validate(lambda x: encode(result.params, x)) == pytest.approx(max(recall))
    assert result.best_val_loss == pytest.approx(loss[result.best_epoch], rel=1e-6)


class _StopAfter:
    """A training log that interrupts training at one step, like Ctrl-C would."""

    def __init__(self, step: int):
        self.step = step

    def begin(self, step):
        pass

    def scalar(self, tag, value, step):
        if step == self.step:
            raise KeyboardInterrupt

    def images(self, tag, images, step):
        pass

    def line(self, text):
        pass

    def close(self):
        pass


def test_a_contrastive_run_resumed_selects_as_the_uninterrupted_one(seasons, tmp_path):
    summer, winter = seasons
    n_val = 30
    pairs = np.stack([summer, winter], axis=1)
    train, val = pairs[:-n_val], pairs[-n_val:]
    validate = _validate_on(summer[-n_val:], winter[-n_val:])
    settings = TrainConfig(epochs=4, batch_size=32, patience=10, checkpoint_every_s=0)

    def fit(folder, log=None):
        return fit_autoencoder(
            ae.FAESpec(hidden=16, standardise=True),
            TrainingData(train, val),
            TrainOptions(
                key=jax.random.key(1),
                settings=settings,
                checkpoint_dir=tmp_path / folder,
                objective="contrastive",
                validate=validate,
                log=log or NoLog(),
            ),
        )

    whole = fit("whole")
    steps_per_epoch = len(train) // 16  # 32 images a step: 16 places
    with pytest.raises(KeyboardInterrupt):
        fit("cut", _StopAfter(2 * steps_per_epoch + 2))
    resumed = fit("cut")
    assert resumed.resumed_epoch == 2
    assert (resumed.best_epoch, resumed.best_score) == (whole.best_epoch, whole.best_score)
    for a, b in zip(jax.tree.leaves(resumed.params), jax.tree.leaves(whole.params), strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("whiten", [False, True])
def test_the_linear_start_codes_are_the_pca_coefficients_of_the_inputs(seasons, whiten):
    images = np.concatenate(seasons)[:240]
    graphdef, drawn = ae.build(ae.FAESpec(hidden=9, standardise=True), jax.random.key(0))
    params = ae.pca_start(graphdef, drawn, images, whiten=whiten)
    model = nnx.merge(graphdef, params)
    inputs = np.asarray(model.inputs(images), np.float64)
    oracle = PCA(n_components=4, svd_solver="full", whiten=whiten)  # whiten: unit variance
    expected = oracle.fit(inputs).transform(inputs)
    codes = np.asarray(model.encode(images), np.float64)
    coefficients = codes[:, 0:8:2] - codes[:, 1:8:2]  # a unit beside its negative
    signs = np.sign(np.sum(coefficients * expected, axis=0))  # components' signs are free
    np.testing.assert_allclose(coefficients * signs, expected, atol=2e-3 * np.abs(expected).max())
    np.testing.assert_array_equal(
        params["encoder"]["kernel"][:, 8], drawn["encoder"]["kernel"][:, 8]
    )
    np.testing.assert_allclose(params["decoder"]["kernel"], params["encoder"]["kernel"].T)
    if whiten:
        np.testing.assert_allclose(np.var(coefficients, axis=0, ddof=1), 1.0, rtol=1e-2)


def test_the_lda_start_codes_are_within_place_whitened_coordinates_of_the_inputs(seasons):
    """numpy oracle: scikit-learn's PCA of both seasons' inputs, the within-place scatter
    of the aligned places in it, shrunk towards trace/m x I and whitened (eigh, ascending)."""
    a, b = seasons[0][:120], seasons[1][:120]
    graphdef, drawn = ae.build(ae.FAESpec(hidden=9, standardise=True), jax.random.key(0))
    params = ae.lda_start(graphdef, drawn, a, b, shrinkage=0.2)
    model = nnx.merge(graphdef, params)
    ia, ib = (np.asarray(model.inputs(x), np.float64) for x in (a, b))
    pca = PCA(n_components=4, svd_solver="full").fit(np.concatenate([ia, ib]))
    za, zb = pca.transform(ia), pca.transform(ib)
    scatter = (za - zb).T @ (za - zb) / (4 * len(za))
    regularised = 0.8 * scatter + 0.2 * np.trace(scatter) / 4 * np.eye(4)
    eigvals, eigvecs = np.linalg.eigh(regularised)
    expected = np.concatenate([za, zb]) @ eigvecs / np.sqrt(eigvals)
    codes = np.asarray(model.encode(np.concatenate([a, b])), np.float64)
    coefficients = codes[:, 0:8:2] - codes[:, 1:8:2]
    signs = np.sign(np.sum(coefficients * expected, axis=0))
    np.testing.assert_allclose(coefficients * signs, expected, atol=2e-3 * np.abs(expected).max())
    np.testing.assert_array_equal(
        params["encoder"]["kernel"][:, 8], drawn["encoder"]["kernel"][:, 8]
    )


def test_start_decay_adds_its_pull_towards_the_start_to_the_gradient(seasons):
    """Plain SGD, one step from weights moved off their start: the step with
    ``start_decay`` d differs from the step without by -learning_rate x d x (params -
    anchor), leaf by leaf (the gradient of d/2 x ||params - anchor||^2)."""
    from vpr_jax.encoders.train_programs import make_optimizer, make_train_step, start_penalty

    graphdef, anchor = ae.build(ae.FAESpec(hidden=8, standardise=True), jax.random.key(0))
    params = jax.tree.map(lambda a: a + 0.01 * jnp.cos(jnp.arange(a.size)).reshape(a.shape), anchor)
    settings = TrainConfig(optimizer="sgd", learning_rate=0.1, augment=False)
    tx = make_optimizer(settings)
    batch = jnp.asarray(np.stack([seasons[0][:8], seasons[1][:8]], axis=1))
    key = jax.random.key(1)
    steps = {
        decay: make_train_step(graphdef, tx, None, None, "contrastive", 0.1, 0, decay)(
            params, tx.init(params), batch, key, jnp.arange(8), anchor
        )
        for decay in (0.0, 0.5)
    }
    assert float(steps[0.0][2]["loss"]) == float(steps[0.5][2]["loss"])  # the objective's
    for moved, plain, p, a in zip(
        *(jax.tree.leaves(x) for x in (steps[0.5][0], steps[0.0][0], params, anchor)),
        strict=True,
    ):
        expected = -0.1 * 0.5 * (np.asarray(p, np.float64) - np.asarray(a, np.float64))
        np.testing.assert_allclose(np.asarray(moved) - np.asarray(plain), expected, atol=1e-6)
    distance = sum(
        np.sum((np.asarray(p, np.float64) - np.asarray(a)) ** 2)
        for p, a in zip(jax.tree.leaves(params), jax.tree.leaves(anchor), strict=True)
    )
    np.testing.assert_allclose(float(start_penalty(params, anchor)), distance / 2, rtol=1e-5)


def test_a_scale_update_leaves_the_start_and_trains_only_a_scale_and_shift_per_unit(seasons):
    """``fae.update=scale``: the model codes as the plain FAE with the same hidden layer
    (numpy: relu(x W + b) of the standardised images) until trained; contrastive steps then
    move each unit's scale and shift and leave the hidden layer's weights and biases at
    their start to the bit (the decoder is no part of the code and trains as it would)."""
    from vpr_jax.encoders.train_programs import make_optimizer, make_train_step

    spec = ae.FAESpec(hidden=8, standardise=True, update="scale")
    graphdef, params = ae.build(spec, jax.random.key(0))
    a, b = (np.asarray(s[:16], np.float32) for s in seasons)
    x = a.reshape(len(a), -1)
    x = 0.25 * (x - x.mean(axis=1, keepdims=True)) / (x.std(axis=1, keepdims=True) + 1e-3)
    kernel, bias = (np.asarray(params["encoder"][k]) for k in ("kernel", "bias"))
    np.testing.assert_allclose(
        np.asarray(ae.make_encode(graphdef)(params, a)),
        np.maximum(x @ kernel + bias, 0),
        atol=1e-4,
    )
    tx = make_optimizer(TrainConfig(augment=False, learning_rate=0.01), ae.frozen(spec))
    step = make_train_step(graphdef, tx, None, None, "contrastive", 0.1, 0, 0.0)
    state, batch = (params, tx.init(params)), jnp.asarray(np.stack([a, b], axis=1))
    for i in range(3):
        *state, _ = step(*state, batch, jax.random.key(i), jnp.arange(16), None)
    trained = state[0]
    for k in ("kernel", "bias"):
        np.testing.assert_array_equal(
            np.asarray(trained["encoder"][k]), np.asarray(params["encoder"][k])
        )
    for k in ("unit_scale", "unit_shift"):
        assert not np.allclose(np.asarray(trained[k]), np.asarray(params[k]))


def test_a_cae_started_at_lda_leads_with_the_fae_start_and_keeps_its_convolutions_alive(seasons):
    """The CAE's linear branch, started at lda, codes as an FAE of as many units started
    there (the FAE's start has its numpy oracle above); the conv code is the drawn one
    times CONV_START_SCALE (ReLU is positively homogeneous), and a contrastive step moves
    every convolution (a zeroed code layer would not)."""
    from vpr_jax.encoders.train_programs import make_optimizer, make_train_step

    a, b = seasons[0][:64], seasons[1][:64]
    spec = ae.CAESpec(
        channels=(4, 8),
        kernel_sizes=(3, 3),
        code_channels=4,
        space_to_depth=2,
        standardise=True,
        linear=12,
    )
    graphdef, drawn = ae.build(spec, jax.random.key(0))
    started = ae.lda_start(graphdef, drawn, a, b)
    fae_graph, fae_drawn = ae.build(ae.FAESpec(hidden=12, standardise=True), jax.random.key(0))
    fae = ae.lda_start(fae_graph, fae_drawn, a, b)
    images = np.concatenate([a, b])
    codes = np.asarray(ae.make_encode(graphdef)(started, images))
    np.testing.assert_allclose(
        codes[:, :12], ae.make_encode(fae_graph)(fae, images), rtol=1e-4, atol=1e-4
    )
    drawn_conv = np.asarray(ae.make_encode(graphdef)(drawn, images))[:, 12:]
    np.testing.assert_allclose(
        codes[:, 12:], ae.CONV_START_SCALE * drawn_conv, rtol=1e-4, atol=1e-7
    )
    assert codes.shape == (128, 12 + 4 * 8 * 4)

    tx = make_optimizer(TrainConfig(augment=False))
    step = make_train_step(graphdef, tx, None, None, "contrastive", 0.1, 0)
    moved, _, _ = step(started, tx.init(started), np.stack([a, b], axis=1), jax.random.key(1))
    for name in ("down", "to_code"):
        for before, after in zip(
            jax.tree.leaves(started[name]), jax.tree.leaves(moved[name]), strict=True
        ):
            assert np.abs(np.asarray(after) - np.asarray(before)).max() > 0, name
