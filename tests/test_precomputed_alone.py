"""Outside descriptors scored alone (``methods=[precomputed]``): numpy's recall@1 for
numpy-made descriptors, the paired differences to the first set, and the sets that cannot
be scored refused in one line before anything is written (different widths, every row zero
or constant) or scored with a warning naming their all-zero rows, never NaN."""

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import assert_one_line_error, run_here, shared_folder
from tests.inputs import N_PLACES, read_grey, write_vpr_bench
from vpr_jax.data.synthetic import synthetic_route

VAL_FRACTION = 0.1  # split.val_fraction's default: the last queries validate


def _make(folder: Path) -> None:
    route = synthetic_route(N_PLACES, ("summer", "fall"), seed=5)
    refs, queries, rows = write_vpr_bench(folder / "bench", route)
    db = np.stack([read_grey(folder / "bench" / "ref" / r) for r in refs]).reshape(len(refs), -1)
    q = np.stack([read_grey(folder / "bench" / "query" / n) for n in queries])
    q = q.reshape(len(queries), -1)
    mean = db.mean(axis=0)
    sets = {
        "centred": (db - mean, q - mean),
        "narrow": (db - mean, (q - mean)[:, :32]),
        "zeros": (np.zeros_like(db), q),
        "constant": (np.ones_like(db), q),
        "holes": (np.where(np.isin(np.arange(len(db)), [3, 7])[:, None], 0.0, db - mean), q - mean),
    }
    for name, (a, b) in sets.items():
        np.save(folder / f"{name}_db.npy", a.astype(np.float32))
        np.save(folder / f"{name}_q.npy", b.astype(np.float32))
    np.save(folder / "truth.npy", np.array([sorted(near) for _, near in rows], dtype=object))


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    return shared_folder(tmp_path_factory, "outside_alone", _make)


def _sweep(folder: Path, logdir: Path, *sets: tuple[str, str]):
    args = ["data.source=vpr_bench", f"data.root={folder / 'bench'}", "methods=[precomputed]"]
    for name, files in sets:
        args += [
            f"precomputed.{name}.database={folder / f'{files}_db.npy'}",
            f"precomputed.{name}.queries={folder / f'{files}_q.npy'}",
        ]
    return run_here(*args, f"logdir={logdir}")


def _numpy_recall_at_1(folder: Path, files: str) -> float:
    """The oracle: cosine by numpy, each test query's best database image checked against
    the ground truth the benchmark folder was written with."""
    db, q = np.load(folder / f"{files}_db.npy"), np.load(folder / f"{files}_q.npy")
    truth = np.load(folder / "truth.npy", allow_pickle=True)
    n_test = len(q) - max(1, round(VAL_FRACTION * len(q)))
    unit = lambda x: x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)  # noqa: E731
    best = np.argmax(unit(q[:n_test]) @ unit(db).T, axis=1)
    return float(np.mean([b in truth[i] for i, b in enumerate(best)]))


def test_outside_sets_alone_give_numpys_recall_and_differences_to_the_first(folder, tmp_path):
    proc = _sweep(folder, tmp_path / "runs", ("mine", "centred"), ("theirs", "holes"))
    assert proc.returncode == 0, proc.stderr
    with open(tmp_path / "runs" / "results.csv", newline="") as f:
        rows = {r["method"]: r for r in csv.DictReader(f)}
    assert set(rows) == {"mine", "theirs"}
    assert float(rows["mine"]["recall_at_1"]) == pytest.approx(
        _numpy_recall_at_1(folder, "centred"), abs=1e-12
    )
    assert float(rows["theirs"]["recall_at_1"]) == pytest.approx(
        _numpy_recall_at_1(folder, "holes"), abs=1e-12
    )
    for row in rows.values():  # every metric a number: the all-zero rows score 0, not NaN
        assert all(math.isfinite(float(row[m])) for m in ("recall_at_1", "auc_pr", "val_margin"))
    results = (tmp_path / "runs" / "results.md").read_text()
    assert "recall@1 - mine [95% CI]" in results and "vs mine: a paired bootstrap" in results
    # The set with all-zero rows is scored, with a warning that names them.
    warning = next(line for line in proc.stdout.splitlines() if line.startswith("warning:"))
    assert "theirs" in warning and "2 database rows" in warning and "ref/r" in warning


@pytest.mark.parametrize(
    "files, words",
    [
        ("narrow", ["has 2,048 columns", "has 32", "same width", "narrow_q.npy"]),
        ("zeros", ["zeros_db.npy", "every row is zero"]),
        ("constant", ["constant_db.npy", "points the same way"]),
    ],
)
def test_sets_that_cannot_be_scored_are_refused_before_anything_is_written(
    folder, tmp_path, files, words
):
    logdir = tmp_path / "runs"
    proc = _sweep(folder, logdir, (files, files))
    assert_one_line_error(proc, *words)
    assert not logdir.exists()
