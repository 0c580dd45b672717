"""TensorBoard output: one run per sweep cell, plus the HParams experiment at the sweep root.

HParams follow the route that keeps scalars safe: the experiment config is written once at
the root, and each run's hparams go into that run's own writer, instead of tensorboardX's
``add_hparams``, which opens a writer of its own in a subfolder and, pointed at the run
itself (``name="."``), can truncate the run's event file (file names carry whole seconds)
and lose every scalar.
"""

from __future__ import annotations

import math
import threading
import time
import traceback
from pathlib import Path
from typing import NamedTuple

import numpy as np
from tensorboard.plugins.hparams import summary_v2 as hp
from tensorboardX import SummaryWriter
from tensorboardX.proto.summary_pb2 import Summary

from vpr_jax.data.ground_truth import GroundTruth
from vpr_jax.evaluation.metrics import Evaluation, pr_counts

# tensorboardX writes event files from a thread of its own: an OSError there (a full disk)
# would only print that thread's traceback, and the run would look written. The hook keeps
# such errors; every writer's close() raises the first one in the thread that saves results.
_writer_faults: list[OSError] = []
_default_hook = threading.excepthook


def _keep_writer_faults(args) -> None:
    frames = traceback.extract_tb(args.exc_traceback)
    if isinstance(args.exc_value, OSError) and any("tensorboardX" in f.filename for f in frames):
        _writer_faults.append(args.exc_value)
        return
    _default_hook(args)


threading.excepthook = _keep_writer_faults


def _closed(writer: SummaryWriter) -> None:
    """Close ``writer`` (its thread flushes and ends) and raise what its thread could not
    write, if anything."""
    writer.close()
    if _writer_faults:
        raise _writer_faults.pop(0)


def _to_tbx(summary_pb) -> Summary:
    return Summary.FromString(summary_pb.SerializeToString())


def write_experiment_config(logdir: Path, domains: dict[str, list], metric_tags: list[str]):
    """The HParams experiment: discrete domains of every swept knob and the metric tags."""
    hparams = [
        hp.HParam(name, hp.Discrete(sorted(set(values)))) for name, values in domains.items()
    ]
    metrics = [hp.Metric(tag) for tag in metric_tags]
    # A resumed or extended sweep replaces the experiment instead of adding a second one.
    for old in Path(logdir).glob("events.out.tfevents.*.hparams"):
        old.unlink()
    writer = SummaryWriter(str(logdir), filename_suffix=".hparams")
    writer.file_writer.add_summary(_to_tbx(hp.hparams_config_pb(hparams, metrics)))
    _closed(writer)


def tile(images: np.ndarray, n_cols: int, pad: int = 1) -> np.ndarray:
    """(n, h, w) images in [0, 1] -> one (rows*(h+pad), cols*(w+pad)) grid, white padding."""
    n, h, w = images.shape
    n_rows = -(-n // n_cols)
    grid = np.ones((n_rows * (h + pad) - pad, n_cols * (w + pad) - pad), np.float32)
    for i, img in enumerate(images):
        r, c = divmod(i, n_cols)
        grid[r * (h + pad) : r * (h + pad) + h, c * (w + pad) : c * (w + pad) + w] = img
    return grid


def normalise_each(images: np.ndarray) -> np.ndarray:
    """Stretch every image to [0, 1] on its own (eigen-images have arbitrary scale)."""
    lo = images.min(axis=(1, 2), keepdims=True)
    hi = images.max(axis=(1, 2), keepdims=True)
    return (images - lo) / np.maximum(hi - lo, 1e-12)


def match_examples(query, db, truth: GroundTruth, best_indices, n: int) -> np.ndarray:
    """Rows of query | best match | a true match (``truth.a_match``: the nearest frame for
    a tolerance; black when the query has none) for n queries spread over the queries."""
    picks = np.linspace(0, len(query) - 1, min(n, len(query))).round().astype(int)
    true = truth.a_match()
    rows = []
    for q in picks:
        rows += [
            query[q],
            db[best_indices[q]],
            db[true[q]] if true[q] >= 0 else np.zeros_like(db[0]),
        ]
    return tile(np.stack(rows), n_cols=3)


def write_cell_run(
    run_dir: Path,
    evaluation: Evaluation,
    *,
    scalars: dict[str, float],
    hparams: dict,
    trial_id: str,
    n_thresholds: int,
    examples: np.ndarray,
    basis_images: np.ndarray | None,
    basis_tag: str = "basis/removed_components",
) -> None:
    """Everything TensorBoard shows for one cell, at step 0: the evaluation's metrics as
    ``metrics/<name>``, the other ``scalars`` under their own tags, its PR curve, images and
    hparams.

    The PR curve uses thresholds linspace(0, 1) on (cosine + 1) / 2; its counts follow the
    evaluation's ``pr_convention`` (see vpr_jax.evaluation.metrics), so TensorBoard's recall is the
    sweep's recall.
    """
    ev = evaluation
    tagged = {**{f"metrics/{k}": v for k, v in ev.scalars().items()}, **scalars}
    writer = SummaryWriter(str(run_dir))
    for tag, value in tagged.items():
        if math.isfinite(value):  # NaN: unknown (outside descriptors' fit time), not a value
            writer.add_scalar(tag, float(value), global_step=0)
    _add_pr_curve(
        writer,
        "pr_curve",
        ev.best_scores,
        ev.best_correct,
        ev.has_match,
        ev.pr_convention,
        n_thresholds,
    )
    writer.add_image("matches/query_best_true", examples, global_step=0, dataformats="HW")
    if basis_images is not None and len(basis_images):
        grid = tile(normalise_each(basis_images), n_cols=min(4, len(basis_images)))
        writer.add_image(basis_tag, grid, global_step=0, dataformats="HW")
    writer.file_writer.add_summary(_to_tbx(hp.hparams_pb(hparams, trial_id=trial_id)))
    _closed(writer)


def _add_pr_curve(
    writer: SummaryWriter,
    tag: str,
    best_scores,
    best_correct,
    has_match,
    pr_convention: str,
    n_thresholds: int,
    step: int = 0,
) -> None:
    """A single-best-match PR curve on thresholds linspace(0, 1) of (cosine + 1) / 2, its
    counts in ``pr_convention`` (TensorBoard's recall is then the sweep's recall)."""
    thresholds = np.linspace(0.0, 1.0, n_thresholds)
    tp, fp, tn, fn = pr_counts(
        (np.asarray(best_scores) + 1.0) / 2.0,
        best_correct,
        has_match,
        thresholds,
        pr_convention=pr_convention,
    )
    precision = np.where(tp + fp > 0, tp / np.maximum(tp + fp, 1), 1.0)
    recall = tp / np.maximum(tp + fn, 1)
    writer.add_pr_curve_raw(
        tag, tp, fp, tn, fn, precision, recall, global_step=step, num_thresholds=n_thresholds
    )


class SummaryCell(NamedTuple):
    """One method's selected cell of a pair, for the pair's summary run."""

    label: str  # the method as tags name it: pca, fae_cross_season, lda_ds10
    setting: str  # what was selected, for the text table: "k=10", ""
    scalars: dict[str, float]  # metric name -> value (the results.csv row's)
    best_scores: np.ndarray
    best_correct: np.ndarray
    has_match: np.ndarray


# The scalars a summary run also puts side by side, one step per method (method order).
COMPARED = ("recall_at_1", "auc_pr", "extended_precision", "recall_at_100_precision")


def write_pair_summary(
    run_dir: Path, cells: list[SummaryCell], *, pr_convention: str, n_thresholds: int
) -> None:
    """A season pair's summary run: each method's selected cell as tags of one run, so
    TensorBoard shows the comparison (the paper's Figs 7-12) without ticking 70 runs.

    - PR CURVES: ``pr_curve/<label>``, one chart per method (the pair's own curve in it);
    - SCALARS: ``compare/<metric>`` for the metrics in ``COMPARED`` with method i at step i,
      all methods on one chart (first: TensorBoard orders groups by name), and
      ``metrics/<metric>/<label>`` at step 0 for every metric;
    - TEXT: ``methods``: which step is which method and setting.
    """
    writer = SummaryWriter(str(run_dir))
    rows = ["| step | method | selected | recall@1 | AUC-PR |", "|---|---|---|---|---|"]
    for step, cell in enumerate(cells):
        _add_pr_curve(
            writer,
            f"pr_curve/{cell.label}",
            cell.best_scores,
            cell.best_correct,
            cell.has_match,
            pr_convention,
            n_thresholds,
        )
        for name, value in cell.scalars.items():
            writer.add_scalar(f"metrics/{name}/{cell.label}", float(value), global_step=0)
        for name in COMPARED:
            writer.add_scalar(f"compare/{name}", float(cell.scalars[name]), global_step=step)
        rows.append(
            f"| {step} | {cell.label} | {cell.setting} | "
            f"{cell.scalars['recall_at_1']:.3f} | {cell.scalars['auc_pr']:.3f} |"
        )
    writer.add_text("methods", "\n".join(rows), global_step=0)
    _closed(writer)


class CompareSeries(NamedTuple):
    """One method's cells of one pair, for its method-by-method run."""

    points: list[tuple[int, float, float]]  # (removed-PC count, recall@1, AUC-PR) per step
    best_scores: np.ndarray  # of its selected cell: the PR curve
    best_correct: np.ndarray
    has_match: np.ndarray
    learning: tuple = ()  # (training places, recall@1, AUC-PR) of a learning curve's points


def write_method_run(
    run_dir: Path,
    series: dict[str, CompareSeries],
    *,
    group: str,
    pr_convention: str,
    n_thresholds: int,
) -> None:
    """A method's run of the method-by-method view (``LOGDIR/compare/<method>``), its tags
    per pair and chart ``group`` (its family's: ``palette.chart_groups``):
    ``pr_curve/<pair>/<group>`` (its selected cell's curve, so PR CURVES overlays the
    group's methods of a pair in one chart) and ``<pair>/<group>/recall_at_1``,
    ``.../auc_pr`` with the removed-PC count as the step (a chart per pair, group and
    metric, a line per method); a learning curve (``split.train_places``) as
    ``<pair>/<group>/by_training_places/recall_at_1`` and ``.../auc_pr`` with the training
    places as the step."""
    writer = SummaryWriter(str(run_dir))
    for pair, s in series.items():
        _add_pr_curve(
            writer,
            f"pr_curve/{pair}/{group}",
            s.best_scores,
            s.best_correct,
            s.has_match,
            pr_convention,
            n_thresholds,
        )
        for k, recall_at_1, auc_pr in s.points:
            writer.add_scalar(f"{pair}/{group}/recall_at_1", float(recall_at_1), global_step=k)
            writer.add_scalar(f"{pair}/{group}/auc_pr", float(auc_pr), global_step=k)
        for places, recall_at_1, auc_pr in s.learning:
            tag = f"{pair}/{group}/by_training_places"
            writer.add_scalar(f"{tag}/recall_at_1", float(recall_at_1), global_step=places)
            writer.add_scalar(f"{tag}/auc_pr", float(auc_pr), global_step=places)
    _closed(writer)


class TrainingRun:
    """A training run's TensorBoard log: losses per step, image grids, and run-log lines.

    ``begin(step)`` opens the writer with ``purge_step=step + 1``: when training resumes
    after the checkpoint of ``step``, TensorBoard drops what an interrupted session logged
    after it, so no step appears twice.
    """

    def __init__(self, run_dir: Path, line):
        self._run_dir, self._line, self._writer = Path(run_dir), line, None

    def begin(self, step: int) -> None:
        self._run_dir.mkdir(parents=True, exist_ok=True)
        # tensorboardX names event files by the second: a session resumed within the same
        # second would truncate the killed session's file. The nanosecond suffix keeps
        # both, in the order they were written.
        self._writer = SummaryWriter(
            str(self._run_dir), purge_step=step + 1, filename_suffix=f".{time.time_ns()}"
        )

    def scalar(self, tag: str, value: float, step: int) -> None:
        self._writer.add_scalar(tag, float(value), global_step=step)

    def images(self, tag: str, images: np.ndarray, step: int) -> None:
        images = np.asarray(images, np.float32)
        images = images[..., 0] if images.ndim == 4 else images
        grid = tile(np.clip(images, 0.0, 1.0), n_cols=min(6, len(images)))
        self._writer.add_image(tag, grid, global_step=step, dataformats="HW")

    def line(self, text: str) -> None:
        self._line(text)

    def close(self) -> None:
        if self._writer is not None:
            writer, self._writer = self._writer, None
            _closed(writer)
