"""Sequence matching and patch normalisation through the CLI: every method x every ds, read
back from results.csv and with TensorBoard's reader; a sweep extended by a longer ds
computes only the new cells; patch normalisation makes the whole sweep blind to the query
season's brightness."""

import shutil
from pathlib import Path

import numpy as np
import pytest
from tensorboard.plugins.hparams import plugin_data_pb2

from tests.conftest import read_run, run_here, shared_folder, shared_sweep, sweep_rows
from tests.inputs import write_release
from vpr_jax.data.synthetic import synthetic_route
from vpr_jax.evaluation.metrics import SCALAR_NAMES
from vpr_jax.outputs.results import read_results

METRICS = SCALAR_NAMES
ARGS = [
    "data.source=nordland_images",
    "split.n_train=200",
    "split.gap=10",
    "split.n_test=200",
    "data.seasons=[summer,fall]",
    "season_pairs=summer-fall",
    "methods=[raw,pca]",
    "removed_pcs=[0,5]",
    "preprocess=patchnorm",
    "sequence.enabled=true",
    "sequence.ds=[1,10]",
]
BRIGHTER = 40  # grey levels added to every query (fall) image


def _write_releases(folder: Path) -> None:
    """The same two seasons as 64x32 PNG releases, ``base/`` and ``brighter/`` (its fall
    brighter by BRIGHTER grey levels)."""
    route = synthetic_route(420, ("summer", "fall"), seed=5)
    base = {s: np.rint(im * 200).astype(np.uint8) for s, im in route.images.items()}
    for name, shift in (("base", 0), ("brighter", BRIGHTER)):
        shifted = {
            s: frames + np.uint8(shift if s == "fall" else 0)  # <= 240: no clip
            for s, frames in base.items()
        }
        write_release(folder / name, shifted)


@pytest.fixture(scope="module")
def releases(tmp_path_factory):
    folder = shared_folder(tmp_path_factory, "sequence_releases", _write_releases)
    return {name: folder / name for name in ("base", "brighter")}


def _sweep(root, logdir, *extra):
    return sweep_rows(*ARGS, f"data.root={root}", f"logdir={logdir}", *extra)


@pytest.fixture(scope="module")
def base_sweep(releases, tmp_path_factory):
    args = (*ARGS, f"data.root={releases['base']}")
    logdir, proc = shared_sweep(tmp_path_factory, "sequence_base_sweep", *args)
    return logdir, read_results(logdir / "results.csv"), proc


def test_every_method_runs_at_every_ds_and_sequences_help(base_sweep):
    logdir, rows, proc = base_sweep
    assert "patch normalisation, 8x8 patches" in proc.stdout
    cells = {(r.method, r.removed_pcs, r.ds): r for r in rows}
    assert set(cells) == {
        (m, k, ds) for m, k in (("raw", 0), ("pca", 0), ("pca", 5)) for ds in (1, 10)
    }
    for (method, k, ds), row in cells.items():
        if ds == 10:  # on a route, sequences of 10 beat single images for every method
            assert row.recall_at_1 > cells[(method, k, 1)].recall_at_1, (method, k)
        name = f"summer-fall/{method}_k{k:03d}" if method == "pca" else f"summer-fall/{method}"
        assert row.run == (name if ds == 1 else f"{name}_ds10")
        ea = read_run(logdir / row.run)
        (recall,) = ea.Scalars("metrics/recall_at_1")
        assert recall.value == pytest.approx(row.recall_at_1, abs=1e-6)
        info = plugin_data_pb2.HParamsPluginData.FromString(
            ea.PluginTagToContent("hparams")["_hparams_/session_start_info"]
        ).session_start_info
        assert info.hparams["ds"].number_value == ds
    assert (logdir / "figures" / "recall_vs_ds.png").stat().st_size > 0
    assert "| ds |" in (logdir / "results.md").read_text()


def test_patch_normalisation_makes_results_blind_to_query_brightness(
    releases, base_sweep, tmp_path
):
    _, base_rows, _ = base_sweep
    rows, _ = _sweep(releases["brighter"], tmp_path / "runs")
    assert len(rows) == len(base_rows)
    for row, base in zip(rows, base_rows, strict=True):
        assert row.run == base.run
        for key in METRICS:
            assert getattr(row, key) == pytest.approx(getattr(base, key), abs=1e-4), (row.run, key)


def test_a_longer_ds_extends_a_finished_sweep(releases, base_sweep, tmp_path):
    logdir, rows, _ = base_sweep
    extended = tmp_path / "runs"
    shutil.copytree(logdir, extended)
    new_rows, proc = _sweep(releases["base"], extended, "sequence.ds=[1,5,10]")
    assert "resuming: 6 of 9 cells already in results.csv" in proc.stdout
    assert new_rows[:6] == rows  # untouched, in order
    assert {(r.run, r.ds) for r in new_rows[6:]} == {
        ("summer-fall/raw_ds05", 5),
        ("summer-fall/pca_k000_ds05", 5),
        ("summer-fall/pca_k005_ds05", 5),
    }


def test_sequence_lengths_without_enabling_them_are_pointed_out(tmp_path):
    """A ds list while sequence matching is off would be silently single images: the run
    log says so (here, before the missing data folder stops the run)."""
    proc = run_here(
        "data.source=nordland_images",
        f"data.root={tmp_path / 'absent'}",
        "sequence.ds=[1,5]",
        f"logdir={tmp_path / 'runs'}",
    )
    assert proc.returncode == 2
    assert "sequence.ds=[1, 5] is ignored while sequence.enabled=false" in proc.stdout
