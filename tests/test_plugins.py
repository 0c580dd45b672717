"""A user's method (``methods=[...,module:name]``) runs exactly like a built-in one: the same
rows, runs, summary and figures; its settings reach its fit; whatever goes wrong in its code
is one line, with the finished cells kept."""

import json
import os
import shutil
import sys
import textwrap
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

from experiments.fitting import checked_encode
from experiments.resolve import resolve_methods, settings_identities
from tests.conftest import (
    REPO,
    TINY_ROUTE,
    assert_one_line_error,
    env_with_repo,
    read_run,
    run_here,
    run_process,
    shared_folder,
    shared_sweep,
    sweep_rows,
)
from vpr_jax.command_line import parse_config
from vpr_jax.errors import UserError
from vpr_jax.method_table import MethodInfo
from vpr_jax.outputs.logdir import check_same_config, config_yaml
from vpr_jax.outputs.results import COLUMNS, read_results

# raw pixels, again: the training mean subtracted, the pixels flattened; its fit writes what
# it received to the file its ``record`` setting names.
CENTRED_PIXELS = """
import json

import jax
import jax.numpy as jnp


class centred_pixels:
    @staticmethod
    def fit(train, aligned, key, record, scale=1.0):
        with open(record, "a") as f:
            shapes = None if aligned is None else [list(a.shape) for a in aligned]
            differ = aligned is not None and bool((aligned[0][3] != aligned[1][3]).any())
            f.write(json.dumps({"train": list(train.shape), "aligned": shapes,
                                "scale": scale, "key": str(jax.random.key_data(key).dtype),
                                "seasons_differ": differ}) + "\\n")
        mean = jnp.mean(jnp.reshape(train, (len(train), -1)), axis=0)
        return {"mean": mean, "scale": jnp.float32(scale)}

    @staticmethod
    def encode(state, images):
        return (jnp.reshape(images, (images.shape[0], -1)) - state["mean"]) * state["scale"]
"""
BROKEN_FIT = """
class centred_pixels:
    @staticmethod
    def fit(train, aligned, key, record):
        raise RuntimeError("deliberately broken")

    @staticmethod
    def encode(state, images):
        return images
"""
SMALL_ROUTE = [*TINY_ROUTE, "season_pairs=summer-fall"]
NOT_COMPARED = {"method", "run", "fit_seconds", "encode_ms_per_image", "val_margin"}


def _module(folder: Path, name: str, source: str) -> dict:
    """Write a module of the user's into ``folder``; the environment that imports it."""
    folder.mkdir(exist_ok=True)
    (folder / f"{name}.py").write_text(textwrap.dedent(source))
    return {"PYTHONPATH": os.pathsep.join([str(REPO), str(folder)])}


@pytest.fixture(scope="session")
def own(tmp_path_factory):
    """(logdir, its arguments, the environment, the fit's record, the module's folder) of
    one sweep per session of raw pixels and a re-implementation of them as a user's
    method (read-only for every test)."""
    folder = shared_folder(
        tmp_path_factory, "own_method", lambda f: _module(f / "mine", "my_methods", CENTRED_PIXELS)
    )
    env = {"PYTHONPATH": os.pathsep.join([str(REPO), str(folder / "mine")])}
    record = folder / "fit.jsonl"
    args = [
        *SMALL_ROUTE,
        "methods=[raw,my_methods:centred_pixels]",
        f"plugin.centred_pixels.record={record}",
        "plugin.centred_pixels.scale=3",
        "preprocess=patchnorm",
        f"train.checkpoint_dir={folder / 'checkpoints'}",
    ]
    logdir, _ = shared_sweep(tmp_path_factory, "own_method_sweep", *args, path=[folder / "mine"])
    return logdir, [*args, f"logdir={logdir}"], env, record, folder / "mine"


def test_a_method_of_your_own_gives_the_numbers_of_the_built_in_it_copies(own):
    logdir, _, _, record, _ = own
    rows = {r.method: r for r in read_results(logdir / "results.csv")}
    assert set(rows) == {"raw", "centred_pixels"}
    mine, raw = rows["centred_pixels"], rows["raw"]
    for column in set(COLUMNS) - NOT_COMPARED:  # every metric, interval and setting
        assert getattr(mine, column) == getattr(raw, column), column
    # Scores (not ranks) enter the margin: float32 cosines of the same vectors, computed
    # from differently scaled ones, agree to float32's precision.
    assert mine.val_margin == pytest.approx(raw.val_margin, rel=1e-5)
    assert mine.run == "summer-fall/centred_pixels"
    assert read_run(logdir / mine.run).Scalars("metrics/recall_at_1")[0].value == pytest.approx(
        raw.recall_at_1, abs=1e-6
    )
    # What the fit received: both seasons' training places, the aligned pair, the settings.
    (received,) = [json.loads(line) for line in record.read_text().splitlines()]
    assert received["train"] == [2 * 125, 32, 64]
    assert received["aligned"] == [[125, 32, 64], [125, 32, 64]]
    assert received["seasons_differ"] and received["scale"] == 3 and received["key"] == "uint32"


def test_a_method_of_your_own_is_in_the_summary_and_the_figures(own):
    logdir, *_ = own
    raw = next(r for r in read_results(logdir / "results.csv") if r.method == "raw")
    summary = read_run(logdir / "summary" / "summer-fall")
    for method in ("raw", "centred_pixels"):
        (point,) = summary.Scalars(f"metrics/recall_at_1/{method}")
        assert point.value == pytest.approx(raw.recall_at_1, abs=1e-6)
        assert f"pr_curve/{method}" in summary.Tags()["tensors"]
    for figure in ("pr_curves.png", "correct_matches.png"):
        legend = Image.open(logdir / "figures" / figure).text["Description"]
        assert "centred_pixels" in legend and "raw" in legend, (figure, legend)


def test_a_method_of_your_own_is_saved_and_a_fresh_process_loads_it(own):
    """Patch normalisation included, it scores the test places as the sweep did."""
    logdir, args, env, _, _ = own
    checks = run_process(
        [sys.executable, "tests/saved_encoder_checks.py", str(logdir), "summer-fall", *args],
        env=env_with_repo(**env),
    )
    assert checks.returncode == 0, checks.stderr[-3000:]
    by_folder = json.loads(checks.stdout.strip().splitlines()[-1])
    assert sorted(Path(f).name for f in by_folder) == ["centred_pixels", "raw"]
    for check in by_folder.values():
        assert check["score_gap"] < 1e-5 and check["recall_at_1"] == check["sweep_recall_at_1"]


def test_a_rerun_resumes_and_other_settings_are_another_configuration(own, tmp_path):
    logdir, args, _, _, mine = own
    shutil.copytree(logdir, tmp_path / "runs")  # the shared sweep stays as it is
    shutil.copytree(logdir.parent.parent / "own_method" / "checkpoints", tmp_path / "checkpoints")
    moved = {"logdir": tmp_path / "runs", "train.checkpoint_dir": tmp_path / "checkpoints"}
    args = [f"{k}={moved[k]}" if k in moved else a for a in args for k in [a.split("=")[0]]]
    again = run_here(*args, path=[mine])
    assert "resuming: 2 of 2 cells" in again.stdout and again.returncode == 0
    other = [a if "scale=" not in a else "plugin.centred_pixels.scale=2" for a in args]
    assert_one_line_error(run_here(*other, path=[mine]), "plugin.centred_pixels", "new logdir")


def test_a_method_that_fails_is_one_line_and_the_fixed_method_resumes(tmp_path):
    """In this process, the module's folder on sys.path as PYTHONPATH would put it; the
    broken module is forgotten after its run, so the fixed one is imported afresh."""
    _module(tmp_path / "mine", "my_methods", BROKEN_FIT)
    logdir, record = tmp_path / "runs", tmp_path / "fit.jsonl"
    args = [
        *SMALL_ROUTE,
        "methods=[raw,my_methods:centred_pixels]",
        f"plugin.centred_pixels.record={record}",
        f"logdir={logdir}",
    ]
    line = assert_one_line_error(
        run_here(*args, path=[tmp_path / "mine"]),
        "method centred_pixels",
        "fit raised RuntimeError",
        "sweep.log",
    )
    assert [r.method for r in read_results(logdir / "results.csv")] == ["raw"]
    log = (logdir / "sweep.log").read_text()
    assert line in log and 'raise RuntimeError("deliberately broken")' in log  # its traceback
    _module(tmp_path / "mine", "my_methods", CENTRED_PIXELS)
    rows, fixed = sweep_rows(*args, path=[tmp_path / "mine"])
    assert "resuming: 1 of 2 cells" in fixed.stdout
    assert [r.method for r in rows] == ["raw", "centred_pixels"]


INFO = MethodInfo(name="centred_pixels", method="my_methods:centred_pixels", plugin=True)


@pytest.mark.parametrize(
    ("encode", "words"),
    [
        (lambda s, x: jnp.reshape(x, (-1, 64)), ["encode gave shape (64, 64) for 2 images"]),
        (lambda s, x: jnp.reshape(x, (len(x), -1)) / 0.0 * 0, ["NaN or infinite"]),
        (lambda s, x: x[:, 0, 0], ["encode gave shape (2,)"]),
        (lambda s, x: jnp.asarray(x) @ jnp.ones(3), ["encode raised TypeError"]),
    ],
)
def test_what_encode_returns_is_checked(encode, words):
    with pytest.raises(UserError) as err:
        checked_encode(INFO, encode)({}, np.ones((2, 32, 64), np.float32))
    message = str(err.value)
    assert message.startswith("method centred_pixels (my_methods:centred_pixels): ")
    assert all(w in message for w in words) and "\n" not in message, message
    good = checked_encode(INFO, lambda s, x: jnp.reshape(x, (len(x), -1)) * s["w"])
    assert good({"w": 2.0}, np.ones((3, 32, 64), np.float32)).shape == (3, 2048)


def test_a_built_in_encode_is_checked_as_a_users_is():
    """The runner checks every method's descriptors the same way: pca's encode on a state
    whose mean is NaN (as a broken fit would leave it) is one line naming the method."""
    from experiments.resolve import load
    from vpr_jax.encoders import pca
    from vpr_jax.method_table import METHODS

    images = np.random.default_rng(0).random((6, 32, 64), np.float32)
    state = pca.fit_pca(images)
    broken = state._replace(mean=state.mean.at[0].set(jnp.nan))
    encode = load(METHODS["pca"]).encode
    with pytest.raises(UserError) as err:
        checked_encode(METHODS["pca"], encode, jit=False)(broken, images)
    message = str(err.value)
    assert message.startswith("method pca (vpr_jax.methods.pca:method): encode gave NaN")
    assert "\n" not in message
    assert checked_encode(METHODS["pca"], encode, jit=False)(state, images).shape[0] == 6


# A method that uses every declaration of the contract (docs/methods.md, "Your own method"):
# PCA coordinates of the pair's shared fit, skipping the first ``skip`` (served: one fit),
# after the sweep's removed counts are taken out (a fit per count), on ``n`` components that
# its check caps to what the shared fit holds (a note), leaving out skips beyond ``n``.
EVERY_DECLARATION = """
import dataclasses

import jax.numpy as jnp

from vpr_jax.errors import UserError
from vpr_jax.methods.contract import Report


@dataclasses.dataclass(frozen=True)
class Settings:
    n: int = 8
    skip: int = 0
    removed_pcs: int = 0  # the sweep hands its removed_pcs to a setting of this name

    def __post_init__(self):
        if self.n < 1:
            raise UserError(f"plugin.every.n={self.n} must be >= 1")


def _check(settings, training, log):
    if settings.skip >= settings.n:
        log(f"note: every: skip={settings.skip} left out (n={settings.n})")
        return None
    held = training.pca_components - settings.removed_pcs
    if settings.n > held:
        log(f"note: every: n={settings.n} capped to {held}")
        return dataclasses.replace(settings, n=held)
    return settings


class every:
    settings = Settings
    axes = {"skip": "served"}
    needs = ("pca_fit", "validation")
    random = False
    check = staticmethod(_check)

    @staticmethod
    def fit(train, aligned, key, *, pca_fit, validation, n, removed_pcs):
        basis = pca_fit.state.components[removed_pcs : removed_pcs + n]
        seen = jnp.float32(len(validation.images))
        return {"mean": pca_fit.state.mean, "basis": basis, "validation_images": seen}

    @staticmethod
    def encode(state, images, skip=0):
        x = jnp.reshape(images, (images.shape[0], -1)) - state["mean"]
        return (x @ state["basis"].T)[:, skip:]

    @staticmethod
    def report(state, settings):
        return Report(n_iter=int(state["basis"].shape[0]), warning=f"every: {settings['skip']}")
"""


def test_a_method_using_every_declaration_runs_as_declared(tmp_path):
    _module(tmp_path / "mine", "every_decl", EVERY_DECLARATION)
    logdir = tmp_path / "runs"
    found, proc = sweep_rows(
        *SMALL_ROUTE,
        "methods=[pca,every_decl:every]",
        "removed_pcs=[0,5]",
        "plugin.every.n=400",
        "plugin.every.skip=[0,2,500]",
        f"logdir={logdir}",
        path=[tmp_path / "mine"],
    )
    assert "note: every: n=400 capped to 244" in proc.stdout  # 249 held, less removed 5
    assert "note: every: skip=500 left out (n=400)" in proc.stdout
    rows = [r for r in found if r.method == "every"]
    cells = sorted((r.removed_pcs, r.setting) for r in rows)
    assert cells == [(k, f"skip={s}") for k in (0, 5) for s in (0, 2)]
    assert {r.n_iter for r in rows} == {244, 249} and all(r.seed == 0 for r in rows)
    assert "warning: summer-fall every skip=2 k=5: every: 2" in proc.stdout


def test_a_method_that_needs_alignment_is_refused_without_aligned_places(tmp_path, monkeypatch):
    _module(tmp_path, "aligned_only", CENTRED_PIXELS + "\ncentred_pixels.needs = ('aligned',)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    cfg = parse_config(["methods=[aligned_only:centred_pixels]", "plugin.centred_pixels.record=x"])
    (mine,) = resolve_methods(cfg, True, "synthetic", frozenset())
    assert mine.method.needs(None) == ("aligned",) and mine.name == "centred_pixels"
    with pytest.raises(UserError, match="needs 'aligned'.*data.source=vpr_bench.*train_source"):
        resolve_methods(cfg, False, "vpr_bench", frozenset())
    both = resolve_methods(parse_config(["methods=[raw,lda]"]), True, "synthetic", frozenset())
    assert [r.name for r in both] == ["raw", "lda"]


def test_adding_a_method_of_your_own_extends_a_logdir(tmp_path):
    logdir = tmp_path / "runs"
    logdir.mkdir()
    before = parse_config(["methods=[raw,a.b:first]", "plugin.first.alpha=1", f"logdir={logdir}"])
    (logdir / "config.yaml").write_text(config_yaml(before))
    check_same_config(logdir, before, _identities(before))
    added = ["methods=[raw,a.b:first,c.d:second]", "plugin.second.beta=2", f"logdir={logdir}"]
    now = parse_config([*added, "plugin.first.alpha=1"])
    check_same_config(logdir, now, _identities(now))
    with pytest.raises(UserError, match=r"differs in plugin\.first"):
        other = parse_config([*added, "plugin.first.alpha=2"])
        check_same_config(logdir, other, _identities(other))


def _identities(cfg):
    """The methods' identities as the plan compares them: a user's method imported only
    where the command (``cfg``) names it."""
    return lambda config: settings_identities(config, tuple(cfg.methods))
