"""Benchmarks that are not frame-aligned, run on tiny datasets the tests
build (the first through a fresh interpreter's CLI, the others by its main in this
process): VPR-Bench's folders with a ground-truth file, a positions benchmark with CSVs,
Nordland* from a tiny 64x32 release, and an aligned route to train on. Raw-pixel recall@1
equals a numpy reference; bad layouts are one line, exit 2, nothing written."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import REPO, assert_one_line_error, run_cli, run_here, sweep_rows
from tests.inputs import N_PLACES, read_grey, u8, write_release, write_vpr_bench
from vpr_jax.data.synthetic import synthetic_route

RAW = ["methods=[raw]"]


@pytest.fixture(scope="module")
def route():
    return synthetic_route(N_PLACES, ("summer", "fall"), seed=3)


def reference_recall(db_paths, query_paths, correct_sets) -> float:
    """Raw pixels centred with the training mean (the database's: what a benchmark without
    a training route fits on), cosine, best match in numpy: share of queries whose best is
    correct."""
    db = np.stack([read_grey(p) for p in db_paths])
    query = np.stack([read_grey(p) for p in query_paths])
    mean = db.mean(axis=0)
    db, query = db - mean, query - mean
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    query /= np.linalg.norm(query, axis=1, keepdims=True)
    best = np.argmax(query @ db.T, axis=1)
    return float(np.mean([b in s for b, s in zip(best, correct_sets, strict=True)]))


def test_vpr_bench_raw_recall_equals_a_numpy_reference(route, tmp_path):
    root = tmp_path / "bench"
    refs, queries, rows = write_vpr_bench(root, route, drop_rows={7})
    (row,), proc = sweep_rows(
        "data.source=vpr_bench",
        f"data.root={root}",
        *RAW,
        f"logdir={tmp_path / 'runs'}",
        run=run_cli,
    )
    n_val = round(0.1 * len(queries))  # split.val_fraction of the queries validate
    n_test = len(queries) - n_val
    sets = {n: set(near) for n, near in rows}  # query 7 has no row: no correct reference
    expected = reference_recall(
        [root / "ref" / r for r in refs],
        [root / "query" / q for q in queries[:n_test]],
        [sets.get(n, set()) for n in range(n_test)],
    )
    assert (row.season_pair, row.n_test, row.n_train) == ("ref-query", n_test, N_PLACES)
    assert row.recall_at_1 == pytest.approx(expected, abs=1e-12) and 0.3 < expected < 1.0
    assert row.ground_truth == "ground_truth_new.npy" and row.tolerance == -1
    assert 0.0 <= row.extended_precision <= 1.0
    assert "converted colour images to grayscale (query 60)" in proc.stdout


def test_the_ground_truth_file_decides_what_is_correct(route, tmp_path):
    """The same images with every reference list shifted by 30 places: recall@1 collapses."""
    root = tmp_path / "bench"
    write_vpr_bench(root, route, skew=30)
    (row,), _ = sweep_rows(
        "data.source=vpr_bench", f"data.root={root}", *RAW, f"logdir={tmp_path / 'runs'}"
    )
    assert row.recall_at_1 < 0.1


def write_positions(root: Path, route, rng) -> tuple[np.ndarray, np.ndarray]:
    """database/ (summer) and queries/ (fall, every 3rd place, JPEG-free colour PNGs) along a
    curving road 12 m a place, with CSVs in shuffled row order; returns the positions."""
    t = np.arange(N_PLACES) * 12.0
    xy = np.stack([4.1e5 + t, 5.6e6 + 80 * np.sin(t / 300)], axis=1)
    for side in ("database", "queries"):
        (root / side).mkdir(parents=True)
    db_rows, q_rows = [], []
    for i in range(N_PLACES):
        cv2.imwrite(str(root / "database" / f"{i:04d}.png"), u8(route.images["summer"][i]))
        db_rows.append((f"{i:04d}.png", *xy[i]))
    places = np.arange(0, N_PLACES, 3)
    q_xy = xy[places] + rng.normal(0, 6, (len(places), 2))
    for n, i in enumerate(places):
        image = cv2.cvtColor(u8(route.images["fall"][i]), cv2.COLOR_GRAY2BGR)
        cv2.imwrite(str(root / "queries" / f"{n:04d}.png"), image)
        q_rows.append((f"{n:04d}.png", *q_xy[n]))
    for side, rows in (("database", db_rows), ("queries", q_rows)):
        with open(root / f"{side}.csv", "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["name", "x", "y"])
            writer.writerows([rows[k] for k in rng.permutation(len(rows))])
    return xy, q_xy


def test_positions_raw_recall_equals_a_numpy_reference(route, tmp_path):
    root = tmp_path / "drive"
    db_xy, q_xy = write_positions(root, route, np.random.default_rng(0))
    (row,), _ = sweep_rows(
        "data.source=positions",
        f"data.root={root}",
        "data.radius_m=20",
        *RAW,
        f"logdir={tmp_path / 'runs'}",
    )
    n_test = len(q_xy) - round(0.1 * len(q_xy))
    distance = np.sqrt(((q_xy[:, None] - db_xy[None]) ** 2).sum(-1))  # dense: the oracle
    sets = [set(np.flatnonzero(distance[n] <= 20)) for n in range(n_test)]
    expected = reference_recall(
        sorted((root / "database").iterdir()), sorted((root / "queries").iterdir())[:n_test], sets
    )
    assert row.season_pair == "database-queries" and row.n_test == n_test
    assert row.recall_at_1 == pytest.approx(expected, abs=1e-12) and expected > 0.3
    assert row.ground_truth == "within 20 m"


def test_an_aligned_route_trains_what_learns_from_alignment(route, tmp_path):
    root = tmp_path / "bench"
    write_vpr_bench(root, route)
    rows, proc = sweep_rows(
        "data.source=vpr_bench",
        f"data.root={root}",
        "data.train_source=synthetic",
        "data.n_frames=300",
        "data.seasons=[summer,fall]",
        "split.n_train=150",
        "split.n_test=60",
        "split.gap=10",
        "methods=[raw,lda,fae]",
        "fae.objective=cross_season",
        "fae.hidden=16",
        "fae.epochs=1",
        f"logdir={tmp_path / 'runs'}",
    )
    rows = {r.method: r for r in rows}
    assert set(rows) == {"raw", "lda", "fae"} and rows["fae"].objective == "cross_season"
    # every query is a test query: validation is the route's own validation stretch
    # 150 training places less 15 validating and a gap of 10, in both seasons
    assert rows["lda"].n_test == N_PLACES // 2 and rows["lda"].n_train == 2 * 125
    assert "training on 125 places of each of summer, fall" in proc.stdout


def test_nordland_star_from_a_tiny_release(route, tmp_path):
    frames = {
        "summer": [u8(im) for im in route.images["summer"]],
        "winter": [u8(im) for im in route.images["fall"]],
    }
    root = write_release(tmp_path / "release", frames)  # images-00001 ... images-00120
    rows, _ = sweep_rows(
        "preset=nordland_star",
        f"data.root={root}",
        "data.frame_list=null",  # every frame: the tiny release has none of the clean list's
        "data.frame_range=[11,110]",
        "removed_pcs=[0,5]",
        "methods=[raw,pca]",
        f"logdir={tmp_path / 'runs'}",
    )
    raw = next(r for r in rows if r.method == "raw")
    n_query = 10  # every 10th of the 100 frames 11..110
    n_test = n_query - 1
    ids = list(range(11, 111))
    sets = [{k for k in (10 * n - 1, 10 * n, 10 * n + 1) if 0 <= k < 100} for n in range(n_test)]
    expected = reference_recall(
        [root / "winter" / f"images-{i:05d}.png" for i in ids],
        [root / "summer" / f"images-{ids[10 * n]:05d}.png" for n in range(n_test)],
        sets,
    )
    assert (raw.season_pair, raw.n_test, raw.n_train) == ("winter-summer", n_test, 100)
    assert raw.recall_at_1 == pytest.approx(expected, abs=1e-12)
    assert raw.ground_truth == "+-1 frame (Nordland*)"


def test_nordland_clean_reads_its_frame_range(route, tmp_path):
    seasons = ("spring", "summer", "fall", "winter")
    images = [u8(im) for im in route.images["summer"]]
    root = write_release(tmp_path / "release", {s: images for s in seasons})
    (row,), proc = sweep_rows(
        "preset=nordland_clean",
        f"data.root={root}",
        "data.frame_list=null",  # every frame: the tiny release has none of the clean list's
        "data.frame_range=[3,118]",
        "split.n_test=20",
        "split.gap=5",
        "methods=[raw]",
        "season_pairs=summer-winter",
        f"logdir={tmp_path / 'runs'}",
    )
    assert "116 frames x 4 seasons" in proc.stdout and "frames 3..118" in proc.stdout
    assert row.n_test == 3 * 20 and row.recall_at_1 == 1.0  # identical seasons


BAD = {
    "no ref folder": (
        lambda r: __import__("shutil").rmtree(r / "ref"),
        ["vpr_bench"],
        ["ref is missing", "ref/, query/ and ground_truth_new.npy"],
    ),
    "no query folder": (
        lambda r: __import__("shutil").rmtree(r / "query"),
        ["vpr_bench"],
        ["query is missing"],
    ),
    "no ground truth file": (
        lambda r: (r / "ground_truth_new.npy").unlink(),
        ["vpr_bench"],
        ["ground_truth_new.npy is missing"],
    ),
    "a row naming an absent query": (
        lambda r: (r / "query" / "q059.png").unlink(),
        ["vpr_bench"],
        ["names query image 59", "holds 59 images"],
    ),
    "a row naming an absent reference": (
        lambda r: [p.unlink() for p in sorted((r / "ref").iterdir())[100:]],
        ["vpr_bench"],
        ["names reference image", "holds 100 images"],
    ),
    "alignment methods without aligned places": (
        lambda r: None,
        ["vpr_bench", "methods=[raw,lda]"],
        ["methods ['lda'] learn from aligned training places", "data.train_source"],
    ),
    "cross_season without aligned places": (
        lambda r: None,
        ["vpr_bench", "methods=[fae]", "fae.objective=cross_season"],
        ["fae.objective=cross_season needs aligned training places"],
    ),
    "the lda start without aligned places": (
        lambda r: None,
        ["vpr_bench", "methods=[fae]", "fae.init=lda"],
        ["fae.init=lda needs aligned training places", "fae.init=whitened_pca"],
    ),
    "a pair the benchmark has not": (
        lambda r: None,
        ["vpr_bench", "season_pairs=summer-fall"],
        ["its one pair is ref-query"],
    ),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_vpr_bench_layouts_are_one_line(route, tmp_path, case):
    spoil, args, words = BAD[case]
    root = tmp_path / "bench"
    write_vpr_bench(root, route)
    spoil(root)
    source, *rest = args
    proc = run_here(
        f"data.source={source}", f"data.root={root}", *rest, f"logdir={tmp_path / 'runs'}"
    )
    assert_one_line_error(proc, *words)
    assert not (tmp_path / "runs").exists()


def _drop_csv_row(path: Path, name: str) -> None:
    lines = [ln for ln in path.read_text().splitlines() if not ln.startswith(name)]
    path.write_text("\n".join(lines) + "\n")


POSITIONS_BAD = {
    "a file without a position": (
        lambda r: _drop_csv_row(r / "queries.csv", "0004.png"),
        [],
        ["queries.csv has no position for 1 image(s)", "0004.png"],
    ),
    "a position that is not a number": (
        lambda r: (r / "database.csv").write_text("name,x,y\n0000.png,east,1\n"),
        [],
        ["database.csv line 2", "not two numbers"],
    ),
    "a csv without name,x,y": (
        lambda r: (r / "database.csv").write_text("file,lat\n"),
        [],
        ["not name,x,y"],
    ),
    "no database folder": (
        lambda r: __import__("shutil").rmtree(r / "database"),
        [],
        ["database is missing", "database.csv and queries.csv"],
    ),
    "a radius of zero": (
        lambda r: None,
        ["data.radius_m=0"],
        ["data.radius_m=0.0 must be positive"],
    ),
    "a negative radius": (lambda r: None, ["data.radius_m=-5"], ["data.radius_m=-5.0"]),
}


@pytest.mark.parametrize("case", sorted(POSITIONS_BAD))
def test_bad_positions_layouts_are_one_line(route, tmp_path, case):
    spoil, args, words = POSITIONS_BAD[case]
    root = tmp_path / "drive"
    write_positions(root, route, np.random.default_rng(1))
    spoil(root)
    proc = run_here(
        "data.source=positions", f"data.root={root}", *args, f"logdir={tmp_path / 'runs'}"
    )
    assert_one_line_error(proc, *words)
    assert not (tmp_path / "runs").exists()


def test_sequences_of_a_benchmark_follow_its_file_order(route, tmp_path):
    """Files named in route order (zero-padded), one query per place: sequence matching of
    4 frames finds more places than single images, scored against the file's sets."""
    root = tmp_path / "bench"
    for side, season in (("ref", "summer"), ("query", "fall")):
        (root / side).mkdir(parents=True)
        for i in range(N_PLACES):
            cv2.imwrite(str(root / side / f"{i:04d}.png"), u8(route.images[season][i]))
    table = np.empty(N_PLACES, dtype=object)
    for i in range(N_PLACES):
        table[i] = (i, [j for j in (i - 1, i, i + 1) if 0 <= j < N_PLACES])
    np.save(root / "ground_truth_new.npy", table, allow_pickle=True)
    rows, _ = sweep_rows(
        "data.source=vpr_bench",
        f"data.root={root}",
        *RAW,
        "sequence.enabled=true",
        "sequence.ds=[1,4]",
        f"logdir={tmp_path / 'runs'}",
    )
    rows = {r.ds: r for r in rows}
    assert set(rows) == {1, 4} and rows[4].n_test == rows[1].n_test == N_PLACES - 12
    assert rows[4].recall_at_1 > rows[1].recall_at_1
    table = (tmp_path / "runs" / "results.md").read_text()
    assert "a match is correct within ground_truth_new.npy" in table


def test_the_halves_script_lays_out_a_route_and_a_benchmark_that_share_no_place(tmp_path, capsys):
    """benchmarks/halves.py: the tuning route holds frames up to the split, the reporting
    benchmark the rest, read back by the suite's own readers; its ground truth is every
    reference within the tolerance of each query's frame, by the definition."""
    import importlib.util

    from tests.inputs import write_folders
    from vpr_jax.data.vpr_bench import read_vpr_bench

    spec = importlib.util.spec_from_file_location("halves", REPO / "benchmarks" / "halves.py")
    halves = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(halves)
    root = write_folders(tmp_path / "frames", n=50)  # frames 0..49
    out = tmp_path / "out"
    assert halves.main([str(root), str(out), "--split", "20", "--query-step", "3"]) == 0
    tuning = sorted(p.name for p in (out / "tuning" / "winter").iterdir())
    assert tuning == [f"frame_{i:04d}.png" for i in range(21)]
    bench = read_vpr_bench(out / "reporting", log=lambda _: None)
    refs, queries = list(range(21, 50)), list(range(21, 50, 3))
    for images, season, frames in ((bench.db, "summer", refs), (bench.query, "winter", queries)):
        expected = [read_grey(root / season / f"frame_{i:04d}.png") for i in frames]
        np.testing.assert_array_equal(images, np.stack(expected).reshape(images.shape))
    truth = bench.truth
    for n, frame in enumerate(queries):
        row = truth.indices[truth.indptr[n] : truth.indptr[n + 1]]
        assert [refs[j] for j in row] == [f for f in refs if abs(f - frame) <= 1]
    same = [str(root), str(out), "--split", "20", "--query-step", "3"]
    assert halves.main(same) == 0  # the same layouts again: nothing to do
    assert "already holds these layouts" in capsys.readouterr().out
    assert halves.main([str(root), str(out), "--split", "3"]) == 2  # nothing is overwritten
    assert "exists: name a new folder" in capsys.readouterr().err
    assert halves.main([str(tmp_path / "nowhere"), str(tmp_path / "other")]) == 2
    assert "has no folder summer/" in capsys.readouterr().err
