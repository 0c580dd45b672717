"""What leaves a sweep and what comes in, end to end on a small VPR-Bench folder the test
writes: ``python -m experiments.export`` checked from its files alone (numpy and the csv
module: the way another pipeline reads them), outside descriptors (``precomputed``) scored
against numpy, the default counts trimmed to a small benchmark, and the method-by-method
TensorBoard runs read back with TensorBoard's reader."""

from __future__ import annotations

import csv
import json
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from experiments import sweep
from tests.conftest import (
    PROCESS_TIMEOUT_S,
    LogLines,
    assert_one_line_error,
    env_with_repo,
    read_run,
    run_here,
    run_process,
    shared_folder,
)
from tests.inputs import N_PLACES, read_grey, write_vpr_bench
from vpr_jax.data.synthetic import synthetic_route
from vpr_jax.errors import UserError

TINY_MODELS = ["fae.hidden=32", "train.epochs=2", "fae.epochs=2"]


def in_process(main, argv: list[str], capsys) -> subprocess.CompletedProcess:
    """A CLI's ``main(argv)`` run in this process, as the finished process it would be: its
    refusals come before JAX loads, so this is the CLI a user runs, without the start-up of
    a fresh interpreter (the sweep's SIGTERM handler is put back afterwards)."""
    handler = signal.getsignal(signal.SIGTERM)
    try:
        code = main(argv)
    finally:
        signal.signal(signal.SIGTERM, handler)
    out, err = capsys.readouterr()
    return subprocess.CompletedProcess(argv, code, out, err)


def export_cli(*args: str):
    return run_process(
        [sys.executable, "-m", "experiments.export", *args],
        env=env_with_repo(),
        timeout=PROCESS_TIMEOUT_S,
    )


def _bench(folder: Path) -> None:
    """The benchmark, numpy's descriptors of it, a sweep of raw, pca, ica and a tiny FAE
    plus two outside sets and sequences of 4, and its export."""
    route = synthetic_route(N_PLACES, ("summer", "fall"), seed=3)
    root = folder / "bench"
    refs, queries, rows = write_vpr_bench(root, route, drop_rows={7})
    db = np.stack([read_grey(root / "ref" / r) for r in refs])
    query = np.stack([read_grey(root / "query" / q) for q in queries])
    mean = db.mean(axis=0)
    for name, (a, b) in {"centred": (db - mean, query - mean), "pixels": (db, query)}.items():
        np.save(folder / f"{name}_db.npy", a.astype(np.float32))
        np.save(folder / f"{name}_q.npy", b.astype(np.float32))
    truth = {n: sorted(near) for n, near in rows}
    (folder / "truth.json").write_text(
        json.dumps({"refs": refs, "queries": queries, "truth": truth})
    )
    sweep = run_here(  # in this process; the export below runs as a user runs it
        "data.source=vpr_bench",
        f"data.root={root}",
        "methods=[raw,pca,ica,fae]",
        "removed_pcs=[0,5,50]",
        *TINY_MODELS,
        "sequence.enabled=true",
        "sequence.ds=[1,4]",
        f"precomputed.centred.database={folder / 'centred_db.npy'}",
        f"precomputed.centred.queries={folder / 'centred_q.npy'}",
        f"precomputed.pixels.database={folder / 'pixels_db.npy'}",
        f"precomputed.pixels.queries={folder / 'pixels_q.npy'}",
        f"logdir={folder / 'runs'}",
    )
    assert sweep.returncode == 0, sweep.stderr
    export = export_cli(str(folder / "runs"), f"out={folder / 'export'}")
    assert export.returncode == 0, export.stderr
    (folder / "outputs.json").write_text(json.dumps([sweep.stdout, export.stdout]))


@pytest.fixture(scope="module")
def bench(tmp_path_factory) -> Path:
    return shared_folder(tmp_path_factory, "exported_bench", _bench)


def results(folder: Path) -> list[dict]:
    with open(folder / "runs" / "results.csv", newline="") as f:
        return list(csv.DictReader(f))


def exported(bench: Path) -> dict[str, dict]:
    """Each exported folder of the selected rows, by folder name: its results.csv row."""
    out = {}
    for row in results(bench):
        if row["selected"] == "1":
            name = row["run"].split("/", 1)[1]
            if row["method"] in ("pca", "ica"):
                name = re.sub(r"_k\d{3}", "", name)
            out[name] = row
    return out


def read_pairs(folder: Path) -> tuple[list[str], list[list[str]]]:
    """(queries in queries.txt's order, each query's database names from pairs.txt)."""
    queries = (folder / "queries.txt").read_text().split()
    lists: dict[str, list[str]] = {q: [] for q in queries}
    for line in (folder / "pairs.txt").read_text().splitlines():
        query, db = line.split()
        lists[query].append(db)
    return queries, [lists[q] for q in queries]


def _plan(bench: Path, logdir: Path, *args: str):
    from experiments.plan import make_plan
    from vpr_jax.command_line import given_keys, parse_config

    argv = ["data.source=vpr_bench", f"data.root={bench / 'bench'}", f"logdir={logdir}", *args]
    notes = LogLines()
    return make_plan(parse_config(argv), notes, given_keys(argv)).cfg, notes


def test_a_small_benchmark_runs_on_the_default_counts(bench, tmp_path):
    """120 training images serve 119 components: ica.n_components=128 with removed_pcs up
    to 100 cannot all fit, so the default ICA size is capped (one note) and every default
    count runs; set on the command line, the counts are kept or refused, never changed."""
    cfg, notes = _plan(bench, tmp_path)
    assert [n for n in notes if n.startswith("note: ica")] == [
        "note: ica.n_components=128 capped to 19: PCA of 120 training images has 119 "
        "components and removed_pcs goes up to 100 (set ica.n_components to choose)"
    ]
    assert cfg.removed_pcs == (0, 5, 10, 20, 50, 100) and cfg.ica["n_components"] == 19
    cfg, notes = _plan(bench, tmp_path, "ica.n_components=100")  # ICA's counts give way to it
    every = [0, 5, 10, 20, 50, 100]  # pca keeps every count: only ICA's size takes room
    assert cfg.ica["removed_pcs"] == [0, 5, 10] and cfg.pca["removed_pcs"] == every
    assert (
        "note: ica removed_pcs=20 left out: PCA of 120 training images has 119 components, "
        "100 of them for ICA (ica.n_components) (set removed_pcs to choose)"
    ) in notes
    with pytest.raises(UserError, match="ica.n_components=100 with removed_pcs up to 50"):
        _plan(bench, tmp_path, "ica.n_components=100", "removed_pcs=[0,50]")
    ica = {int(r["removed_pcs"]) for r in results(bench) if r["method"] == "ica"}
    assert ica == {0, 5, 50}  # the sweep ran with the capped size


def test_the_top_of_pairs_txt_reproduces_the_sweeps_recall(bench):
    """From the exported files and the benchmark's ground truth only: every method's (and
    sequence cell's) first line per query scores results.csv's recall@1."""
    facts = json.loads((bench / "truth.json").read_text())
    position = {f"ref/{name}": i for i, name in enumerate(facts["refs"])}
    truth = {f"query/{facts['queries'][int(n)]}": set(near) for n, near in facts["truth"].items()}
    chosen = exported(bench)
    assert {"raw", "pca", "ica", "fae", "centred", "pixels", "pca_ds04"} <= set(chosen)
    for name, row in chosen.items():
        queries, lists = read_pairs(bench / "export" / "ref-query" / name)
        assert len(queries) == int(row["n_test"]) and all(len(m) == 10 for m in lists), name
        hits = [position[m[0]] in truth.get(q, set()) for q, m in zip(queries, lists, strict=True)]
        assert np.mean(hits) == pytest.approx(float(row["recall_at_1"]), abs=1e-9), name
        scores = list(csv.DictReader(open(bench / "export" / "ref-query" / name / "scores.csv")))
        assert [s["database"] for s in scores[:10]] == lists[0]
        assert [int(s["correct"]) for s in scores[::10]] == [int(h) for h in hits]


def test_exported_descriptors_rematched_by_numpy_give_the_same_best_match(bench):
    chosen = exported(bench)
    for name in (n for n in chosen if "_ds" not in n):
        folder = bench / "export" / "ref-query" / name
        db, query = np.load(folder / "database.npy"), np.load(folder / "queries.npy")
        assert db.dtype == query.dtype == np.float32 and len(db) == N_PLACES
        db_names = (folder / "database.txt").read_text().split()
        db, query = (
            x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)
            for x in (db.astype(np.float64), query.astype(np.float64))
        )
        cosine = query @ db.T
        _, lists = read_pairs(folder)
        top = np.array([db_names.index(m[0]) for m in lists])
        best = np.argmax(cosine, axis=1)
        rows = np.arange(len(top))  # the same best match, or one that ties with it
        np.testing.assert_allclose(cosine[rows, top], cosine[rows, best], atol=1e-6, err_msg=name)
    sequence = bench / "export" / "ref-query" / "pca_ds04"
    assert not list(sequence.glob("*.npy")) and (sequence / "pairs.txt").is_file()


def read_global_feats(path: Path, names: list[str]) -> tuple[np.ndarray, list[str]]:
    """(each name's ``global_descriptor``, float32 checked, as hloc reads it; the path of
    every dataset in the file, from which hloc lists the names)."""
    import h5py

    datasets = []
    with h5py.File(path, "r") as f:
        f.visititems(
            lambda key, obj: datasets.append(key) if isinstance(obj, h5py.Dataset) else None
        )
        for n in names:
            assert f[n]["global_descriptor"].dtype == np.float32, n
        return np.stack([f[n]["global_descriptor"][()] for n in names]), datasets


def test_global_feats_h5_holds_the_npy_rows_normalised_in_hlocs_layout(bench):
    """Read as hloc reads it (a group per name, its ``global_descriptor``; hloc lists the
    names from the datasets): every name of database.txt and queries.txt, hence of
    pairs.txt, and nothing else; unit rows equal to the .npy rows normalised by numpy; the
    plain dot product hloc ranks by puts each query's first pairs.txt line first."""
    chosen = exported(bench)
    for name in (n for n in chosen if "_ds" not in n):
        folder = bench / "export" / "ref-query" / name
        queries, lists = read_pairs(folder)
        db_names = (folder / "database.txt").read_text().split()
        assert {m for matched in lists for m in matched} <= set(db_names)
        rows, found = read_global_feats(folder / "global-feats.h5", [*db_names, *queries])
        db, query = rows[: len(db_names)], rows[len(db_names) :]
        assert sorted(found) == sorted(f"{n}/global_descriptor" for n in [*db_names, *queries])
        for got, npy in ((db, "database.npy"), (query, "queries.npy")):
            x = np.load(folder / npy).astype(np.float64)
            np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-6, err_msg=name)
            normalised = x / np.linalg.norm(x, axis=1, keepdims=True)
            np.testing.assert_allclose(got, normalised, rtol=1e-6, atol=1e-7, err_msg=name)
        best = np.argmax(query @ db.T, axis=1)
        assert [db_names[b] for b in best] == [matched[0] for matched in lists], name
        readme = (folder / "README.txt").read_text()
        assert "as the encoder produced them (not normalised" in readme
        assert "L2-normalised" in readme and "hloc.pairs_from_retrieval" in readme
        assert re.search(rf"^protocol +{chosen[name]['protocol']} \(results\.csv", readme, re.M)
    assert not (bench / "export" / "ref-query" / "pca_ds04" / "global-feats.h5").exists()


def test_a_name_on_both_sides_is_refused_not_renamed(tmp_path):
    """hloc keys global-feats.h5 by name: a database and a query image of one name cannot
    both be stored under it, so the file is refused (one line) rather than renamed."""
    from vpr_jax.outputs import export as files

    db_names = np.array(["ref/a.png", "same.png"], dtype=object)
    query_names = np.array(["same.png"], dtype=object)
    rows = np.ones((2, 4), np.float32)
    with pytest.raises(UserError, match="image same.png is both a database and a query name"):
        files.write_global_features(tmp_path, db_names, rows, query_names, rows[:1])
    assert not (tmp_path / "global-feats.h5").exists()


def test_each_exported_folder_is_an_encoder_that_reproduces_its_descriptors(bench, tmp_path):
    """Moved elsewhere, every folder loads with vpr_jax.load_encoder; encoding the images
    its txt files name gives its .npy rows. A set of outside descriptors is an encoder of
    the benchmark's own images: their rows, and NaN for an image it does not describe."""
    from vpr_jax import load_encoder

    chosen = exported(bench)
    encoders = [n for n in chosen if "_ds" not in n]
    assert sorted(encoders) == ["centred", "fae", "ica", "pca", "pixels", "raw"]
    for name in encoders:
        moved = shutil.copytree(bench / "export" / "ref-query" / name, tmp_path / name)
        encode, params = load_encoder(moved)
        for side in ("database", "queries"):
            names = (moved / f"{side}.txt").read_text().split()
            images = np.stack([read_grey(bench / "bench" / n).reshape(32, 64) for n in names])
            expected = np.load(moved / f"{side}.npy")
            got = np.asarray(encode(params, images.astype(np.float32)))
            scale = np.abs(expected).max()
            np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-5 * scale, err_msg=name)
    encode, params = load_encoder(tmp_path / "centred")
    unseen = np.random.default_rng(0).random((2, 32, 64), np.float32)
    assert np.isnan(np.asarray(encode(params, unseen))).all()


def test_outside_descriptors_score_the_recall_numpy_computes(bench):
    """Raw pixels centred on the database mean, computed by numpy and fed as precomputed:
    recall@1 on the test queries equals numpy's cosine best match."""
    facts = json.loads((bench / "truth.json").read_text())
    rows = {r["method"]: r for r in results(bench) if r["ds"] == "1"}
    n_test = int(rows["centred"]["n_test"])
    db, query = np.load(bench / "centred_db.npy"), np.load(bench / "centred_q.npy")[:n_test]
    cosine = (query / np.linalg.norm(query, axis=1, keepdims=True)) @ (
        db / np.linalg.norm(db, axis=1, keepdims=True)
    ).T
    best = np.argmax(cosine, axis=1)
    hits = [b in set(facts["truth"].get(str(n), [])) for n, b in enumerate(best)]
    assert float(rows["centred"]["recall_at_1"]) == pytest.approx(np.mean(hits), abs=1e-9)
    assert float(rows["centred"]["recall_at_1"]) == pytest.approx(
        float(rows["raw"]["recall_at_1"]), abs=1e-9
    )  # the same descriptors as the suite's raw pixels
    assert 0.0 <= float(rows["pixels"]["val_recall_at_1"]) <= 1.0
    assert rows["centred"]["fit_seconds"] == "nan"


def test_every_setting_exports_under_its_run_name(bench, tmp_path, capsys):
    """In this process (the bench fixture runs the export in a fresh interpreter)."""
    from experiments import export

    out = tmp_path / "all"
    argv = [str(bench / "runs"), f"out={out}", "all_settings=true"]
    proc = in_process(export.main, [*argv, "top_k=3"], capsys)
    assert proc.returncode == 0, proc.stderr
    names = {p.name for p in (out / "ref-query").iterdir()}
    assert {"pca_k000", "pca_k050", "ica_k050", "raw", "pca_k005_ds04"} <= names
    _, lists = read_pairs(out / "ref-query" / "pca_k050")
    assert {len(m) for m in lists} == {3}
    again = in_process(export.main, argv, capsys)
    assert_one_line_error(again, f"out={out} is not empty", "overwrite=true")
    assert {len(m) for m in read_pairs(out / "ref-query" / "pca_k050")[1]} == {3}  # kept


@pytest.mark.parametrize(
    "args, words",
    [
        ([], ["name one logdir"]),
        (["{tmp}", "top_k=0"], ["top_k=0"]),
        (["{tmp}", "format=hloc"], ["unknown option format"]),
        (["{tmp}"], ["holds no sweep"]),
        (["{tmp}", "all_settings=yes"], ["all_settings=yes is not true or false"]),
    ],
)
def test_export_refuses_bad_input_in_one_line(tmp_path, capsys, args, words):
    from experiments import export

    proc = in_process(export.main, [a.replace("{tmp}", str(tmp_path)) for a in args], capsys)
    assert_one_line_error(proc, *words)
    assert not (tmp_path / "export").exists()


def _bad(path: Path, case: str) -> None:
    good = np.ones((N_PLACES, 8), np.float32)
    if case == "rows":
        np.save(path, good[:-3])
    elif case == "nan":
        good[17, 2] = np.nan
        np.save(path, good)
    elif case == "dtype":
        np.save(path, good.astype(np.int32))
    elif case == "pickle":
        np.save(path, np.array([good, "x"], dtype=object), allow_pickle=True)


@pytest.mark.parametrize(
    "case, words",
    [
        ("rows", ["has 117 rows", "ref/ holds 120 images", "sorted file order"]),
        ("nan", ["row 17 (ref/r113.png) holds NaN"]),
        ("dtype", ["holds int32 values", "numpy.save"]),
        ("pickle", ["pickled Python objects"]),
    ],
)
def test_outside_descriptors_that_cannot_serve_are_one_line(bench, tmp_path, capsys, case, words):
    bad = tmp_path / "bad.npy"
    _bad(bad, case)
    argv = [
        "data.source=vpr_bench",
        f"data.root={bench / 'bench'}",
        "methods=[raw]",
        f"precomputed.database={bad}",
        f"precomputed.queries={bench / 'centred_q.npy'}",
        f"logdir={tmp_path / 'runs'}",
    ]
    proc = in_process(sweep.main, argv, capsys)
    assert_one_line_error(proc, f"precomputed.database={bad}", *words)
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize(
    "args, words",
    [
        (["precomputed.database=a.npy", "precomputed.queries=b.npy"], ["benchmark sources"]),
        (
            [
                "data.source=vpr_bench",
                "data.root=x",
                "precomputed.database=a.npy",
                "precomputed.x.queries=b",
            ],
            ["cannot be mixed"],
        ),
        (
            ["data.source=vpr_bench", "data.root=x", "precomputed.database=a.npy"],
            ["has no queries"],
        ),
        (
            ["data.source=vpr_bench", "data.root=x", "methods=[raw,precomputed]"],
            ["no descriptors are given"],
        ),
        (
            [
                "data.source=vpr_bench",
                "data.root=x",
                "precomputed.pca.database=a",
                "precomputed.pca.queries=b",
            ],
            ["precomputed set 'pca' has the name of a method"],
        ),
    ],
)
def test_bad_precomputed_settings_are_one_line(tmp_path, capsys, args, words):
    proc = in_process(sweep.main, [*args, f"logdir={tmp_path / 'runs'}"], capsys)
    assert_one_line_error(proc, *words)


def test_the_method_by_method_runs_hold_each_pair(small_sweep):
    """LOGDIR/compare/<method>, read back with TensorBoard's reader: per pair a PR curve
    and recall@1 / AUC-PR against the removed-PC count (a flat line for the methods
    without that axis), the values of results.csv."""
    logdir, _ = small_sweep
    with open(logdir / "results.csv", newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["ds"] == "1"]
    pairs = {r["season_pair"] for r in rows}
    labels = {
        r["method"] + (f"_{r['objective']}" if r["objective"] not in ("", "reconstruct") else "")
        for r in rows
    }
    assert {p.name for p in (logdir / "compare").iterdir()} == labels
    for label in labels:
        run = read_run(logdir / "compare" / label)
        group = "autoencoders" if label.startswith(("fae", "cae")) else "linear"
        assert set(run.Tags()["tensors"]) == {f"pr_curve/{p}/{group}" for p in pairs}
        for pair in pairs:
            recall = {e.step: e.value for e in run.Scalars(f"{pair}/{group}/recall_at_1")}
            assert sorted(recall) == [0, 5, 20], label
            mine = [
                r
                for r in rows
                if r["season_pair"] == pair
                and r["method"] == label.split("_cross")[0]
                and (r["objective"] == "cross_season") == label.endswith("cross_season")
            ]
            if len(mine) == 1:  # no removed-PC axis: flat
                flat = float(mine[0]["recall_at_1"])
                assert all(v == pytest.approx(flat) for v in recall.values()), label
            else:
                for r in mine:
                    assert recall[int(r["removed_pcs"])] == pytest.approx(float(r["recall_at_1"]))
