"""The runner end to end: a subprocess sweep, read back with TensorBoard's own reader."""

import csv
import re
import shutil

import cv2
import numpy as np
import pytest
from tensorboard.plugins.hparams import plugin_data_pb2
from tensorboard.util import tensor_util

from tests.conftest import SMALL, numpy_cosine, read_run, run_here, sweep_rows
from vpr_jax.outputs.results import COLUMNS, read_results

PAIRS = {"summer-spring", "summer-fall", "spring-fall"}


def test_results_table_has_one_row_per_cell(small_sweep):
    logdir, proc = small_sweep
    with open(logdir / "results.csv") as f:
        header = next(csv.reader(f))
    assert tuple(header) == COLUMNS
    rows = read_results(logdir / "results.csv")
    cells = {(r.season_pair, r.method, r.objective, r.removed_pcs) for r in rows}
    # raw, PCA, diff_pca and ICA at k = 0, 5, 20, LDA, FAE and CAE with both objectives
    assert len(rows) == len(cells) == 3 * (1 + 3 + 3 + 3 + 1 + 2 + 2)
    for r in rows:
        trained = r.method in ("fae", "cae")
        assert (r.objective in ("reconstruct", "cross_season")) if trained else r.objective == ""
    assert {r.season_pair for r in rows} == PAIRS
    for r in rows:
        assert r.db_season + "-" + r.query_season == r.season_pair
        # 150 places per season: 15 validate, 10 are the gap before them, 125 train
        assert r.n_train == 250 and r.n_test == 60 and r.tolerance == 2
        assert 0.0 <= r.val_recall_at_1 <= 1.0
        assert r.recall_at_1_ci_low <= r.recall_at_1 <= r.recall_at_1_ci_high
        assert r.auc_pr_ci_low <= r.auc_pr <= r.auc_pr_ci_high
        for key in ("recall_at_1", "auc_pr", "recall_at_100_precision", "recall_at_10"):
            assert 0.0 <= getattr(r, key) <= 1.0
        # Every query has a true match, so the PR curve reaches full recall at precision R@1.
        assert r.precision_at_full_recall == pytest.approx(r.recall_at_1)
        assert r.recall_at_1 <= r.recall_at_5 <= r.recall_at_10
        if r.method == "ica":
            assert 1 <= r.n_iter <= 200 and r.converged == (r.n_iter < 200)
            assert r.stopped_early == 0
        elif r.method in ("fae", "cae"):
            assert r.n_iter == 2 and r.stopped_early == 0  # 2 epochs, no early stop
            assert r.converged == 1  # not an iterative fit with a tolerance
        else:
            assert r.n_iter == 0 and r.converged == 1 and r.stopped_early == 0
    # Exactly one selected row per pair x method x objective (x ds): the best on validation.
    groups = {(r.season_pair, r.method, r.objective, r.ds) for r in rows}
    chosen = [r for r in rows if r.selected]
    assert (
        len(chosen) == len(groups)
        and {(r.season_pair, r.method, r.objective, r.ds) for r in chosen} == groups
    )
    for r in chosen:
        rivals = [
            o
            for o in rows
            if (o.season_pair, o.method, o.objective, o.ds)
            == (r.season_pair, r.method, r.objective, r.ds)
        ]
        best = max((o.val_recall_at_1, o.val_auc_pr) for o in rivals)
        assert (r.val_recall_at_1, r.val_auc_pr) == best
    # One plain line per finished cell, whatever the terminal.
    assert proc.stdout.count(": recall@1") == len(rows)


def test_tensorboard_reads_back_scalars_pr_curves_images_hparams(small_sweep):
    logdir, _ = small_sweep
    rows = read_results(logdir / "results.csv")
    for row in rows:
        ea = read_run(logdir / row.run)
        tags = ea.Tags()
        for key in ("recall_at_1", "auc_pr", "recall_at_100_precision", "recall_at_5"):
            (event,) = ea.Scalars(f"metrics/{key}")
            assert event.value == pytest.approx(getattr(row, key), abs=1e-6)
        (fit,) = ea.Scalars("timing/fit_seconds")
        assert fit.value == pytest.approx(row.fit_seconds, rel=1e-5)
        (pr,) = ea.Tensors("pr_curve")
        data = tensor_util.make_ndarray(pr.tensor_proto)
        assert data.shape == (6, 201)
        tp, fp, tn, fn = data[:4, 0]  # threshold 0 accepts every query
        assert tp / (tp + fp) == pytest.approx(row.recall_at_1, abs=1e-6)
        assert "matches/query_best_true" in tags["images"]
        for key in ("n_iter", "converged", "stopped_early"):
            (event,) = ea.Scalars(f"fit/{key}")
            assert event.value == getattr(row, key)
        has_removed = "basis/removed_components" in tags["images"]
        assert has_removed == (row.method == "pca" and row.removed_pcs > 0)
        has_changes = "basis/removed_changes" in tags["images"]
        assert has_changes == (row.method == "diff_pca" and row.removed_pcs > 0)
        has_ics = "basis/independent_components" in tags["images"]
        assert has_ics == (row.method == "ica")
        assert ("basis/invariant_directions" in tags["images"]) == (row.method == "lda")
        assert ("basis/hidden_units" in tags["images"]) == (row.method == "fae")
        if has_ics:  # the first 8 mixing columns as 32x64 tiles in a 2 x 4 grid
            (image,) = ea.Images("basis/independent_components")
            assert (image.height, image.width) == (2 * 32 + 1, 4 * 64 + 3)
        content = ea.PluginTagToContent("hparams")
        info = plugin_data_pb2.HParamsPluginData.FromString(
            content["_hparams_/session_start_info"]
        ).session_start_info
        assert info.hparams["season_pair"].string_value == row.season_pair
        assert info.hparams["objective"].string_value == row.objective
        assert info.hparams["removed_pcs"].number_value == row.removed_pcs
        assert info.hparams["ds"].number_value == row.ds == 1
    root = read_run(logdir)
    experiment = plugin_data_pb2.HParamsPluginData.FromString(
        root.PluginTagToContent("hparams")["_hparams_/experiment"]
    ).experiment
    assert {h.name for h in experiment.hparam_infos} == {
        "season_pair",
        "method",
        "objective",
        "setting",
        "removed_pcs",
        "ds",
        "seed",
    }
    assert "metrics/recall_at_1" in {m.name.tag for m in experiment.metric_infos}


def test_autoencoder_training_is_logged_and_checkpointed(small_sweep):
    logdir, proc = small_sweep
    for pair in PAIRS:
        for method in ("fae", "cae", "fae_cross_season", "cae_cross_season"):
            ea = read_run(logdir / pair / f"{method}_training")
            steps = [e.step for e in ea.Scalars("loss/train")]
            assert steps == list(range(1, len(steps) + 1)) and len(steps) >= 2
            # The starting weights, then every epoch: the loss and the recall that selects.
            assert len(ea.Scalars("loss/validation")) == 3
            assert len(ea.Scalars("validation/recall_at_1")) == 3
            images = ea.Tags()["images"]
            assert "reconstructions/validation" in images and "inputs/augmented" in images
            # Rows of six: inputs over outputs; for cross_season both seasons' inputs, their
            # mean (the target), then the output for each season.
            shown = ea.Images("reconstructions/validation")[-1]
            rows = 5 if method.endswith("cross_season") else 2
            assert (shown.height, shown.width) == (rows * 33 - 1, 6 * 65 - 1)
            folder = logdir.parent / "checkpoints" / logdir.name / pair / method / "training"
            saved = sorted(p.name for p in folder.iterdir() if p.name.isdigit())
            assert saved[-1] == "2" and set(saved) <= {"1", "2"}  # the last epoch, always
    assert proc.stdout.count("validation loss") == 3 * 4 * 3  # per model: the start, 2 epochs


def test_summaries_and_figures_are_written(small_sweep):
    logdir, proc = small_sweep
    table = (logdir / "results.md").read_text()
    assert all(pair in table for pair in PAIRS)
    sections = [line for line in table.splitlines() if line.startswith("## ")]
    assert sections[0].startswith("## Each method at the setting chosen on the validation")
    # the small sweep trains auto-encoders: what training added to each start comes next
    assert sections[1] == "## Trained against their start"
    assert "optimistic" in sections[2]
    headline = table.split(sections[0])[1].split(sections[1])[0]
    labels = [
        line.split("|")[-2].strip()
        for line in headline.splitlines()
        if line.startswith("| ") and "season_pair" not in line
    ]
    assert len(labels) == 3 * 9  # a selected row per pair, method and objective
    assert labels.count("baseline") == 3
    assert set(labels) <= {"baseline", "better", "worse", "no clear difference"}
    for name in ("pr_curves.png", "correct_matches.png"):
        image = cv2.imread(str(logdir / "figures" / name))
        assert image is not None and image.shape[0] > 100
    assert "recall@1" in (logdir / "sweep.log").read_text()
    assert "tensorboard --logdir" in proc.stdout


def test_rerun_skips_finished_cells_and_recomputes_lost_ones(small_sweep, tmp_path):
    finished, _ = small_sweep
    logdir = tmp_path / "runs"
    shutil.copytree(finished, logdir)
    rows = read_results(logdir / "results.csv")
    # Simulate a crash after PCA and ICA runs were written but before their rows were.
    spring_fall = [r for r in rows if r.season_pair == "spring-fall"]
    lost = [r for r in spring_fall if r.method == "pca"][:2] + [
        r for r in spring_fall if r.method in ("ica", "fae")
    ][-2:]
    kept = [r for r in rows if r not in lost]
    lines = (logdir / "results.csv").read_text().splitlines()
    keep_runs = {r.run for r in kept}
    (logdir / "results.csv").write_text(
        "\n".join([lines[0]] + [ln for ln in lines[1:] if ln.split(",")[-1] in keep_runs]) + "\n"
    )
    # The models trained by the first run are restored, not retrained (a copy of them: the
    # shared sweep's worker holds their folders' locks; both logdirs are "runs").
    checkpoints = shutil.copytree(finished.parent / "checkpoints", tmp_path / "checkpoints")
    again, proc = sweep_rows(*SMALL, f"logdir={logdir}", f"train.checkpoint_dir={checkpoints}")
    assert f"resuming: {len(kept)} of {len(rows)}" in proc.stdout
    assert "spring-fall fae: restored the trained model" in proc.stdout
    assert "validation loss" not in proc.stdout
    assert proc.stdout.count(": recall@1") == len(lost)
    assert len(again) == len(rows)
    metric = ("recall_at_1", "auc_pr", "recall_at_100_precision", "recall_at_10")
    by_run = {r.run: r for r in again}
    for r in rows:  # recomputed cells give the same numbers: deterministic
        redone = by_run[r.run]
        assert all(getattr(redone, m) == pytest.approx(getattr(r, m), abs=1e-6) for m in metric)
    # The recomputed runs hold one event file each: the stale ones were replaced.
    for r in lost:
        assert len(list((logdir / r.run).glob("events.out.tfevents.*"))) == 1
    # A finished sweep run again computes nothing.
    proc = run_here(*SMALL, f"logdir={logdir}")
    assert proc.returncode == 0 and proc.stdout.count(": recall@1") == 0


def test_named_pairs_select_database_and_query_seasons(tmp_path):
    (row,), _ = sweep_rows(*SMALL, "season_pairs=fall-summer", "methods=raw", f"logdir={tmp_path}")
    assert (row.db_season, row.query_season) == ("fall", "summer")


def test_pixel_output_gives_the_same_metrics(small_sweep, tmp_path):
    logdir, _ = small_sweep
    rows, _ = sweep_rows(
        *SMALL, "season_pairs=summer-fall", "methods=pca", "pca.output=pixels", f"logdir={tmp_path}"
    )
    coeff = {r.run: r for r in read_results(logdir / "results.csv")}
    for r in rows:
        assert r.recall_at_1 == pytest.approx(coeff[r.run].recall_at_1, abs=0.01)
        assert np.isfinite(r.encode_ms_per_image)


def test_olid_sections_match_queries_against_the_whole_database_season(tmp_path):
    from vpr_jax.config import SplitConfig
    from vpr_jax.data.splits import make_split
    from vpr_jax.data.synthetic import synthetic_route

    logdir = tmp_path / "sections"
    split_keys = ["split.test_sections=2", "split.n_test=60", "split.gap=20", "split.database=all"]
    (row,), _ = sweep_rows(
        *[k for k in SMALL if not k.startswith("split.")],
        *split_keys,
        "methods=[raw]",
        "season_pairs=summer-fall",
        f"logdir={logdir}",
    )
    # Oracle: numpy brute force over every frame of the database season.
    n = int(next(k for k in SMALL if k.startswith("data.n_frames=")).split("=")[1])
    route = synthetic_route(n, ("summer", "fall"), 0)
    split = make_split(route.frame_ids, SplitConfig(test_sections=2, n_test=60, gap=20))
    stretch = n - 120 - 4 * 20  # frames more than the gap from both test sections
    n_val = round(0.1 * stretch)
    assert row.n_test == 120 and row.n_train == 2 * len(split.train) == 2 * (stretch - n_val - 20)
    flat = {s: route.images[s].reshape(n, -1).astype(np.float64) for s in ("summer", "fall")}
    mean = np.concatenate([flat["summer"][split.train], flat["fall"][split.train]]).mean(0)
    db = flat["summer"] - mean
    query = flat["fall"][split.test] - mean
    best = route.frame_ids[np.argmax(numpy_cosine(query, db), axis=1)]
    correct = np.abs(best - route.frame_ids[split.test]) <= row.tolerance
    assert row.recall_at_1 == pytest.approx(correct.mean(), abs=1 / 120 + 1e-9)


def test_each_pair_has_one_summary_run_of_its_selected_cells(small_sweep):
    """TensorBoard opens on the comparison: logdir/summary holds one run per pair (fewer than
    the 40 runs TensorBoard ticks by default), whose tags are every method's selected cell."""
    from tensorboard.backend.event_processing.plugin_event_multiplexer import EventMultiplexer

    from vpr_jax.method_table import model_name

    logdir, _ = small_sweep
    rows = read_results(logdir / "results.csv")
    pairs = sorted({r.season_pair for r in rows})
    multiplexer = EventMultiplexer()
    multiplexer.AddRunsFromDirectory(str(logdir / "summary"))
    multiplexer.Reload()
    assert sorted(multiplexer.Runs()) == pairs
    for pair in pairs:
        chosen = [r for r in rows if r.season_pair == pair and r.selected]
        ea = read_run(logdir / "summary" / pair)
        labels = [model_name(r.method, r.objective) for r in chosen]
        assert sorted(t for t in ea.Tags()["tensors"] if t.startswith("pr_curve/")) == sorted(
            f"pr_curve/{label}" for label in labels
        )
        compared = [e.value for e in ea.Scalars("compare/recall_at_1")]
        assert [e.step for e in ea.Scalars("compare/recall_at_1")] == list(range(len(chosen)))
        for step, (row, label) in enumerate(zip(chosen, labels, strict=True)):
            (value,) = ea.Scalars(f"metrics/recall_at_1/{label}")
            assert value.value == pytest.approx(row.recall_at_1, abs=1e-6)
            assert compared[step] == pytest.approx(row.recall_at_1, abs=1e-6)
            (ep,) = ea.Scalars(f"metrics/extended_precision/{label}")
            assert ep.value == pytest.approx(row.extended_precision, abs=1e-6)
            # the same PR curve as the cell's own run
            (mine,) = ea.Tensors(f"pr_curve/{label}")
            (cells,) = read_run(logdir / row.run).Tensors("pr_curve")
            np.testing.assert_array_equal(
                tensor_util.make_ndarray(mine.tensor_proto),
                tensor_util.make_ndarray(cells.tensor_proto),
            )


@pytest.mark.timeout(240)
def test_every_row_of_a_sweep_names_its_protocol(small_sweep):
    logdir, proc = small_sweep
    with open(logdir / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    by_pair = {}
    for row in rows:
        assert re.fullmatch(r"[0-9a-f]{12}", row["protocol"]), row["run"]
        by_pair.setdefault(row["season_pair"], set()).add(row["protocol"])
    assert all(len(p) == 1 for p in by_pair.values()), by_pair
    prints = {pair: next(iter(p)) for pair, p in by_pair.items()}
    assert len(set(prints.values())) == len(prints)  # another direction, another protocol
    printed = dict(re.findall(r"^protocol (\S+) ([0-9a-f]{12}): ", proc.stdout, re.M))
    assert printed == prints
    results = (logdir / "results.md").read_text()
    assert all(f"{pair} {fp}" in results for pair, fp in prints.items())
