"""The built-in seasonal route: determinism, geometry, and the properties that make it a
useful stand-in for Nordland, measured with the suite's own PCA, matching and metrics."""

import subprocess
import sys

import cv2
import numpy as np
import pytest

from tests.conftest import REPO
from vpr_jax.data.synthetic import render_season, synthetic_route
from vpr_jax.encoders.pca import fit_pca, project
from vpr_jax.errors import UserError
from vpr_jax.matching import cosine_similarity
from vpr_jax.metrics import evaluate

# The default protocol: 2,500 training places, a 100-frame gap, 450 test places, tolerance 2.
TRAIN, TEST = np.arange(2500), np.arange(2600, 3050)
PAPER_PAIRS = [("summer", "fall"), ("spring", "fall"), ("summer", "spring")]
WINTER_PAIRS = [("summer", "winter"), ("spring", "winter"), ("fall", "winter")]


def test_same_seed_same_pixels_other_seed_other_route():
    ids = np.arange(0, 400, 37)
    a = render_season(ids, "fall", seed=4)
    np.testing.assert_array_equal(a, render_season(ids, "fall", seed=4))
    assert np.abs(a - render_season(ids, "fall", seed=5)).mean() > 0.02
    assert a.shape == (len(ids), 32, 64) and a.dtype == np.float32
    assert 0.0 <= a.min() and a.max() <= 1.0 and a.std() > 0.05


def test_a_subset_renders_exactly_the_rows_of_the_whole():
    whole = render_season(np.arange(300), "winter", seed=1)
    ids = np.array([299, 3, 150, 3, 0])
    np.testing.assert_array_equal(render_season(ids, "winter", seed=1), whole[ids])


def test_route_is_frame_aligned_with_step():
    route = synthetic_route(50, ("summer", "winter"), seed=0, frame_step=10)
    np.testing.assert_array_equal(route.frame_ids, [0, 10, 20, 30, 40])
    assert route.seasons == ("summer", "winter")
    np.testing.assert_array_equal(route.images["summer"],
                                  render_season(route.frame_ids, "summer", seed=0))


def test_neighbouring_frames_overlap_distant_ones_do_not():
    imgs = render_season(np.arange(1000, 1200), "summer", seed=0).reshape(200, -1)
    imgs = imgs - imgs.mean(axis=0)
    near = np.mean([np.corrcoef(imgs[i], imgs[i + 1])[0, 1] for i in range(0, 150, 10)])
    far = np.mean([np.corrcoef(imgs[i], imgs[i + 50])[0, 1] for i in range(0, 150, 10)])
    assert near > far + 0.3


@pytest.mark.parametrize("bad", [dict(season="autumn"), dict(seed=-1), dict(traversal=1.5)])
def test_bad_arguments_are_user_errors(bad):
    args = dict(season="summer", seed=0, traversal=0) | bad
    with pytest.raises(UserError):
        render_season(np.arange(3), args.pop("season"), **args)


@pytest.fixture(scope="module")
def seasons():
    ids = np.arange(3050)
    return {s: render_season(ids, s, seed=0) for s in ("spring", "summer", "fall", "winter")}


def _recall_at_1(db, query, mean=None, pca=None, removed=0):
    if pca is not None:
        db, query = project(pca, db)[:, removed:], project(pca, query)[:, removed:]
    else:
        db, query = (db - mean).reshape(len(db), -1), (query - mean).reshape(len(query), -1)
    return evaluate(np.asarray(cosine_similarity(query, db)), TEST, TEST, 2).recall_at_1


def _raw(seasons, db, query):
    mean = np.concatenate([seasons[db][TRAIN], seasons[query][TRAIN]]).mean(axis=0)
    return _recall_at_1(seasons[db][TEST], seasons[query][TEST], mean=mean)


@pytest.mark.parametrize("season", ["spring", "summer", "fall", "winter"])
def test_a_season_matches_another_traversal_of_itself(seasons, season):
    again = render_season(TEST, season, seed=0, traversal=1)
    assert not np.array_equal(again, seasons[season][TEST])  # other noise, clouds, offset
    mean = seasons[season][TRAIN].mean(axis=0)
    assert _recall_at_1(seasons[season][TEST], again, mean=mean) >= 0.95


def test_raw_pixels_across_seasons_are_clearly_imperfect_and_worst_with_winter(seasons):
    paper = [_raw(seasons, db, q) for db, q in PAPER_PAIRS]
    winter = [_raw(seasons, db, q) for db, q in WINTER_PAIRS]
    assert all(0.2 <= r <= 0.85 for r in paper), paper
    assert max(winter) < min(paper), (winter, paper)


def test_pca_change_removal_beats_raw_pixels(seasons):
    gains = []
    for db, q in PAPER_PAIRS:
        pca = fit_pca(np.concatenate([seasons[db][TRAIN], seasons[q][TRAIN]]))
        best = max(_recall_at_1(seasons[db][TEST], seasons[q][TEST], pca=pca, removed=k)
                   for k in (0, 5, 10, 20, 50, 100))
        gains.append(best - _raw(seasons, db, q))
    assert sum(g >= 0.05 for g in gains) >= 2, gains


def test_contact_sheet_command_writes_a_png(tmp_path):
    out = tmp_path / "sheet.png"
    proc = subprocess.run([sys.executable, "-m", "experiments.contact_sheet", "--out", str(out),
                           "--n-places", "5", "--seasons", "summer,winter", "--scale", "2"],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == str(out)
    sheet = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE)
    assert sheet.shape == (2 * 32 * 2, 70 + 5 * 64 * 2)
    bad = subprocess.run([sys.executable, "-m", "experiments.contact_sheet", "--seasons",
                          "autumn", "--out", str(tmp_path / "x.png")], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "autumn" in bad.stderr and "Traceback" not in bad.stderr
