"""The recognition options end to end on the built-in route: residual input, the linear
start, the contrastive objective and ``train.augment=auto`` train and checkpoint in one
sweep, and the epoch and model kept are the ones the validation places' recall
chooses, the same recall the sweep reports for the cell. (Resuming and restoring such
models: tests/test_recognition_training.py and the sweep's rerun tests.)"""

import csv
from pathlib import Path

import pytest

from tests.conftest import read_run, shared_sweep
from vpr_jax.encoders import checkpoints
from vpr_jax.encoders.train import SELECT_RECALL
from vpr_jax.outputs.results import read_results

ARGS = [
    "data.n_frames=400",
    "split.n_train=200",
    "split.n_test=60",
    "split.gap=10",
    "season_pairs=summer-fall",
    "methods=[pca,fae,cae]",
    "removed_pcs=[0,5,10]",
    "fae.hidden=16",
    "fae.input=residual",
    "fae.init=whitened_pca",
    "fae.objective=contrastive",
    "cae.input=residual",
    "cae.objective=cross_season",
    "cae.channels=[4,8]",
    "cae.code_channels=2",
    "train.epochs=2",
    "fae.epochs=2",
    "train.augment=auto",
]
MODELS = {"fae": "fae_contrastive", "cae": "cae_cross_season"}


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    """(logdir, the finished sweep), run once per session (whichever worker asks first)."""
    return shared_sweep(tmp_path_factory, "recognition_sweep", *ARGS)


def _recall_curve(run_dir) -> list[float]:
    return [e.value for e in read_run(run_dir).Scalars("validation/recall_at_1")]


def test_the_kept_model_and_epoch_are_validation_recall_s_choice(sweep):
    """``train.augment=auto`` is the axis augment=[true,false]: a model and a row each, the
    runner's rule selects between them; each model keeps its epoch of best validation
    recall, the recall the sweep reports for its cell."""
    logdir, proc = sweep
    rows = read_results(logdir / "results.csv")
    with open(logdir / "encoders.csv") as f:
        folders = {(e["method"], e["setting"]): e["folder"] for e in csv.DictReader(f)}
    for method, model in MODELS.items():
        mine = [r for r in rows if r.method == method]
        assert sorted(r.setting for r in mine) == ["augment=False", "augment=True"]
        for row in mine:
            name = f"{model}_{row.setting}"
            curve = _recall_curve(logdir / "summer-fall" / f"{name}_training")
            assert len(curve) == 3  # epoch 0, then both epochs
            # The recall that chose the epoch is the recall the sweep reports for the cell.
            assert row.val_recall_at_1 == pytest.approx(max(curve), abs=1e-6)
            line = f"summer-fall {name}: input residual, 10 leading components"
            assert line in proc.stdout  # fae.residual_pcs' default
            folder = Path(folders[(method, row.setting)])
            assert folder.name == name  # the model's state, saved
            meta = checkpoints.read_meta(folder / "training")
            assert meta["done"] and meta["selected_by"] == SELECT_RECALL
            assert meta["best_epoch"] == curve.index(max(curve))
            assert meta["best_score"] == pytest.approx(max(curve), abs=1e-6)
        (chosen,) = [r for r in mine if r.selected]
        scores = [(r.val_recall_at_1, r.val_margin) for r in mine]
        assert (chosen.val_recall_at_1, chosen.val_margin) == max(scores)
