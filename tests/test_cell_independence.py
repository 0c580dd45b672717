"""A cell is its own: a method's numbers do not depend on which other methods share the
sweep. The pair's shared PCA fit once held as many components as its most demanding user
asked for (lda's 200 against pca's 50 here) and was solved differently for each count, so
pca's rows and the residual-input FAE's training inputs moved when lda or ica joined.

The same sweep runs with ``methods=[pca,fae]`` and with ``[pca,lda,fae]``; pca's and
the FAE's rows must agree in every column but the timings, and their saved states (pca's
components, the FAE's weights, trained on the images less PCA's leading components) to the
last bit."""

import csv
from pathlib import Path

import jax
import numpy as np
import pytest

from tests.conftest import TINY_ROUTE, run_here
from vpr_jax import load_encoder
from vpr_jax.outputs.results import TIMING_NAMES

SWEEP = (
    *TINY_ROUTE,
    "season_pairs=summer-fall",
    "removed_pcs=[0,5,50]",
    "fae.hidden=32",
    "fae.input=residual",
    "fae.objective=[cross_season]",
    "fae.epochs=1",
    "train.epochs=1",
)
MINE = ("pca", "fae")


def _sweep(root: Path, methods: str) -> Path:
    logdir = root / methods.strip("[]").replace(",", "_")
    proc = run_here(*SWEEP, f"methods={methods}", f"logdir={logdir}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    return logdir


def _rows(logdir: Path) -> dict[str, dict]:
    with open(logdir / "results.csv", newline="") as f:
        return {
            r["run"]: {k: v for k, v in r.items() if k not in TIMING_NAMES}
            for r in csv.DictReader(f)
            if r["method"] in MINE
        }


@pytest.mark.timeout(240)
def test_a_methods_rows_and_states_do_not_depend_on_its_neighbours(tmp_path):
    alone = _sweep(tmp_path, "[pca,fae]")
    beside = _sweep(tmp_path, "[pca,lda,fae]")
    rows_alone, rows_beside = _rows(alone), _rows(beside)
    assert {r["method"] for r in rows_alone.values()} == set(MINE)
    assert rows_alone == rows_beside
    for model in ("pca", "fae_cross_season"):
        _, params_alone = load_encoder(
            tmp_path / "checkpoints" / alone.name / "summer-fall" / model
        )
        _, params_beside = load_encoder(
            tmp_path / "checkpoints" / beside.name / "summer-fall" / model
        )
        leaves_alone, leaves_beside = _leaves(params_alone), _leaves(params_beside)
        assert leaves_alone.keys() == leaves_beside.keys() and leaves_alone
        for name, a in leaves_alone.items():
            np.testing.assert_array_equal(a, leaves_beside[name], err_msg=f"{model}{name}")


def _leaves(params) -> dict[str, np.ndarray]:
    """A saved state's arrays by path, less its timings (``train_seconds``)."""
    return {
        jax.tree_util.keystr(path): np.asarray(leaf)
        for path, leaf in jax.tree_util.tree_leaves_with_path(params)
        if "seconds" not in jax.tree_util.keystr(path)
    }


@pytest.mark.timeout(120)
def test_pca_without_removal_still_gets_its_fit(tmp_path):
    """``removed_pcs=[0]``: PCA's one cell is the image less its training mean, so it needs
    the fit though it removes no component (it once got none, and crashed)."""
    proc = run_here(
        *TINY_ROUTE,
        "season_pairs=summer-fall",
        "removed_pcs=[0]",
        "methods=[pca]",
        f"logdir={tmp_path / 'runs'}",
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    with open(tmp_path / "runs" / "results.csv", newline="") as f:
        assert [(r["method"], r["removed_pcs"]) for r in csv.DictReader(f)] == [("pca", "0")]
