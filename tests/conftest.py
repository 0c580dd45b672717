import os
import subprocess
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path

import cv2
import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

REPO = Path(__file__).resolve().parent.parent

# A small but complete sweep: the three default pairs, every method, three removed-PC counts
# and tiny auto-encoders trained for two epochs.
SMALL = [
    "data.n_frames=700",
    "split.n_train=300",
    "split.n_test=120",
    "split.gap=20",
    "removed_pcs=[0,5,20]",
    "fae.hidden=32",
    "cae.channels=[4,8]",
    "cae.code_channels=2",
    "train.epochs=2",
    "fae.epochs=2",
]


def run_cli(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    """``python -m experiments.sweep ARGS`` in a fresh interpreter, as a user runs it, with
    ``env`` added to the environment.

    Unless the test names one, models are checkpointed next to the logdir (in the test's
    own tmp folder), not in the repository's checkpoints/.
    """
    logdirs = [a.split("=", 1)[1] for a in args if a.startswith("logdir=")]
    if logdirs and not any(a.startswith("train.checkpoint_dir=") for a in args):
        args = (*args, f"train.checkpoint_dir={Path(logdirs[-1]).parent / 'checkpoints'}")
    env = {**os.environ, "PYTHONPATH": str(REPO), **(env or {})}
    return subprocess.run(
        [sys.executable, "-m", "experiments.sweep", *args],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
    )


@pytest.fixture(scope="session")
def small_sweep(tmp_path_factory):
    """One finished small sweep shared by the end-to-end tests (read-only for them)."""
    logdir = tmp_path_factory.mktemp("sweep") / "runs"
    proc = run_cli(*SMALL, f"logdir={logdir}")
    assert proc.returncode == 0, proc.stderr
    return logdir, proc


def numpy_cosine(q, d):
    """The oracle for cosine similarity: (n_queries, n_db), rows and columns L2-normalised."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    return q @ d.T


def write_release(
    root: Path, frames: Mapping[str, Iterable[np.ndarray]], ids: Iterable[int] | None = None
) -> Path:
    """Nordland's 64x32 release layout, ``ROOT/<season>/images-%05d.png``, from each season's
    uint8 images, numbered ``ids`` (default 1, 2, ...). Returns ``root``."""
    for season, images in frames.items():
        folder = Path(root) / season
        folder.mkdir(parents=True, exist_ok=True)
        images = list(images)
        numbers = range(1, len(images) + 1) if ids is None else ids
        for i, img in zip(numbers, images, strict=True):
            assert cv2.imwrite(str(folder / f"images-{i:05d}.png"), img)
    return Path(root)


class LogLines(list):
    """Collects what a reader or loop logs: pass it where ``log=print`` would go."""

    def __call__(self, line: str) -> None:
        self.append(line)


def read_run(path: Path) -> EventAccumulator:
    """A TensorBoard run read back by TensorBoard's own reader, keeping every event (its
    default keeps only a sample of each tag)."""
    ea = EventAccumulator(str(path), size_guidance={"scalars": 0, "tensors": 0, "images": 0})
    ea.Reload()
    return ea


def tail_validation(images, n_groups: int, fraction: float):
    """(train, val): the last ``fraction`` of each of ``n_groups`` equal consecutive groups
    held out, as the sweep's split holds out the end of each season's training stretch."""
    groups = np.split(np.asarray(images), n_groups)
    n_val = max(1, int(round(len(groups[0]) * fraction)))
    return (
        np.concatenate([g[:-n_val] for g in groups]),
        np.concatenate([g[-n_val:] for g in groups]),
    )
