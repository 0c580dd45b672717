"""What a trained method kept and the learning curve (issue 46): results.csv's
``kept_epoch``, ``epochs_trained`` and ``start`` (and encoders.csv's ``kept_epoch``),
results.md's marks of a model kept at its start and of rows that are one model; and
``split.train_places``: each method fitted on that many of the training places, spread
evenly, the validation and test places unchanged, every value its own rows, drawn and
logged as a learning curve, resumed and extended like any axis."""

import csv
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import (
    TINY_MODELS,
    TINY_ROUTE,
    assert_one_line_error,
    read_run,
    run_here,
    shared_sweep,
    sweep_rows,
)
from tests.inputs import FOLDERS, write_folders
from vpr_jax.config import SplitConfig
from vpr_jax.data.pair import pair_data, with_train_places
from vpr_jax.data.route import Route
from vpr_jax.data.splits import make_split
from vpr_jax.outputs.results import read_results, swept_of

PAIR = "summer-fall"

# The FAE cannot move from its drawn weights at a step of 1e-12 (below float32's resolution
# of them), so no epoch beats its start; both its objectives start from the same weights
# and are then one model.
KEPT_ARGS = [
    *TINY_ROUTE,
    *TINY_MODELS,
    f"season_pairs={PAIR}",
    "methods=[raw,fae]",
    "fae.init=random",
    "fae.learning_rate=1e-12",
    "fae.epochs=2",
]
FAE_START = "drawn weights"

# A learning curve on the built-in route (125 training places a season). The FAE from
# drawn weights gains on the validation places at its first epoch and loses at its second,
# at both values (seeds are fixed: every time).
CURVE_ARGS = [
    *TINY_ROUTE,
    *TINY_MODELS,
    f"season_pairs={PAIR}",
    "methods=[raw,pca,fae]",
    "fae.objective=reconstruct",
    "removed_pcs=[0,5]",
    "fae.epochs=2",
]
PLACES = [20, 60]
TRAINING_PLACES = 125  # TINY_ROUTE: 150 less 15 validating, a gap of 10


def _places(values: list[int]) -> str:
    return f"split.train_places=[{','.join(map(str, values))}]"


@pytest.fixture(scope="module")
def kept(tmp_path_factory):
    """(logdir, the finished sweep) of KEPT_ARGS, once per session."""
    return shared_sweep(tmp_path_factory, "learning_kept_sweep", *KEPT_ARGS)


@pytest.fixture(scope="module")
def curve(tmp_path_factory):
    """(logdir, the finished sweep) of the learning curve over PLACES, once per session."""
    return shared_sweep(tmp_path_factory, "learning_curve_sweep", *CURVE_ARGS, _places(PLACES))


def _validation_recall(logdir: Path, run: str) -> list[float]:
    """A training run's validation recall@1 per epoch, the start (epoch 0) first."""
    events = read_run(logdir / f"{run}_training").Scalars("validation/recall_at_1")
    assert np.all(np.diff([e.step for e in events]) > 0)  # in training order
    return [e.value for e in events]


def _encoders(logdir: Path) -> dict[tuple[str, str, str], dict]:
    """encoders.csv's rows by method, objective and setting."""
    with open(logdir / "encoders.csv") as f:
        return {(e["method"], e["objective"], e["setting"]): e for e in csv.DictReader(f)}


def test_a_model_no_epoch_beat_is_kept_at_its_start_and_results_say_so(kept):
    """kept_epoch 0 with the epochs trained and the start named; empty for raw; results.md
    marks the rows, names them in one line, and says the two objectives are one model."""
    logdir, _ = kept
    rows = {(r.method, r.objective): r for r in read_results(logdir / "results.csv")}
    assert set(rows) == {("raw", ""), ("fae", "reconstruct"), ("fae", "cross_season")}
    raw = rows["raw", ""]
    assert (raw.kept_epoch, raw.epochs_trained, raw.start) == (None, None, "")
    encoders = _encoders(logdir)
    assert encoders["raw", "", ""]["kept_epoch"] == ""
    for objective in ("reconstruct", "cross_season"):
        row = rows["fae", objective]
        assert (row.kept_epoch, row.epochs_trained, row.start) == (0, 2, FAE_START)
        assert encoders["fae", objective, ""]["kept_epoch"] == "0"
        curve = _validation_recall(logdir, row.run)
        assert len(curve) == 3 and max(curve[1:]) <= curve[0]  # no epoch beat the start
        assert row.val_recall_at_1 == pytest.approx(curve[0], abs=1e-6)
    md = (logdir / "results.md").read_text()
    marked = [line for line in md.splitlines() if "(its start)" in line]
    assert len(marked) == 2 and all("| fae |" in line for line in marked), marked
    assert (
        "Kept at their start, untouched by training (no epoch beat it on the validation "
        f"places; marked its start): {PAIR} fae cross_season ({FAE_START}, 2 epochs trained); "
        f"{PAIR} fae reconstruct ({FAE_START}, 2 epochs trained)." in md
    )
    assert (
        f"{PAIR}: fae cross_season, fae reconstruct score every query identically: one model, "
        f"all kept at their start ({FAE_START})." in md
    )


def test_a_model_training_improved_keeps_its_epoch_of_best_validation_recall(curve):
    """Each FAE of the learning curve keeps the first epoch of the best validation recall@1
    its TensorBoard run logged: one past its start and before its last; no mark of a start."""
    logdir, _ = curve
    fae = [r for r in read_results(logdir / "results.csv") if r.method == "fae"]
    encoders = _encoders(logdir)
    assert len(fae) == len(PLACES)
    for row in fae:
        assert row.epochs_trained == 2 and row.start == "drawn weights"
        curve = _validation_recall(logdir, row.run)
        assert len(curve) == row.epochs_trained + 1
        assert row.kept_epoch == curve.index(max(curve))
        assert 0 < row.kept_epoch < row.epochs_trained  # beat the start, not the last epoch
        assert row.val_recall_at_1 == pytest.approx(max(curve), abs=1e-6)
        assert encoders["fae", "reconstruct", row.setting]["kept_epoch"] == str(row.kept_epoch)
    md = (logdir / "results.md").read_text()
    assert "(its start" not in md and "Kept at their start" not in md


def test_a_trained_model_is_compared_with_its_start_on_the_same_queries(curve, kept):
    """results.md's trained-against-start table: the FAEs of the learning curve left their
    drawn start, whose recall@1 is what the same drawn weights score untrained (the kept
    sweep's FAE, which no step could move, on the same test queries); the paired difference
    is the mean of the per-query differences, its interval around it. A model kept at its
    start is its start: 0."""
    logdir, _ = curve
    untrained = {
        r.objective: r for r in read_results(kept[0] / "results.csv") if r.method == "fae"
    }["reconstruct"]
    md = (logdir / "results.md").read_text()
    assert "## Trained against their start" in md
    table = md.split("## Trained against their start")[1].split("\n## ")[0]
    for row in (r for r in read_results(logdir / "results.csv") if r.method == "fae"):
        with np.load(logdir / row.run / "curve.npz") as z:
            start, mine = z["start_correct"], z["best_correct"]
        assert start.mean() == pytest.approx(untrained.recall_at_1, abs=1e-9)
        line = next(ln for ln in table.splitlines() if f"| {row.setting} |" in ln)
        cells = [c.strip() for c in line.strip("|").split("|")]
        assert cells[5] == f"{row.kept_epoch} of {row.epochs_trained}"
        assert float(cells[7]) == pytest.approx(untrained.recall_at_1, abs=5e-4)
        value, low, high = (float(x) for x in re.findall(r"[-+]\d\.\d{3}", cells[8]))
        assert value == pytest.approx(mine.mean() - start.mean(), abs=5e-4)
        assert low <= value <= high
    kept_md = (kept[0] / "results.md").read_text()
    assert kept_md.count("0 (the start itself)") == 2  # both objectives' FAE


def _route(n: int) -> Route:
    """Constant images that say their place and season: summer f / 1000, fall 0.5 + f / 1000."""
    ids = np.arange(n, dtype=np.int64) * 3 + 7
    summer = np.broadcast_to((ids / 1000.0)[:, None, None], (n, 32, 64)).astype(np.float32)
    return Route(ids, {"summer": summer, "fall": summer + np.float32(0.5)})


def test_with_train_places_thins_the_training_places_evenly_and_nothing_else():
    route = _route(200)
    split = make_split(route.frame_ids, SplitConfig(n_train=120, n_test=40, gap=5))
    pair = pair_data(route, split, "summer", "fall", "test", 2)
    n = len(split.train)
    assert with_train_places(pair, None) is pair
    for places in (2, 7, 33, n):
        thinned = with_train_places(pair, places)
        for field in pair._fields:
            if field != "train":  # validation and test places, ground truth: the same objects
                assert getattr(thinned, field) is getattr(pair, field), field
        a, b = thinned.aligned_train
        assert len(a) == len(b) == places and len(thinned.train) == 2 * places
        kept_ids = np.round(a[:, 0, 0] * 1000).astype(int)
        np.testing.assert_array_equal(b[:, 0, 0], a[:, 0, 0] + np.float32(0.5))  # same places
        train_ids = route.frame_ids[split.train]
        assert set(kept_ids) <= set(train_ids) and (np.diff(kept_ids) > 0).all()
        assert kept_ids[0] == train_ids[0] and kept_ids[-1] == train_ids[-1]  # the ends
        steps = np.diff(np.searchsorted(train_ids, kept_ids))
        assert steps.max() - steps.min() <= 1  # spread evenly
    np.testing.assert_array_equal(with_train_places(pair, n).train, pair.train)
    database = pair._replace(train=pair.db, aligned_training=False)  # trained on its database
    assert len(with_train_places(database, 9).train) == 9
    with pytest.raises(ValueError, match=f"exceeds the {n} training places"):
        with_train_places(pair, n + 1)


def _assert_learning_curve(
    logdir: Path, places: list[int], methods: set[str], pair: str = PAIR
) -> None:
    """A row per method per value of training places, each fitted on that many places of
    both seasons, each value's own selection; one protocol and test set throughout; the
    learning-curve table and figure."""
    rows = read_results(logdir / "results.csv")
    values = {(r.method, swept_of(r)["train_places"]) for r in rows}
    assert values == {(m, p) for m in methods for p in places}
    for r in rows:
        p = swept_of(r)["train_places"]
        assert f"train_places={p}" in r.setting and r.n_train == 2 * p
    for m in methods:
        for p in places:
            mine = [r for r in rows if r.method == m and swept_of(r)["train_places"] == p]
            assert sum(r.selected for r in mine) == 1, (m, p)
    assert len({r.protocol for r in rows}) == 1 and len({r.n_test for r in rows}) == 1
    md = (logdir / "results.md").read_text()
    head = "| season_pair | method | objective | setting | " + " | ".join(
        f"{p} places" for p in places
    )
    assert "## Learning curves" in md and head in md
    table = md.split("## Learning curves", 1)[1].split("\n## ", 1)[0]
    lines = [line for line in table.splitlines() if line.startswith(f"| {pair} |")]
    assert sorted(line.split(" | ")[1] for line in lines) == sorted(methods)
    figure = cv2.imread(str(logdir / "figures" / "learning_curves.png"))
    assert figure is not None and figure.ndim == 3 and min(figure.shape[:2]) > 100


def test_train_places_is_a_learning_curve_in_results_figures_and_tensorboard(curve):
    logdir, _ = curve
    _assert_learning_curve(logdir, PLACES, {"raw", "pca", "fae"})
    rows = read_results(logdir / "results.csv")
    pca = [r for r in rows if r.method == "pca" and r.selected]
    recall = {swept_of(r)["train_places"]: r.recall_at_1 for r in pca}
    tb = read_run(logdir / "compare" / "pca")
    events = tb.Scalars(f"{PAIR}/linear/by_training_places/recall_at_1")
    assert [e.step for e in events] == sorted(recall) == PLACES
    assert [e.value for e in events] == pytest.approx([recall[p] for p in PLACES], abs=1e-6)
    # The other charts show the largest value of training places.
    largest = {
        r.removed_pcs: r.recall_at_1
        for r in rows
        if r.method == "pca" and swept_of(r)["train_places"] == max(PLACES)
    }
    events = tb.Scalars(f"{PAIR}/linear/recall_at_1")
    assert {e.step: e.value for e in events} == pytest.approx(largest, abs=1e-6)


def _copy(logdir: Path, to: Path) -> Path:
    """The shared sweep's logdir and models, to resume in this test's folder."""
    shutil.copytree(logdir.parent / "checkpoints", to / "checkpoints")
    return Path(shutil.copytree(logdir, to / "runs"))


def test_a_learning_curve_resumes_and_a_value_added_adds_only_its_cells(curve, tmp_path):
    logdir, _ = curve
    copy = _copy(logdir, tmp_path)
    before = read_results(copy / "results.csv")
    rows, proc = sweep_rows(*CURVE_ARGS, _places(PLACES), f"logdir={copy}")
    n = len(before)
    assert f"resuming: {n} of {n} cells already in results.csv" in proc.stdout
    assert "epoch" not in proc.stdout  # nothing trained again
    assert rows == before
    more = [*PLACES, TRAINING_PLACES]
    after, proc = sweep_rows(*CURVE_ARGS, _places(more), f"logdir={copy}")
    new = [r for r in after if swept_of(r)["train_places"] == TRAINING_PLACES]
    assert len(after) == n + len(new) and {r.method for r in new} == {"raw", "pca", "fae"}
    assert f"resuming: {n} of {len(after)} cells already in results.csv" in proc.stdout
    old = {r.run: r for r in after if r.run in {b.run for b in before}}
    assert [old[b.run] for b in before] == before  # each value its own selection
    assert f"fae_train_places={PLACES[0]} epoch" not in proc.stdout  # only the new one trains
    _assert_learning_curve(copy, more, {"raw", "pca", "fae"})


def test_train_places_on_a_folder_route_up_to_every_training_place(tmp_path):
    """A folder of frames (25 training places a season): a learning curve up to all of
    them; one more is refused."""
    root = write_folders(tmp_path / "frames")
    args = [*FOLDERS, f"data.root={root}"]  # raw pixels: their training mean
    proc = run_here(*args, "split.train_places=[4,25]", f"logdir={tmp_path / 'runs'}")
    assert proc.returncode == 0, proc.stderr
    _assert_learning_curve(tmp_path / "runs", [4, 25], {"raw"}, pair="summer-winter")
    proc = run_here(*args, "split.train_places=[4,26]", f"logdir={tmp_path / 'more'}")
    assert_one_line_error(proc, "split.train_places", "25 training places")
    assert not (tmp_path / "more").exists()


def test_more_training_places_than_a_season_has_are_refused_in_one_line(tmp_path):
    logdir = tmp_path / "runs"
    too_many = TRAINING_PLACES + 1
    proc = run_here(
        *TINY_ROUTE,
        f"season_pairs={PAIR}",
        "methods=[raw]",
        f"split.train_places=[20,{too_many}]",
        f"logdir={logdir}",
    )
    assert_one_line_error(proc, "split.train_places", f"{TRAINING_PLACES} training places")
    assert not logdir.exists()
