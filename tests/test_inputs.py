"""What a method sees (``<method>.input``, ``vpr_jax.methods.inputs``): each part and a
combination's scaling against numpy and scikit-image; a list of inputs is an axis chosen on
the validation places; every encoder a sweep saved with an input scores the sweep's test
places as the sweep did, in a fresh process, and works under jit, vmap and grad."""

import csv
import json
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.conftest import TINY_ROUTE, assert_one_line_error, run_here, run_process, shared_sweep
from vpr_jax import load_encoder
from vpr_jax.encoders import inputs
from vpr_jax.outputs.results import read_results, swept_of

skimage_feature = pytest.importorskip("skimage.feature")

ARGS = [
    *TINY_ROUTE,
    "season_pairs=summer-fall",
    "methods=[raw,pca,ica,lda]",
    "removed_pcs=[0,5]",
    "ica.n_components=8",
    "lda.n_components=24",
    "raw.input=[pixels,gradients]",
    "pca.input=standardised+gradients",
    "ica.input=patchnorm",
    "lda.input=[pixels,standardised,standardised+gradients]",
]


def _hog(image: np.ndarray) -> np.ndarray:
    """scikit-image's histograms with the suite's defaults (gradients.*)."""
    return skimage_feature.hog(
        image, orientations=9, pixels_per_cell=(4, 4), cells_per_block=(3, 3), block_norm="L2"
    )


def test_a_combination_is_its_parts_each_scaled_to_unit_total_variance():
    """numpy's standardisation and scikit-image's histograms, each part divided by the square
    root of its summed feature variances over the training images, side by side."""
    rng = np.random.default_rng(3)
    train = rng.integers(0, 256, (12, 32, 64)).astype(np.float64) / 256  # exact gradients
    new = rng.integers(0, 256, (3, 32, 64)).astype(np.float64) / 256

    def standardised(x):
        centred = x - x.mean(axis=(1, 2), keepdims=True)
        return (0.25 * centred / (x.std(axis=(1, 2), keepdims=True) + 1e-3)).reshape(len(x), -1)

    def gradients(x):
        return np.stack([_hog(image) for image in x])

    def scale(features):
        return 1 / np.sqrt(((features - features.mean(axis=0)) ** 2).sum() / len(features))

    scales = [scale(part(train)) for part in (standardised, gradients)]
    expected = np.concatenate([standardised(new) * scales[0], gradients(new) * scales[1]], 1)
    state = inputs.fit("standardised+gradients", jnp.asarray(train, jnp.float32))
    np.testing.assert_allclose(np.asarray(state.scales), scales, rtol=1e-5)
    ours = np.asarray(inputs.apply(state, jnp.asarray(new, jnp.float32)))
    np.testing.assert_allclose(ours, expected, rtol=1e-4, atol=1e-5)
    # each part of the training images' input has total variance 1
    seen = np.asarray(inputs.apply(state, jnp.asarray(train, jnp.float32)))
    width = 32 * 64
    for part in (seen[:, :width], seen[:, width:]):
        assert ((part - part.mean(axis=0)) ** 2).sum() / len(part) == pytest.approx(1, rel=1e-4)


def test_a_single_part_is_left_unscaled_and_pixels_are_the_images():
    x = jnp.asarray(np.random.default_rng(4).random((3, 32, 64)), jnp.float32)
    state = inputs.fit("pixels", x)
    assert inputs.apply(state, x) is not None and np.array_equal(inputs.apply(state, x), x)
    gradients = inputs.apply(inputs.fit("gradients", x), x)
    assert gradients.shape == (3, inputs.n_values("gradients", (32, 64)))  # 6,804


def test_a_standardised_input_ignores_a_season_s_brightness_and_contrast():
    """raw on standardised images: an image scaled and shifted in grey level has the same
    code up to its length (the 1e-3 that keeps a flat image's standardisation finite)."""
    from vpr_jax.methods import raw

    rng = np.random.default_rng(1)
    a = rng.random((40, 32, 64), dtype=np.float32)
    state = raw.method.fit(a, None, None, input="standardised")
    code = np.asarray(raw.method.encode(state, a[:5]))
    brighter = np.asarray(raw.method.encode(state, 0.6 * a[:5] + 0.3))
    cosines = (code * brighter).sum(1) / np.linalg.norm(code, axis=1)
    np.testing.assert_allclose(cosines / np.linalg.norm(brighter, axis=1), 1.0, atol=1e-5)
    plain = raw.method.fit(a, None, None)
    code, brighter = (np.asarray(raw.method.encode(plain, x)) for x in (a[:5], 0.6 * a[:5] + 0.3))
    cosines = (code * brighter).sum(1) / np.linalg.norm(code, axis=1)
    assert not np.allclose(cosines / np.linalg.norm(brighter, axis=1), 1.0, atol=1e-3)


@pytest.fixture(scope="session")
def inputs_sweep(tmp_path_factory):
    logdir, proc = shared_sweep(tmp_path_factory, "inputs", *ARGS)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return logdir


def test_a_list_of_inputs_is_an_axis_chosen_on_validation(inputs_sweep):
    rows = read_results(inputs_sweep / "results.csv")
    for method, values in (
        ("raw", {"pixels", "gradients"}),
        ("lda", {"pixels", "standardised", "standardised+gradients"}),
    ):
        mine = [r for r in rows if r.method == method]
        assert {swept_of(r)["input"] for r in mine} == values, method
        assert sum(r.selected for r in mine) == 1, method  # one choice among them
    # one input, no axis: no input in the swept values, as for any setting given once
    assert all("input" not in swept_of(r) for r in rows if r.method in ("pca", "ica"))


def test_a_fresh_process_scores_every_input_s_encoder_as_the_sweep_did(inputs_sweep):
    proc = run_process(
        [sys.executable, "tests/saved_encoder_checks.py", str(inputs_sweep), "summer-fall", *ARGS]
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    checks = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(checks) == 2 + 1 + 2 + 3  # raw x2, pca, ica x2 counts, lda x3
    for folder, check in checks.items():
        assert check["score_gap"] < 1e-5, (folder, check)
        assert check["recall_at_1"] == check["sweep_recall_at_1"], (folder, check)


def test_an_encoder_with_an_input_works_inside_jit_vmap_and_grad(inputs_sweep):
    with open(inputs_sweep / "encoders.csv", newline="") as f:
        folders = {e["folder"].rsplit("/", 1)[-1]: e["folder"] for e in csv.DictReader(f)}
    encode, params = load_encoder(folders["lda_input=standardised+gradients"])
    x = jnp.asarray(np.random.default_rng(5).random((4, 32, 64)), jnp.float32)
    codes = encode(params, x)
    one_by_one = jax.vmap(lambda image: encode(params, image[None])[0])(x)
    np.testing.assert_allclose(np.asarray(one_by_one), np.asarray(codes), atol=1e-5)
    again = jax.jit(lambda p, images: encode(p, images))(params, x)
    np.testing.assert_allclose(np.asarray(again), np.asarray(codes), atol=1e-5)
    grad = jax.grad(lambda images: jnp.sum(encode(params, images) ** 2))(x)
    assert grad.shape == x.shape and bool(jnp.all(jnp.isfinite(grad)))


def test_a_logdir_from_before_inputs_resumes_and_a_changed_one_is_refused(tmp_path):
    """A config.yaml written before ``input`` and ``gradients.*`` existed (lda's old
    ``standardise: false``, no gradients group) resumes: the same numbers; one that recorded
    ``standardise: true`` (another fit than today's) is refused in one line."""
    import yaml

    args = [*TINY_ROUTE, "season_pairs=summer-fall", "methods=[raw,lda]", "lda.n_components=24"]
    logdir = tmp_path / "runs"
    first = run_here(*args, f"logdir={logdir}")
    assert first.returncode == 0, first.stderr[-2000:]
    config = yaml.safe_load((logdir / "config.yaml").read_text())
    config.pop("gradients")
    for method in ("raw", "lda"):
        config[method].pop("input")
    config["lda"]["standardise"] = False
    _resumes_and_a_change_is_refused(args, logdir, config, 2, "lda", {"standardise": True})


def _resumes_and_a_change_is_refused(args, logdir, config: dict, cells: int, method, change):
    """The sweep resumes ``logdir`` with its config.yaml rewritten to ``config`` (every
    cell already there); with ``change`` made to ``config[method]`` it is another
    configuration, refused in one line."""
    import yaml

    (logdir / "config.yaml").write_text(yaml.safe_dump(config))
    again = run_here(*args, f"logdir={logdir}")
    assert again.returncode == 0, again.stderr[-2000:]
    assert f"resuming: {cells} of {cells} cells already in results.csv" in again.stdout
    config[method].update(change)
    (logdir / "config.yaml").write_text(yaml.safe_dump(config))
    assert_one_line_error(run_here(*args, f"logdir={logdir}"), "different configuration", method)


def test_an_autoencoder_s_old_input_and_standardise_resume_as_one_input(tmp_path):
    """fae.input and fae.standardise, recorded apart before they became one input: a logdir
    that recorded the default pair (pixels, true) resumes as ``standardised``; (pixels,
    false) is another input and refused. The model's checkpoint still names its input as
    checkpoints always have (pixels, standardised), so a model trained before resumes."""
    import yaml

    from vpr_jax.encoders import checkpoints

    args = [
        *TINY_ROUTE,
        "season_pairs=summer-fall",
        "methods=[fae]",
        "fae.objective=reconstruct",
        "fae.hidden=8",
        "fae.epochs=1",
    ]
    logdir = tmp_path / "runs"
    first = run_here(*args, f"logdir={logdir}")
    assert first.returncode == 0, first.stderr[-2000:]
    meta = checkpoints.read_meta(
        tmp_path / "checkpoints" / "runs" / "summer-fall" / "fae" / "training"
    )
    model = meta["identity"]["model"]
    assert (model["input"], model["standardise"]) == ("pixels", True)
    config = yaml.safe_load((logdir / "config.yaml").read_text())
    assert config["fae"]["input"] == "standardised"
    config["fae"].update(input="pixels", standardise=True)
    _resumes_and_a_change_is_refused(args, logdir, config, 1, "fae", {"standardise": False})


@pytest.mark.parametrize(
    ("field", "claim"), [("bins", 10**9), ("cell", 0), ("norm", "L3")], ids=str
)
def test_a_saved_input_claiming_options_no_image_allows_is_refused(
    inputs_sweep, tmp_path, field, claim
):
    """A skeleton is data: options that would make the histograms loop or allocate without
    bound (a billion bins), or fail inside JAX, are one line at load, nothing computed."""
    import shutil

    from vpr_jax.errors import UserError

    with open(inputs_sweep / "encoders.csv", newline="") as f:
        folders = {e["folder"].rsplit("/", 1)[-1]: e["folder"] for e in csv.DictReader(f)}
    folder = tmp_path / "raw_input=gradients"
    shutil.copytree(folders["raw_input=gradients"], folder)
    skeleton_path = folder / "state" / "skeleton.json"
    skeleton = json.loads(skeleton_path.read_text())
    skeleton["fields"]["input"]["static"]["options"]["fields"][field] = claim
    skeleton_path.write_text(json.dumps(skeleton))
    with pytest.raises(UserError, match="outside what an image allows"):
        load_encoder(folder)
