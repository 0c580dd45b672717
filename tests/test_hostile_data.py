"""Hostile but valid data through the CLI: a tunnel (black frames in every season), a train
standing at a station, over-exposed frames, a season shifted by two frames and so shorter
than the others, a colour image. The sweep must finish, say in the run log what it saw, and
score finite metrics; constant frames are dropped only when asked."""

import math

import cv2
import numpy as np
import pytest

from tests.conftest import sweep_rows
from tests.inputs import write_release
from vpr_jax.data.synthetic import synthetic_route
from vpr_jax.evaluation.metrics import SCALAR_NAMES

SEASONS = ("spring", "summer", "fall")
METRICS = SCALAR_NAMES
# Test places are positions 110..239 of the route: the tunnel, the station and the
# over-exposed frames all fall among them.
SPLIT = ["split.n_train=100", "split.gap=10", "split.n_test=130"]


@pytest.fixture(scope="module")
def hostile_root(tmp_path_factory):
    route = synthetic_route(260, SEASONS, seed=3)
    images = {s: np.rint(im * 255).astype(np.uint8) for s, im in route.images.items()}
    images["fall"] = images["fall"][2:]  # fall's frame i shows place i + 2; 258 frames
    for season in SEASONS:
        images[season][150:156] = 0  # a tunnel: 6 black places in every season
    images["fall"][200:203] = 255  # the camera saturates for 3 frames
    images["spring"][170:180] = images["spring"][170]  # standing 9 more seconds at a station
    root = write_release(tmp_path_factory.mktemp("hostile") / "data", images)
    colour = cv2.cvtColor(images["summer"][9], cv2.COLOR_GRAY2BGR)
    cv2.imwrite(str(root / "summer" / "images-00010.png"), colour)
    return root


def _run(root, logdir, *args):
    """The sweep's ``main`` in this process (what is tested is what it prints, logs and
    scores; the command line's start is test_bad_input.py's): its rows, process and log."""
    rows, proc = sweep_rows(
        "data.source=nordland_images",
        f"data.root={root}",
        *SPLIT,
        "season_pairs=summer-fall,spring-fall",
        f"logdir={logdir}",
        *args,
    )
    assert "Traceback" not in proc.stderr
    return rows, proc, (logdir / "sweep.log").read_text()


def _assert_finite(rows):
    for row in rows:
        for key in METRICS:
            value = getattr(row, key)
            assert math.isfinite(value) and 0.0 <= value <= 1.0, (row.run, key)


def test_hostile_route_is_reported_kept_and_scored(hostile_root, tmp_path):
    logdir = tmp_path / "runs"
    rows, proc, log = _run(
        hostile_root,
        logdir,
        "methods=[raw,pca,ica,fae]",
        "removed_pcs=[0,5]",
        "ica.n_components=16",
        "fae.hidden=64",
        "fae.epochs=2",
    )
    for line in (
        "converted colour images to grayscale (summer 1)",
        "seasons hold different frames: keeping the 258 common to all; frames dropped per "
        "season: spring 2, summer 2, fall 0",
        "repeated frames (the same image as the frame before, e.g. a train standing at a "
        "station): spring 9, summer 0, fall 0; kept",
        "constant frames (pixel std <= data.constant_std=0.01: black, over-exposed or blank): "
        "spring 6, summer 6, fall 9, at 9 places; kept (data.drop_constant_frames=true drops "
        "them)",
        "sweep: 258 frames per season",
    ):
        assert line in proc.stdout and line in log, line
    assert len(rows) == 2 * (1 + 2 + 2 + 2)  # raw, PCA and ICA at two counts, both FAEs
    _assert_finite(rows)
    # A two-frame shift is within the default tolerance of 2: raw pixels still find most places.
    raw = {r.season_pair: r.recall_at_1 for r in rows if r.method == "raw"}
    assert raw["summer-fall"] > 0.5, raw


def test_constant_frames_are_dropped_when_asked(hostile_root, tmp_path):
    logdir = tmp_path / "runs"
    rows, _, log = _run(
        hostile_root,
        logdir,
        "methods=[raw,pca]",
        "removed_pcs=[0,5]",
        "data.drop_constant_frames=true",
    )
    assert (
        "spring 6, summer 6, fall 9, at 9 places; dropped from every season "
        "(data.drop_constant_frames=true), 249 places left"
    ) in log
    assert "sweep: 249 frames per season" in log
    assert len(rows) == 2 * (1 + 2)
    _assert_finite(rows)


@pytest.fixture(scope="module")
def station_root(tmp_path_factory):
    """Two seasons whose training stretch holds a long station stop: 50 frames of the same
    place in both, so the training images have far lower rank than their count."""
    route = synthetic_route(200, ("summer", "winter"), seed=4)
    images = {s: np.rint(im * 255).astype(np.uint8) for s, im in route.images.items()}
    for season in images:
        images[season][10:60] = images[season][10]
    return write_release(tmp_path_factory.mktemp("station") / "data", images)


def test_repeated_training_frames_give_pca_that_is_pca(station_root, tmp_path):
    """The Gram solver (what auto picks for fewer images than pixels) on a route with a
    station stop: PCA with no component removed scores exactly as raw pixels, and removed
    counts beyond the training images' numerical rank are left out with a note, for PCA and
    for ICA, instead of being scored on components that are not PCA's."""
    logdir = tmp_path / "runs"
    rows, _ = sweep_rows(
        "data.source=nordland_images",
        f"data.root={station_root}",
        "data.seasons=[summer,winter]",
        "season_pairs=summer-winter",
        "split.n_train=100",
        "split.gap=10",
        "split.n_test=60",
        "methods=[raw,pca,ica]",
        "removed_pcs=[0,5,150]",
        "ica.n_components=8",
        "pca.solver=gram",
        f"logdir={logdir}",
    )
    log = (logdir / "sweep.log").read_text()
    assert "note: summer-winter: the PCA fit holds" in log
    assert "pca_k150: not scored: removed_pcs=150 is beyond the" in log
    assert "ica_k150: not scored: ica.n_components=8 with removed_pcs=150" in log
    assert sorted((r.method, r.removed_pcs) for r in rows) == [
        ("ica", 0),
        ("ica", 5),
        ("pca", 0),
        ("pca", 5),
        ("raw", 0),
    ]
    raw = next(r for r in rows if r.method == "raw")
    pca0 = next(r for r in rows if r.method == "pca" and r.removed_pcs == 0)
    for column in (*METRICS, "recall_at_1_ci_low", "recall_at_1_ci_high", "val_recall_at_1"):
        assert getattr(pca0, column) == pytest.approx(getattr(raw, column), abs=1e-6), column
