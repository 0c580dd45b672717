"""Bad input through the CLI: one line naming problem and fix, exit 2, no traceback, and the
log directory exactly as it was."""

import hashlib
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import SMALL, run_cli


def _snapshot(folder: Path) -> dict:
    if not folder.exists():
        return {}
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _release(root: Path, seasons=("spring", "summer", "fall"), ids=range(1, 5), shape=(32, 64)):
    for season in seasons:
        (root / season).mkdir(parents=True, exist_ok=True)
        for i in ids:
            img = np.full(shape, 40 + i, np.uint8)
            cv2.imwrite(str(root / season / f"images-{i:05d}.png"), img)
    return root


def _assert_refused(proc, *words):
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    assert "Traceback" not in proc.stderr + proc.stdout
    for word in words:
        assert word in lines[0], lines[0]


def _corrupt(root):
    path = _release(root) / "summer" / "images-00002.png"
    path.write_bytes(path.read_bytes()[:20])
    return root


def _wrong_size(root):
    _release(root)
    cv2.imwrite(str(root / "fall" / "images-00003.png"), np.zeros((48, 64), np.uint8))
    return root


def _no_common(root):
    _release(root, seasons=("spring", "summer"), ids=range(1, 4))
    return _release(root, seasons=("fall",), ids=range(10, 14))


DATA_CASES = {
    "missing root": (lambda root: root / "absent", ["does not exist", "data.root"]),
    "empty root": (lambda root: root, ["data.root"]),
    "missing season": (lambda root: _release(root, seasons=("spring", "summer")), ["fall"]),
    "corrupt image": (_corrupt, ["images-00002.png"]),
    "wrong size": (_wrong_size, ["images-00003.png", "data.source=folders"]),
    "no common frames": (_no_common, ["share no frame"]),
}


@pytest.mark.parametrize("case", DATA_CASES)
def test_bad_data(case, tmp_path):
    make, words = DATA_CASES[case]
    root = tmp_path / "data"
    root.mkdir()
    root = make(root)
    logdir = tmp_path / "runs"
    logdir.mkdir()
    (logdir / "keep.txt").write_text("mine")
    proc = run_cli("data.source=nordland_images", f"data.root={root}", f"logdir={logdir}")
    _assert_refused(proc, *words)
    assert _snapshot(logdir) == {"keep.txt": hashlib.sha256(b"mine").hexdigest()}


CONFIG_CASES = {
    "unknown key": (["method=raw"], ["method"]),
    "wrong type": (["tolerance=two"], ["tolerance"]),
    "bad pair name": (["season_pairs=summer_fall"], ["summer_fall", "season_pairs"]),
    "pair of one season": (["season_pairs=fall-fall"], ["fall-fall"]),
    "pair outside seasons": (["season_pairs=summer-winter"], ["winter", "data.seasons"]),
    "negative removed count": (["removed_pcs=[-1,5]"], ["removed_pcs"]),
    "removed count leaves nothing": ([*SMALL, "removed_pcs=[0,599]"], ["599", "below 599"]),
    "more ICs than the data allow": (
        [*SMALL, "ica.n_components=590"],
        ["ica.n_components=590", "up to 20", "ica.n_components <= 579"],
    ),
    "ICs not a count": (["ica.n_components=many"], ["ica.n_components=many", "all"]),
    "unknown ICA contrast": (["ica.fun=tanh"], ["ica.fun=tanh", "logcosh"]),
}


@pytest.mark.parametrize("case", CONFIG_CASES)
def test_bad_config(case, tmp_path):
    args, words = CONFIG_CASES[case]
    proc = run_cli(*args, f"logdir={tmp_path / 'runs'}")
    _assert_refused(proc, *words)
    assert _snapshot(tmp_path / "runs") == {}


def test_logdir_that_is_a_file(tmp_path):
    path = tmp_path / "runs"
    path.write_text("not a folder")
    _assert_refused(run_cli(f"logdir={path}"), "is a file")
    assert path.read_text() == "not a folder"


def test_logdir_that_cannot_be_written():
    # /proc refuses new folders even to root, unlike a chmod-ed folder.
    _assert_refused(run_cli("logdir=/proc/vpr_jax_runs"), "not writable", "logdir")


def test_finished_logdir_is_untouched_by_bad_reruns(small_sweep, tmp_path):
    finished, _ = small_sweep
    logdir = tmp_path / "runs"
    shutil.copytree(finished, logdir)
    before = _snapshot(logdir)
    _assert_refused(run_cli(*SMALL, "tolerance=3", f"logdir={logdir}"),
                    "different configuration", "tolerance")
    _assert_refused(run_cli(*SMALL, "removed_pcs=[0,900]", f"logdir={logdir}"), "900")
    assert _snapshot(logdir) == before
