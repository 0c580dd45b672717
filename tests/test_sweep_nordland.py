"""Nordland-shaped data through the CLI (its ``main``, in this process): a 64x32 release
folder and season videos that the test writes itself (from the built-in renderer, so the
places are real places)."""

import cv2
import numpy as np

from tests.conftest import sweep_rows
from tests.inputs import write_release
from vpr_jax.data.synthetic import render_season

SEASONS = ("summer", "fall")
N_FRAMES = 90
SPLIT = [
    "split.n_train=50",
    "split.n_test=30",
    "split.gap=4",
    "removed_pcs=[0,3]",
    "data.seasons=[summer,fall]",
    "methods=[raw,pca]",
]  # the readers are under test


def _frames(season):
    return (render_season(np.arange(N_FRAMES), season, seed=3) * 255).round().astype(np.uint8)


def test_image_release_folder_runs_through_the_cli(tmp_path):
    root = write_release(tmp_path / "nordland", {s: _frames(s) for s in SEASONS})
    rows, _ = sweep_rows(
        "data.source=nordland_images", f"data.root={root}", *SPLIT, f"logdir={tmp_path / 'runs'}"
    )
    assert {(r.method, r.removed_pcs) for r in rows} == {("raw", 0), ("pca", 0), ("pca", 3)}
    assert all(r.n_train == 2 * 41 and r.n_test == 30 for r in rows)  # 50 less 5 val, gap 4
    assert all(r.recall_at_1 > 0 for r in rows)


def test_season_videos_run_through_the_cli_and_are_cached(tmp_path):
    root, fps = tmp_path / "videos", 4
    root.mkdir()
    for season in SEASONS:
        writer = cv2.VideoWriter(
            str(root / f"nordland_{season}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), fps, (128, 64)
        )
        for img in _frames(season):
            big = cv2.resize(img, (128, 64), interpolation=cv2.INTER_NEAREST)
            for _ in range(fps):  # one place per second of video
                writer.write(cv2.cvtColor(big, cv2.COLOR_GRAY2BGR))
        writer.release()
    args = [
        "data.source=nordland_videos",
        f"data.root={root}",
        f"data.cache_dir={tmp_path / 'cache'}",
        *SPLIT,
        "methods=raw",
    ]
    (row,), _ = sweep_rows(*args, f"logdir={tmp_path / 'runs'}")
    assert len(list((tmp_path / "cache").iterdir())) == 2
    assert row.n_test == 30 and row.recall_at_1 > 0
    root.joinpath("nordland_summer.avi").touch()  # newer mtime: a new cache entry
    again, _ = sweep_rows(*args, f"logdir={tmp_path / 'runs2'}")
    assert len(list((tmp_path / "cache").iterdir())) == 3
    assert again[0].recall_at_1 == row.recall_at_1
