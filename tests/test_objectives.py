"""The auto-encoders' objectives: what cross_season trains on, how it is augmented and
scored, and that its models train, checkpoint and load like the paper's."""

import jax
import numpy as np
import pytest
from flax import nnx
from omegaconf import OmegaConf

from tests.conftest import (
    assert_one_line_error,
    method_settings,
    run_here,
    tail_validation,
)
from tests.inputs import frame_image, write_release
from vpr_jax.command_line import parse_config
from vpr_jax.config import SplitConfig, TrainConfig
from vpr_jax.data.augment import AugmentConfig
from vpr_jax.data.nordland import read_image_release
from vpr_jax.data.pair import pair_data
from vpr_jax.data.splits import make_split
from vpr_jax.data.synthetic import synthetic_route
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import objectives
from vpr_jax.encoders.train import TrainingData, TrainOptions, fit_autoencoder
from vpr_jax.errors import UserError
from vpr_jax.methods.loading import load_encoder
from vpr_jax.presets import DIR as PRESET_DIR


def _images(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).random((n, 32, 64), dtype=np.float32)


def test_training_pairs_follow_frame_ids_not_positions(tmp_path):
    # fall lacks frame 1 and has frame 41: by position every fall image would be one place on.
    write_release(
        tmp_path, {"summer": [frame_image("summer", f) for f in range(1, 41)]}, range(1, 41)
    )
    write_release(tmp_path, {"fall": [frame_image("fall", f) for f in range(2, 42)]}, range(2, 42))
    route = read_image_release(tmp_path, ["summer", "fall"], log=lambda line: None)
    split = make_split(route.frame_ids, SplitConfig(n_train=20, n_test=10, gap=2))
    data = pair_data(route, split, "summer", "fall", "test", 2)
    pairs = objectives.training_data("cross_season", data.train)
    ids = route.frame_ids[split.train]
    assert ids[0] == 2 and len(pairs) == len(ids) == 16  # 20 less 2 validating, a gap of 2
    val_pairs = objectives.training_data("cross_season", data.val)
    for some, frames in ((pairs, ids), (val_pairs, route.frame_ids[split.val])):
        for i, frame in enumerate(frames):
            for season, j in (("summer", 0), ("fall", 1)):
                np.testing.assert_array_equal(
                    some[i, j], frame_image(season, frame) / np.float32(255)
                )


def test_a_places_two_images_get_the_same_augmentation():
    a = _images(16)
    pairs = np.stack([a, 0.5 * a], axis=1)  # season b: season a at half the brightness
    out = np.asarray(objectives.augment(jax.random.key(3), pairs, AugmentConfig(), "cross_season"))
    np.testing.assert_allclose(out[:, 1], 0.5 * out[:, 0], rtol=1e-6)
    moved = [not np.array_equal(out[i, 0], a[i]) for i in range(16)]
    assert sum(moved) >= 12  # and each place drew its own transform
    assert len({out[i, 0].tobytes() for i in range(16)}) == 16


def test_cross_season_scores_either_season_against_the_places_mean():
    graphdef, params = ae.build(ae.FAESpec(hidden=8), jax.random.key(0))
    model = ae.make_reconstruct(graphdef)
    a, b = _images(6, 1), _images(6, 2)
    got = np.asarray(
        objectives.per_example_loss(
            "cross_season", nnx.merge(graphdef, params), np.stack([a, b], axis=1)
        )
    )
    mean = (a + b) / 2
    out_a, out_b = np.asarray(model(params, a)), np.asarray(model(params, b))
    error = lambda out: ((out - mean) ** 2).mean(axis=(1, 2))  # noqa: E731
    expected = (error(out_a) + error(out_b)) / 2
    np.testing.assert_allclose(got, expected, rtol=1e-5)
    assert float(
        objectives.loss("cross_season", graphdef, params, np.stack([a, b], 1))
    ) == pytest.approx(expected.mean(), rel=1e-5)


@pytest.mark.parametrize(
    "spec",
    [
        ae.FAESpec(hidden=16),
        ae.CAESpec(channels=(4, 8), kernel_sizes=(3, 3), code_channels=8, space_to_depth=2),
    ],
)
def test_cross_season_trains_checkpoints_and_loads(spec, tmp_path):
    images = np.concatenate([_images(120, 4), _images(120, 4) * 0.6 + 0.2])  # two "seasons"
    train, val = tail_validation(images, 2, 0.1)
    settings = TrainConfig(
        epochs=3, batch_size=32, learning_rate=3e-3, patience=10, checkpoint_every_s=0
    )
    pairs, val_pairs = (objectives.training_data("cross_season", x) for x in (train, val))

    def fit(train, val, objective):
        key = jax.random.key(0)
        return fit_autoencoder(
            spec,
            TrainingData(train, val),
            TrainOptions(
                key=key, settings=settings, checkpoint_dir=tmp_path / "m", objective=objective
            ),
        )

    result = fit(pairs, val_pairs, "cross_season")
    assert result.steps == 3 * (len(pairs) // 16)  # 32 images a step: 16 places
    encode, params = load_encoder(tmp_path / "m")
    np.testing.assert_array_equal(
        encode(params, val[:5]), ae.make_encode(result.graphdef)(result.params, val[:5])
    )
    assert fit(pairs, val_pairs, "cross_season").restored
    # The objective is part of the model's identity: the paper's objective does not reuse it.
    with pytest.raises(UserError, match="other data or settings"):
        fit(train, val, "reconstruct")


def test_cross_season_lowers_its_validation_loss():
    route = synthetic_route(120, ("summer", "fall"), 0)
    train, val = tail_validation(
        np.concatenate([route.images["summer"], route.images["fall"]]), 2, 0.1
    )
    pairs, val_pairs = (objectives.training_data("cross_season", x) for x in (train, val))
    spec = ae.FAESpec(hidden=16)
    settings = TrainConfig(epochs=5, batch_size=16, learning_rate=3e-3, patience=10)
    graphdef, initial = ae.build(spec, jax.random.fold_in(jax.random.key(0), 0))
    before = float(
        np.mean(
            objectives.per_example_loss("cross_season", nnx.merge(graphdef, initial), val_pairs)
        )
    )
    result = fit_autoencoder(
        spec,
        TrainingData(pairs, val_pairs),
        TrainOptions(key=jax.random.key(0), settings=settings, objective="cross_season"),
    )
    assert result.best_val_loss < 0.8 * before


def test_an_objective_list_is_one_value_or_many():
    def objective(argv, name="fae"):
        return method_settings(parse_config(argv), name).objective

    assert objective(["fae.objective=cross_season"]) == ("cross_season",)
    both = objective(["cae.objective=[cross_season,reconstruct]"], "cae")
    assert both == ("cross_season", "reconstruct")
    assert objective(["preset=paper"]) == ("reconstruct",)
    assert objective([]) == ("reconstruct", "cross_season")


@pytest.mark.parametrize(
    "args,words",
    [
        (["fae.objective=swap"], ["fae.objective=['swap']", "cross_season"]),
        (["cae.objective=[reconstruct,reconstruct]"], ["cae.objective", "repeats"]),
        (["cae.model=huge"], ["cae.model=huge", "fast or calc"]),
        (["fae.input=edges"], ["fae.input=edges", "standardised, pixels, residual, residual_"]),
        (["cae.input=gradients"], ["cae.input=gradients", "the linear methods'"]),
        (
            ["fae.standardise=false"],
            ["fae.standardise is now fae.input", "fae.input=pixels (for false)", "residual_pixels"],
        ),
        (["fae.init=xavier"], ["fae.init=xavier", "random, pca, whitened_pca"]),
        (["train.augment=maybe"], ["train.augment=maybe", "true, false, auto or place"]),
        (["train.temperature=0"], ["train.temperature=0", "> 0"]),
    ],
)
def test_bad_objective_or_model_is_one_line(args, words, tmp_path):
    assert_one_line_error(run_here(*args, f"logdir={tmp_path / 'runs'}"), *words)


def test_the_real_preset_sets_no_data_keys_and_its_logdir_names_the_source():
    preset = OmegaConf.load(PRESET_DIR / "real.yaml")
    assert not {"data", "split", "season_pairs", "tolerance"} & set(preset)
    assert parse_config(["preset=real"]).logdir == "runs/real_synthetic"
    argv = ["preset=real", "data.source=vpr_bench", "data.root=/nowhere"]
    cfg = parse_config(argv)
    assert cfg.logdir == "runs/real_vpr_bench" and cfg.train.augment == "auto"
    # Without aligned training places its paired objectives give way to the paper's (each
    # auto-encoder's check), unless named on the command line.
    from experiments.resolve import load
    from vpr_jax.method_table import METHODS
    from vpr_jax.methods.contract import TrainingSet

    for name in ("fae", "cae"):
        unaligned = TrainingSet(
            n_images=100,
            n_pixels=2048,
            aligned=False,
            swept={},
            given=frozenset(),
        )
        check = load(METHODS[name]).check
        assert check(method_settings(cfg, name), unaligned, print).objective == ("reconstruct",)
        named = method_settings(parse_config([*argv, f"{name}.objective=contrastive"]), name)
        with pytest.raises(UserError, match=f"{name}.objective=contrastive needs aligned"):
            check(named, unaligned._replace(given=frozenset({"objective"})), print)
    assert parse_config(["preset=real", "logdir=mine"]).logdir == "mine"
    assert parse_config(["train.augment=false"]).train.augment is False


def test_augment_contrastive_is_infonce_of_two_changes_of_conditions():
    """The loss of augment_contrastive is numpy's InfoNCE of the codes of each image's two
    views (condition_views of the key), every other image of the batch a wrong place."""
    from flax import nnx

    from vpr_jax.data.augment import condition_views
    from vpr_jax.encoders import autoencoders as ae
    from vpr_jax.encoders import objectives

    graphdef, params = ae.build(ae.FAESpec(hidden=16), jax.random.key(0))
    model = nnx.merge(graphdef, params)
    images = np.random.default_rng(0).random((6, 32, 64)).astype(np.float32)
    key = jax.random.key(9)
    got = np.asarray(
        objectives.per_example_loss("augment_contrastive", model, images, 0.1, key=key)
    )
    views = np.asarray(condition_views(key, images))
    codes = [np.asarray(model.encode(views[:, j]), np.float64) for j in (0, 1)]
    a, b = (c / np.linalg.norm(c, axis=1, keepdims=True) for c in codes)
    logits = a @ b.T / 0.1
    rows = np.log(np.exp(logits).sum(axis=1)) - np.diag(logits)
    cols = np.log(np.exp(logits).sum(axis=0)) - np.diag(logits)
    np.testing.assert_allclose(got, (rows + cols) / 2, rtol=1e-4, atol=1e-5)
    assert objectives.examples_per_image("augment_contrastive") == 2
    assert "augment_contrastive" not in objectives.PAIRED  # no aligned places needed
