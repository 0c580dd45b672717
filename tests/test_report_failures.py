"""A report can never cost the results it reports: a figure that cannot be drawn or written
is skipped with one warning naming it, everything else is written, the exit code is 0, and
the same command run again completes what is missing. And seeds that tie draw a figure."""

import shutil

import cv2
import numpy as np

from tests.conftest import SMALL, run_here, sweep_rows
from vpr_jax.outputs.plots import correct_matches_figure
from vpr_jax.outputs.results import COLUMNS, ResultRow, read_results


def _seed_row(seed: int, recall: float) -> ResultRow:
    values = dict.fromkeys(COLUMNS, 0)
    values.update(
        season_pair="summer-fall",
        db_season="summer",
        query_season="fall",
        method="ica",
        objective="",
        setting="",
        ds=1,
        recall_at_1=recall,
        selected=1,
        seed=seed,
        run=f"summer-fall/ica_seed{seed}",
    )
    return ResultRow(**values)


def test_seeds_that_tie_draw_their_bar(tmp_path):
    """Three seeds of 0.7: their float mean is 0.7 less a rounding, which made the whisker
    above the bar negative and matplotlib refuse the figure."""
    assert np.mean([0.7] * 3) != 0.7
    path = tmp_path / "correct_matches.png"
    correct_matches_figure([_seed_row(s, 0.7) for s in range(3)], path)
    assert cv2.imread(str(path)) is not None


def test_a_figure_that_fails_leaves_the_rest_of_the_report_and_a_rerun_completes_it(
    small_sweep, tmp_path
):
    finished, _ = small_sweep
    logdir = shutil.copytree(finished, tmp_path / "runs")
    checkpoints = finished.parent / "checkpoints"
    for name in ("results.md", "encoders.csv"):
        (logdir / name).unlink()
    shutil.rmtree(logdir / "figures")
    # A folder where the figure goes: writing it fails, as a full or read-only disk would.
    (logdir / "figures" / "correct_matches.png" / "in_the_way").mkdir(parents=True)
    args = (*SMALL, f"logdir={logdir}", f"train.checkpoint_dir={checkpoints}")
    rows, proc = sweep_rows(*args)
    warnings = [ln for ln in proc.stdout.splitlines() if ln.startswith("warning: figures/")]
    assert len(warnings) == 1 and "figures/correct_matches.png not written" in warnings[0]
    assert "rerun the same command" in warnings[0]
    assert "done, but not written: figures/correct_matches.png" in proc.stdout
    assert "Traceback" in (logdir / "sweep.log").read_text()  # for whoever looks into it
    assert (logdir / "results.md").read_text().startswith("#")
    listing = (logdir / "encoders.csv").read_text().splitlines()
    assert len(listing) > 1
    assert cv2.imread(str(logdir / "figures" / "pr_curves.png")) is not None
    assert len(rows) == len(read_results(finished / "results.csv"))

    shutil.rmtree(logdir / "figures" / "correct_matches.png")
    proc = run_here(*args)
    assert proc.returncode == 0, proc.stderr
    assert "not written" not in proc.stdout
    assert cv2.imread(str(logdir / "figures" / "correct_matches.png")) is not None
