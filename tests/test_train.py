"""Auto-encoder training: loss falls, checkpoints round-trip, interrupted runs resume exactly."""

import json

import jax
import numpy as np
import pytest

from tests.conftest import read_run, tail_validation
from vpr_jax.config import TrainConfig
from vpr_jax.data.synthetic import synthetic_route
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import checkpoints
from vpr_jax.encoders.train import TrainingData, TrainOptions, fit_autoencoder
from vpr_jax.encoders.train_programs import make_eval_loss
from vpr_jax.errors import UserError
from vpr_jax.methods.loading import load_encoder
from vpr_jax.outputs.tb import TrainingRun

SPEC = ae.FAESpec(hidden=16)
SETTINGS = TrainConfig(epochs=3, batch_size=32, patience=10, checkpoint_every_s=0)


@pytest.fixture(scope="module")
def data():
    route = synthetic_route(120, ("summer", "fall"), 0)
    images = np.concatenate([route.images["summer"], route.images["fall"]])
    return tail_validation(images, 2, 0.1)  # 216 training images: 6 steps per epoch


class StopAt:
    """A training log that interrupts training at one step, like Ctrl-C would."""

    def __init__(self, step: int, inner=None):
        self.step, self.inner = step, inner

    def begin(self, step):
        if self.inner:
            self.inner.begin(step)

    def scalar(self, tag, value, step):
        if self.inner:
            self.inner.scalar(tag, value, step)
        if step == self.step:
            raise KeyboardInterrupt

    def images(self, tag, images, step):
        if self.inner:
            self.inner.images(tag, images, step)

    def line(self, text):
        pass

    def close(self):
        if self.inner:
            self.inner.close()


def _equal(a, b) -> bool:
    return all(
        np.array_equal(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    )


def _train_steps(run_dir, tag="loss/train") -> list[int]:
    return [e.step for e in read_run(run_dir).Scalars(tag)]


@pytest.mark.parametrize(
    "spec", [SPEC, ae.CAESpec(channels=(4, 8), kernel_sizes=(3, 3), code_channels=2)]
)
def test_validation_loss_falls(data, spec):
    train, val = data
    graphdef, initial = ae.build(spec, jax.random.fold_in(jax.random.key(0), 0))
    before = make_eval_loss(graphdef, 32)(initial, val)
    settings = TrainConfig(epochs=5, batch_size=16, learning_rate=3e-3, patience=10)
    result = fit_autoencoder(
        spec, TrainingData(train, val), TrainOptions(key=jax.random.key(0), settings=settings)
    )
    assert result.best_val_loss < 0.8 * before
    assert result.epochs == 5 and result.steps == 5 * (len(train) // 16)
    assert not result.restored and result.resumed_epoch == 0


def test_checkpoint_round_trip_gives_identical_codes(data, tmp_path):
    train, val = data
    result = fit_autoencoder(
        SPEC,
        TrainingData(train, val),
        TrainOptions(key=jax.random.key(1), settings=SETTINGS, checkpoint_dir=tmp_path / "fae"),
    )
    encode, params = load_encoder(tmp_path / "fae")
    assert _equal(params, result.params)
    np.testing.assert_array_equal(
        encode(params, val), ae.make_encode(result.graphdef)(result.params, val)
    )
    # Run again: the finished model is restored, not retrained.
    again = fit_autoencoder(
        SPEC,
        TrainingData(train, val),
        TrainOptions(key=jax.random.key(1), settings=SETTINGS, checkpoint_dir=tmp_path / "fae"),
    )
    assert again.restored and _equal(again.params, result.params)
    assert again.epochs == result.epochs and again.train_seconds == pytest.approx(
        result.train_seconds, rel=1e-6
    )


def test_an_interrupted_run_resumes_at_its_saved_epoch_and_ends_as_an_uninterrupted_one(
    data, tmp_path
):
    train, val = data
    key = jax.random.key(2)
    whole = fit_autoencoder(
        SPEC,
        TrainingData(train, val),
        TrainOptions(key=key, settings=SETTINGS, checkpoint_dir=tmp_path / "whole"),
    )
    steps_per_epoch = len(train) // 32
    folder, tb_dir = tmp_path / "cut", tmp_path / "tb"
    cut = StopAt(2 * steps_per_epoch + 3, TrainingRun(tb_dir, print))  # mid epoch 3
    with pytest.raises(KeyboardInterrupt):
        try:
            fit_autoencoder(
                SPEC,
                TrainingData(train, val),
                TrainOptions(key=key, settings=SETTINGS, checkpoint_dir=folder, log=cut),
            )
        finally:
            cut.close()  # as the sweep does: what was logged reaches the disk
    assert _train_steps(tb_dir)[-1] == 2 * steps_per_epoch + 3
    log = TrainingRun(tb_dir, print)
    try:
        resumed = fit_autoencoder(
            SPEC,
            TrainingData(train, val),
            TrainOptions(key=key, settings=SETTINGS, checkpoint_dir=folder, log=log),
        )
    finally:
        log.close()
    assert resumed.resumed_epoch == 2 and resumed.steps == whole.steps
    assert _equal(resumed.params, whole.params)
    assert resumed.best_val_loss == whole.best_val_loss
    # TensorBoard shows every step once: what the cut session logged after epoch 2 is purged.
    assert _train_steps(tb_dir) == list(range(1, whole.steps + 1))
    # The starting weights are scored at step 0, then every epoch.
    assert _train_steps(tb_dir, "loss/validation") == [steps_per_epoch * e for e in (0, 1, 2, 3)]


def test_checkpoints_wait_checkpoint_every_s_but_the_last_epoch_is_always_saved(data, tmp_path):
    train, val = data
    rare = TrainConfig(epochs=3, batch_size=32, patience=10, checkpoint_every_s=3600)
    folder = tmp_path / "rare"
    cut = StopAt(2 * (len(train) // 32) + 3)  # in epoch 3: epochs 1 and 2 were not due
    with pytest.raises(KeyboardInterrupt):
        fit_autoencoder(
            SPEC,
            TrainingData(train, val),
            TrainOptions(key=jax.random.key(5), settings=rare, checkpoint_dir=folder, log=cut),
        )
    assert not checkpoints.has_checkpoint(folder)
    result = fit_autoencoder(
        SPEC,
        TrainingData(train, val),
        TrainOptions(key=jax.random.key(5), settings=rare, checkpoint_dir=folder),
    )
    assert result.resumed_epoch == 0 and checkpoints.read_meta(folder)["epoch"] == 3
    again = fit_autoencoder(
        SPEC,
        TrainingData(train, val),
        TrainOptions(key=jax.random.key(5), settings=rare, checkpoint_dir=folder),
    )
    assert again.restored and _equal(again.params, result.params)


def test_early_stopping_keeps_the_best_parameters(data):
    train, val = data
    # A learning rate far below float32 resolution: no epoch beats the starting weights.
    frozen = TrainConfig(epochs=10, batch_size=32, learning_rate=1e-12, patience=2)
    result = fit_autoencoder(
        SPEC, TrainingData(train, val), TrainOptions(key=jax.random.key(3), settings=frozen)
    )
    assert result.stopped_early and result.epochs == 2 and result.best_epoch == 0
    graphdef = result.graphdef
    assert make_eval_loss(graphdef, 32)(result.params, val) == result.best_val_loss


def test_a_checkpoint_of_other_data_or_settings_is_refused(data, tmp_path):
    train, val = data
    one = TrainConfig(epochs=1, batch_size=32)
    folder = tmp_path / "m"
    fit_autoencoder(
        SPEC,
        TrainingData(train, val),
        TrainOptions(
            key=jax.random.key(4), settings=one, checkpoint_dir=folder, identity={"seed": 4}
        ),
    )
    with pytest.raises(UserError, match="other data or settings"):
        fit_autoencoder(
            SPEC,
            TrainingData(train, val),
            TrainOptions(
                key=jax.random.key(4), settings=one, checkpoint_dir=folder, identity={"seed": 5}
            ),
        )
    with pytest.raises(UserError, match="other data or settings"):
        fit_autoencoder(
            ae.FAESpec(hidden=8),
            TrainingData(train, val),
            TrainOptions(
                key=jax.random.key(4), settings=one, checkpoint_dir=folder, identity={"seed": 4}
            ),
        )


def test_a_checkpoint_of_another_format_is_refused_and_left_alone(data, tmp_path):
    """Checkpoints carry their format: one of another format is neither resumed nor loaded,
    and stays as it was."""
    train, val = data
    one = TrainConfig(epochs=1, batch_size=32)
    folder = tmp_path / "other_format"
    fit_autoencoder(
        SPEC,
        TrainingData(train, val),
        TrainOptions(key=jax.random.key(4), settings=one, checkpoint_dir=folder),
    )
    for meta_file in folder.glob("*/meta/metadata"):  # as another version would write it
        meta = json.loads(meta_file.read_text())
        assert meta["format"] == checkpoints.FORMAT
        meta_file.write_text(json.dumps({**meta, "format": checkpoints.FORMAT - 1}))
    before = {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}
    for attempt in (
        lambda: load_encoder(folder),
        lambda: fit_autoencoder(
            SPEC,
            TrainingData(train, val),
            TrainOptions(key=jax.random.key(4), settings=one, checkpoint_dir=folder),
        ),
    ):
        with pytest.raises(UserError, match="another format .*use a new folder"):
            attempt()
    assert {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()} == before


def test_what_orbax_says_while_saving_reaches_file_descriptor_2_under_a_redirected_stderr(capfd):
    """A save that succeeds passes on what was written to stderr meanwhile, also where
    sys.stderr is another stream (a sweep's main run with its output captured)."""
    import contextlib
    import io
    import os

    with contextlib.redirect_stderr(io.StringIO()), checkpoints.orbax_noise_held():
        os.write(2, b"orbax: a warning\n")
    assert capfd.readouterr().err == "orbax: a warning\n"
