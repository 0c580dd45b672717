"""Any setting given as a list is a sweep axis, chosen on the validation places, and
``seeds`` repeats every method that draws random numbers: one small sweep with
``ica.n_components=[16,32]``, a user's method with a setting one fit serves and one that
needs a fit per value, and ``seeds=[0,1]``, read back as a user reads it."""

import json
import shutil
import textwrap
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import (
    SMALL_ROUTE,
    TINY_MODELS,
    TINY_ROUTE,
    read_run,
    shared_folder,
    shared_sweep,
    sweep_rows,
)
from vpr_jax import load_encoder
from vpr_jax.outputs.results import read_results

# A user's method: a PCA projection of n_components directions (a fit per value) starting
# ``skip`` directions in (one fit serves every value: ``axes``); it draws no random
# numbers, so it fits once whatever the seeds. Each fit appends its settings to ``record``.
PROJECTION = """
import json

import jax.numpy as jnp


class projection:
    axes = {"skip": "served"}
    random = False

    @staticmethod
    def fit(train, aligned, key, record, n_components=4):
        with open(record, "a") as f:
            f.write(json.dumps({"n_components": n_components, "n": len(train)}) + "\\n")
        x = jnp.reshape(train, (len(train), -1))
        mean = x.mean(axis=0)
        _, _, vt = jnp.linalg.svd(x - mean, full_matrices=False)
        return {"mean": mean, "components": vt[: n_components + 8]}

    @staticmethod
    def encode(state, images, skip=0):
        n = state["components"].shape[0] - 8
        x = jnp.reshape(images, (images.shape[0], -1)) - state["mean"]
        return x @ state["components"][skip : skip + n].T
"""


def _write_module(folder: Path) -> None:
    (folder / "mine").mkdir()
    (folder / "mine" / "my_methods.py").write_text(textwrap.dedent(PROJECTION))


@pytest.fixture(scope="session")
def axes(tmp_path_factory):
    """(logdir, args, the module's folder, fit record, process) of one sweep per session
    (read-only for every test)."""
    folder = shared_folder(tmp_path_factory, "axes_module", _write_module)
    record = folder / "fits.jsonl"
    args = [
        *SMALL_ROUTE,
        "season_pairs=summer-fall",
        "removed_pcs=[0,5]",
        "methods=[raw,pca,ica,my_methods:projection]",
        "ica.n_components=[16,32]",
        "ica.max_iter=50",
        "plugin.projection.n_components=[4,8]",
        "plugin.projection.skip=[0,2]",
        f"plugin.projection.record={record}",
        "seeds=[0,1]",
        f"train.checkpoint_dir={folder / 'checkpoints'}",
    ]
    logdir, proc = shared_sweep(tmp_path_factory, "axes_sweep", *args, path=[folder / "mine"])
    return logdir, args, folder / "mine", record, proc


def _group(rows, method):
    return [r for r in rows if r.method == method]


def test_every_value_of_a_list_is_a_cell_and_validation_chooses(axes):
    logdir, *_ = axes
    rows = read_results(logdir / "results.csv")
    ica = _group(rows, "ica")
    assert {(r.setting, r.removed_pcs, r.seed) for r in ica} == {
        (f"n_components={n}", k, s) for n in (16, 32) for k in (0, 5) for s in (0, 1)
    }
    for method in ("ica", "projection", "pca"):
        mine = _group(rows, method)
        means = {}  # each setting and count: its validation recall@1, mean over its seeds
        for r in mine:
            means.setdefault((r.setting, r.removed_pcs), []).append(r.val_recall_at_1)
        best = max(np.mean(v) for v in means.values())
        chosen = {(r.setting, r.removed_pcs) for r in mine if r.selected}
        assert len(chosen) == 1 and np.mean(means[chosen.pop()]) == best, method
        selected = [r for r in mine if r.selected]  # every seed's row of the chosen setting
        assert len(selected) == len({r.seed for r in mine})
    # The TensorBoard compare view: removed PCs as the step, each value a run of its own.
    for n in (16, 32):
        run = read_run(logdir / "compare" / f"ica_n_components={n}")
        (group,) = {t.split("/")[1] for t in run.Tags()["scalars"] if t.startswith("summer-fall/")}
        assert group.startswith("linear"), group  # its family's chart group
        points = run.Scalars(f"summer-fall/{group}/recall_at_1")
        assert [p.step for p in points] == [0, 5]
    assert "| ica |  | n_components=" in (logdir / "results.md").read_text()


def test_a_setting_one_fit_serves_is_fitted_once_and_scored_per_value(axes):
    logdir, _, _, record, _ = axes
    fits = [json.loads(line) for line in record.read_text().splitlines()]
    # A fit per value, not per skip (the resume test below may add one of n_components=6).
    assert sorted(f["n_components"] for f in fits if f["n_components"] != 6) == [4, 8]
    rows = _group(read_results(logdir / "results.csv"), "projection")
    assert {r.setting for r in rows} == {
        f"n_components={n} skip={s}" for n in (4, 8) for s in (0, 2)
    }
    assert {r.seed for r in rows} == {0}  # it declares random = False: no fit per seed
    assert {r.run for r in rows} >= {"summer-fall/projection_n_components=4_skip=2"}


def test_seeds_repeat_what_draws_random_numbers_and_results_md_shows_their_spread(axes):
    logdir, *_ = axes
    rows = read_results(logdir / "results.csv")
    assert {r.seed for r in _group(rows, "raw") + _group(rows, "pca")} == {0}
    assert {r.seed for r in _group(rows, "ica")} == {0, 1}
    assert (logdir / "summer-fall" / "ica_n_components=16_seed1_k005").is_dir()
    text = (logdir / "results.md").read_text()
    seeds = text.split("## Seeds", 1)[1].split("##", 1)[0]
    (line,) = [ln for ln in seeds.splitlines() if ln.startswith("| summer-fall | ica |")]
    chosen = [r for r in _group(rows, "ica") if r.selected]
    assert f"| {np.mean([r.recall_at_1 for r in chosen]):.3f} |" in line
    low, high = sorted(r.recall_at_1 for r in chosen)
    assert f"{low:.3f}-{high:.3f}" in line and line.count("(") == 2  # a difference per seed


def test_a_method_s_name_loads_the_fit_validation_chose(axes):
    logdir, *_ = axes
    pair = logdir.parent.parent / "axes_module" / "checkpoints" / "runs" / "summer-fall"
    (chosen,) = [
        r
        for r in read_results(logdir / "results.csv")
        if r.method == "ica" and r.selected and r.seed == 0
    ]
    encode, params = load_encoder(pair / "ica")
    _, direct = load_encoder(pair / chosen.run.split("/", 1)[1])
    np.testing.assert_array_equal(params.unmixing, direct.unmixing)
    images = np.random.default_rng(0).random((3, 32, 64), np.float32)
    assert encode(params, images).shape == (3, int(chosen.setting.split("=")[1]))


def test_a_value_added_to_a_list_adds_only_its_cells(axes, tmp_path):
    logdir, args, mine, _, _ = axes
    copy = shutil.copytree(logdir, tmp_path / "runs")
    checkpoints = logdir.parent.parent / "axes_module" / "checkpoints"
    shutil.copytree(checkpoints, tmp_path / "checkpoints")
    more = [a.replace("[4,8]", "[4,8,6]") for a in args]
    more = [a for a in more if "checkpoint_dir" not in a]
    rows, proc = sweep_rows(*more, f"logdir={copy}", path=[mine])
    before, after = len(read_results(logdir / "results.csv")), len(rows)
    assert after - before == 2  # n_components=6 at skip 0 and 2
    assert f"resuming: {before} of {after} cells" in proc.stdout


def test_training_settings_and_inputs_are_axes_and_the_baseline_a_key(tmp_path):
    """Every setting of a trained method is an ordinary axis (a model per value, the
    runner's validation rule chooses), the residual input among them; ``baseline`` names
    what results.md's paired differences are to."""
    logdir = tmp_path / "runs"
    rows, _ = sweep_rows(
        *TINY_ROUTE,
        "season_pairs=summer-fall",
        "methods=[raw,lda,fae,cae]",
        "fae.learning_rate=[0.001,0.0001]",
        "fae.objective=cross_season",
        "cae.input=[standardised,residual]",
        "cae.objective=reconstruct",
        *TINY_MODELS,
        "train.epochs=1",
        "fae.epochs=1",
        "baseline=lda",
        f"logdir={logdir}",
    )
    fae = [r for r in rows if r.method == "fae"]
    assert sorted(r.setting for r in fae) == ["learning_rate=0.0001", "learning_rate=0.001"]
    cae = [r for r in rows if r.method == "cae"]
    assert sorted(r.setting for r in cae) == ["input=residual", "input=standardised"]
    for mine in (fae, cae):
        (chosen,) = [r for r in mine if r.selected]
        best = max((r.val_recall_at_1, r.val_margin) for r in mine)
        assert (chosen.val_recall_at_1, chosen.val_margin) == best
    text = (logdir / "results.md").read_text()
    assert "recall@1 - LDA" in text and "| summer-fall | lda |" in text
    headline = text.split("## ")[1]  # each method at its validation-chosen setting
    (lda_line,) = [ln for ln in headline.splitlines() if ln.startswith("| summer-fall | lda |")]
    assert lda_line.rstrip().endswith("| baseline |")


def test_a_setting_of_the_shared_pca_fit_is_an_axis_with_a_fit_per_value(tmp_path):
    """``pca.solver=[covariance,gram]``: pca's cells get a shared fit per value (and, PCA
    being PCA whatever solves it, the same numbers); ica takes the first value's fit."""
    logdir = tmp_path / "runs"
    rows, _ = sweep_rows(
        *TINY_ROUTE,
        "season_pairs=summer-fall",
        "methods=[pca,ica]",
        "pca.solver=[covariance,gram]",
        "removed_pcs=[0,5]",
        "ica.n_components=8",
        f"logdir={logdir}",
    )
    pca = {(r.setting, r.removed_pcs): r for r in rows if r.method == "pca"}
    assert set(pca) == {(f"solver={s}", k) for s in ("covariance", "gram") for k in (0, 5)}
    for k in (0, 5):
        a, b = pca[("solver=covariance", k)], pca[("solver=gram", k)]
        assert a.recall_at_1 == b.recall_at_1 and a.auc_pr == pytest.approx(b.auc_pr, abs=1e-6)
    assert {r.setting for r in rows if r.method == "ica"} == {""}
