"""The rectified code (``rectify``: ``[relu(z), relu(-z)]``) and lda's standardised input:
the code's cosine against numpy's, its place as a sweep axis for built-in linear methods and
a user's, and ``load_encoder`` giving the same code back."""

import json
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.conftest import TINY_ROUTE, shared_folder, shared_sweep
from vpr_jax import load_encoder
from vpr_jax.methods.rectify import rectified
from vpr_jax.outputs.results import read_results, swept_of


def _cosines(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    x = x / np.linalg.norm(x, axis=1, keepdims=True)
    y = y / np.linalg.norm(y, axis=1, keepdims=True)
    return x @ y.T


def test_a_rectified_code_scores_only_the_coordinates_of_one_sign():
    """cos([a+, a-], [b+, b-]) = sum over i with a_i b_i > 0 of a_i b_i / (|a| |b|): numpy's
    sum, against the cosine of our code (eager, jitted and vmapped over rows alike)."""
    rng = np.random.default_rng(0)
    a = rng.normal(size=(7, 12)).astype(np.float32)
    b = rng.normal(size=(5, 12)).astype(np.float32)
    same_sign = np.where(a[:, None, :] * b[None, :, :] > 0, a[:, None, :] * b[None, :, :], 0)
    oracle = same_sign.sum(axis=2) / np.outer(np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1))
    ours = _cosines(np.asarray(rectified(jnp.asarray(a))), np.asarray(rectified(jnp.asarray(b))))
    np.testing.assert_allclose(ours, oracle, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(jax.jit(rectified)(a)), np.asarray(rectified(a)))
    one_row = jax.vmap(lambda row: rectified(row[None])[0])(jnp.asarray(a))
    np.testing.assert_array_equal(np.asarray(one_row), np.asarray(rectified(a)))
    # a coordinate that flips sign between the two images adds nothing
    flipped = np.array([[1.0, 2.0]], np.float32), np.array([[1.0, -2.0]], np.float32)
    code = [np.asarray(rectified(jnp.asarray(v))) for v in flipped]
    assert _cosines(*code)[0, 0] == pytest.approx(1 / 5)


# A user's linear method made rectifiable: a PCA projection of its first n directions.
PROJECTION = """
import jax.numpy as jnp

from vpr_jax.methods.rectify import rectifiable


class _projection:
    random = False

    @staticmethod
    def fit(train, aligned, key, n=6):
        x = jnp.reshape(train, (len(train), -1))
        mean = x.mean(axis=0)
        _, _, vt = jnp.linalg.svd(x - mean, full_matrices=False)
        return {"mean": mean, "components": vt[:n]}

    @staticmethod
    def encode(state, images):
        x = jnp.reshape(images, (images.shape[0], -1)) - state["mean"]
        return x @ state["components"].T


projection = rectifiable(_projection)
"""


def _write_module(folder: Path) -> None:
    (folder / "mine").mkdir()
    (folder / "mine" / "linear_codes.py").write_text(textwrap.dedent(PROJECTION))


@pytest.fixture(scope="session")
def rectify_sweep(tmp_path_factory):
    folder = shared_folder(tmp_path_factory, "rectify_module", _write_module)
    args = [
        *TINY_ROUTE,
        "season_pairs=summer-fall",
        "removed_pcs=[0,5]",
        "methods=[pca,lda,linear_codes:projection]",
        "pca.rectify=[false,true]",
        "lda.rectify=[false,true]",
        "lda.n_components=24",
        "plugin.projection.rectify=[false,true]",
        f"train.checkpoint_dir={folder / 'checkpoints'}",
    ]
    logdir, proc = shared_sweep(tmp_path_factory, "rectify", *args, path=[folder / "mine"])
    assert proc.returncode == 0, proc.stderr[-3000:]
    return logdir, folder / "mine"


def _fitted(logdir: Path) -> dict[str, str]:
    """Each saved fit's folder by its name (encoders.csv)."""
    import csv

    with open(logdir / "encoders.csv") as f:
        return {Path(e["folder"]).name: e["folder"] for e in csv.DictReader(f)}


def test_rectify_is_an_axis_of_built_in_and_user_methods(rectify_sweep):
    """A list for rectify gives both codes as rows, chosen among on validation; a rectified
    PCA serves each removed count by itself (one row per count, as the plain one)."""
    rows = read_results(rectify_sweep[0] / "results.csv")
    for method in ("pca", "lda", "projection"):
        mine = [r for r in rows if r.method == method]
        values = {swept_of(r)["rectify"] for r in mine}
        assert values == {False, True}, method
        assert sum(r.selected for r in mine) == 1, method  # one choice among them all
    pca_rows = {(swept_of(r)["rectify"], r.removed_pcs) for r in rows if r.method == "pca"}
    assert pca_rows == {(False, 0), (False, 5), (True, 0), (True, 5)}


@pytest.mark.parametrize(
    "name", ["pca_rectify=True", "lda_rectify=True", "projection_rectify=True"]
)
def test_load_encoder_gives_the_rectified_code_back(rectify_sweep, name, monkeypatch):
    """The rectified fit's encoder is the plain fit's code, rectified (numpy), for every
    method and served value."""
    logdir, module_folder = rectify_sweep
    monkeypatch.syspath_prepend(str(module_folder))  # the user's method, as a user runs it
    folders = _fitted(logdir)
    plain = folders[name.replace("True", "False")]
    with open(Path(folders[name]) / "encoder.json") as f:
        served = [cell["served"] for cell in json.load(f)["cells"]]
    images = np.random.default_rng(2).random((6, 32, 64), dtype=np.float32)
    for values in served:
        mine = ["linear_codes:projection"]  # the user's method, named as the sweep named it
        encode, params = load_encoder(folders[name], plugins=mine, **values)
        encode_plain, params_plain = load_encoder(plain, plugins=mine, **values)
        z = np.asarray(encode_plain(params_plain, images))
        expected = np.concatenate([np.maximum(z, 0), np.maximum(-z, 0)], axis=1)
        np.testing.assert_allclose(np.asarray(encode(params, images)), expected, atol=1e-5)
