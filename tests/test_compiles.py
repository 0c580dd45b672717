"""Everything compiles once per shape: no recompilation across season pairs, epochs, removed-PC
counts or blocks (counted with jax.log_compiles in a fresh process)."""

import json
import sys

import pytest

from tests.conftest import REPO, SMALL, run_process

BASE = [k for k in SMALL if not k.startswith(("removed_pcs", "train.epochs", "fae.epochs"))]
# Four database blocks and a padded last query block (60 test places per season).
BASE += ["ica.n_components=16", "matching.block_size=16"]


def _sweep(*overrides: str) -> str:
    return " ".join([*BASE, *overrides])


@pytest.fixture(scope="module")
def compiled(tmp_path_factory):
    """What each of three sweeps in one process compiled."""
    logdir = tmp_path_factory.mktemp("compiles")
    sweeps = [
        _sweep("season_pairs=summer-fall", "removed_pcs=[0,5]", "train.epochs=2"),
        _sweep("season_pairs=spring-fall", "removed_pcs=[0,5]", "train.epochs=2"),
        _sweep("season_pairs=spring-fall", "removed_pcs=[0,5,10,20]", "train.epochs=3"),
    ]
    proc = run_process(
        [sys.executable, str(REPO / "tests" / "count_compiles.py"), str(logdir), *sweeps]
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_the_first_sweep_compiles_the_training_step_once_per_model(compiled):
    first = compiled[0]
    steps = [c for c in first if c.startswith("jit(train_step)")]
    assert len(steps) == 4, steps  # the FAE's and the CAE's for each objective, both epochs
    # One batch gather for images, one for the places' pairs: the same for every model.
    assert sum(c.startswith("jit(take_batch)") for c in first) == 2
    assert sum(c.startswith("jit(whitening_matrix)") for c in first) == 1  # both counts


def test_a_second_season_pair_compiles_nothing(compiled):
    assert compiled[1] == []


def test_more_epochs_and_removed_pc_counts_compile_only_the_new_suffix_matchers(compiled):
    # The removed-PC counts are a static tuple of the suffix matcher (one pass scores every
    # count), so a new set of counts compiles it once for PCA's descriptors and once for
    # diff_pca's, each for the test and for the validation places; their fits (PCA fits the
    # same leading components: lda's 200 outnumber the counts), ICA's new counts, the
    # auto-encoders' extra epochs and all their blocks compile nothing.
    names = [c.split(" | ")[0] for c in compiled[2]]
    assert names == ["jit(_top_k_unpadded)"] * 4, compiled[2]
