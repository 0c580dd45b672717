import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent

# A small but complete sweep: the three default pairs, every method, three removed-PC counts
# and tiny auto-encoders trained for two epochs.
SMALL = ["data.n_frames=700", "split.n_train=300", "split.n_test=120", "split.gap=20",
         "removed_pcs=[0,5,20]", "fae.hidden=32", "cae.channels=[4,8]", "cae.code_channels=2",
         "train.epochs=2", "fae.epochs=2"]


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
    return subprocess.run([sys.executable, "-m", "experiments.sweep", *args], cwd=REPO,
                          env=env, capture_output=True, text=True)


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
