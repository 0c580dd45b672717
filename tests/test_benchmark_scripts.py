"""Every script in benchmarks/ runs: each is run as its ``__main__`` with ``--tiny`` (a
seconds-long run on data too small for its figures to mean anything), and must finish with
exit code 0 and print the lines only a finished measurement prints (its ratios, its table),
and where a script compares two computations of the same thing, their agreement.
An API change that breaks a benchmark then fails here instead of waiting for the next person
who runs it. (halves.py is tested in test_benchmarks.py.)"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO, env_with_repo, run_process
from tests.inputs import write_folders

BENCHMARKS = REPO / "benchmarks"
RATIO = r"ratio\s+\d+\.\d+x"  # common.ratio_row's ratio column


def run_script(name: str, *args: str):
    """``python benchmarks/NAME ARGS`` in a fresh interpreter, in the repository; asserts
    it succeeded and returns its stdout."""
    proc = run_process([sys.executable, str(BENCHMARKS / name), *args], env=env_with_repo())
    assert proc.returncode == 0, (proc.stdout[-3000:], proc.stderr[-3000:])
    return proc.stdout


def run_here(capfd, name: str, *args: str) -> str:
    """``python benchmarks/NAME ARGS`` run as its ``__main__`` in this process (benchmarks/
    first on ``sys.path``, as for a script; ``capfd``: the test's captured output, also of
    the processes it starts); asserts it succeeded and returns its stdout. A fresh
    interpreter would pay JAX's import and its compilations again, most of a tiny run."""
    saved = list(sys.path)
    sys.path[:0] = [str(BENCHMARKS)]
    capfd.readouterr()
    try:
        from common import run_script

        code = run_script(BENCHMARKS / name, list(args))
    finally:
        sys.path[:] = saved
    out, err = capfd.readouterr()
    assert code == 0, (out[-3000:], err[-3000:])
    return out


def line_matching(out: str, pattern: str) -> str:
    """The first line of ``out`` that ``pattern`` matches (searched in each line)."""
    for line in out.splitlines():
        if re.search(pattern, line):
            return line
    raise AssertionError(f"no line matches {pattern!r} in:\n{out[-3000:]}")


def number(out: str, pattern: str) -> float:
    """The number ``pattern``'s first group reads in the first line of ``out`` it matches."""
    return float(re.search(pattern, line_matching(out, pattern)).group(1))


@pytest.fixture(scope="module")
def device_check_run(tmp_path_factory) -> tuple[str, Path]:
    """What ``device_check.py --tiny`` prints, on the CPU, where the "device" is the CPU,
    and its ``--out`` folder. Its last step is ``run_all.py --tiny --skip-scaling``, which
    test_run_all reads (its table as JSON: ``run_all.json`` there)."""
    out = tmp_path_factory.mktemp("device_check")
    return run_script("device_check.py", "--tiny", "--out", str(out)), out


@pytest.fixture(scope="module")
def device_check_out(device_check_run) -> str:
    return device_check_run[0]


def test_device_check(device_check_out):
    """Its oracle tests pass, its two tiny sweeps agree to the digit, and run_all's table
    names the device."""
    out = device_check_out
    line_matching(out, r"^device: .+ \(cpu\), jax \d")
    line_matching(out, r"^\d+ passed in ")
    line_matching(out, r"^  2 cells compared: 0 differences .*recall@1 0\.0000, AUC-PR 0\.0000$")
    line_matching(out, r"^jax \S+ on cpu ")
    line_matching(out, r"^device check passed on ")


def test_run_all(device_check_run):
    """Every row but the scaling exponents: those are scaling.py's ``measure`` at the same
    tiny lengths (test_scaling), three more fresh processes this test leaves out. The CPU
    is named, and the JSON holds the table as printed."""
    printed, folder = device_check_run
    out = printed[printed.index("3. run_all") :]
    cpu = line_matching(out, r"^cpu: .+, \d+ cores$").removeprefix("cpu: ")
    table_json = json.loads((folder / "run_all.json").read_text())
    assert table_json["cpu"] == cpu and table_json["jax"] and table_json["date"]
    for row in table_json["rows"]:
        line_matching(out, "^" + re.escape(row["what"]) + r"\s+" + re.escape(row["ours"]))
    assert len(table_json["rows"]) >= 14
    header = line_matching(out, r"^what\s+ours\s+peer, same run\s+ratio\s+goal\s+met$")
    table = out[out.index(header) :]
    for row in (
        "PCA fit, every component, 300 x 256",
        "FastICA, 8 components",
        "matching, top-10 of 100 x 100",
        "  the same at matching.precision=default",
        "sequence matching ds=10, 100 x 100",
        "encode ICA (8)",
        "encode CAE calc (64,128) c8",
        "paper protocol, tiny",
        "encode raw on gradients (6,804 values)",
        "encode raw on standardised+gradients (8,852 values)",
        "  PCA fit on it, 200 of 300 x 8,852",
        "  the transform of the training images",
    ):
        line_matching(table, "^" + re.escape(row) + r"\s.*\d+\.\d{3}x\s+<= [\d.]+x\s+(yes|no)")
    assert "whole route (preset=full) peak RSS: left out with --tiny" in out
    # pca at two removed-PC counts and the FAE
    line_matching(out, r"^  3 cells, peak RSS \d+\.\d+ GiB; training seconds \{'fae': \d")
    line_matching(out, r"^total \d+ s; the table as JSON: ")


def test_bench_linear(capfd):
    out = run_here(capfd, "bench_linear.py", "--tiny")
    assert "train (300, 256), queries 100 x database 100" in out
    for row in (
        "PCA fit ",
        "PCA fit, 100 components",
        "removed-PC sweep, 6 counts",
        "the same with the PCA fit",
        "matching, top-10 cosine",
        "metrics, 100 top-10 lists of 2000",
    ):
        line_matching(out, re.escape(row) + ".*" + RATIO)
    line_matching(out, r"PCA encode \(100 \+ residual\)\s+\d+\.\d+ ms per image")


def test_bench_ica(capfd):
    out = run_here(capfd, "bench_ica.py", "--tiny")
    line_matching(out, r"images, 8 ICs\s+ours \(JAX\)\s+\d+\.\d+\s+\d+")
    line_matching(out, r"sklearn whiten_solver=eigh\s+\d+\.\d+\s+\d+\s+\d+\.\d+x")
    line_matching(out, r"Known sources mixed into 300 x 256")
    # The known-source problem's lines: Amari distance of each unmixing from the true mixing
    # (0: every component one source; a random 8 x 256 unmixing gives 0.28-0.39), and the
    # peer's speed-up. test_ica.py's rule: ours separates the sources, as well as
    # scikit-learn does (the same contrast and tol on the same data) to 5%.
    ours = number(out, r"sources\s+ours \(JAX\)\s+\d+\.\d+\s+\d+\s+(\d\.\d{4})$")
    peer = number(out, r"sklearn whiten_solver=svd\s+\d+\.\d+\s+\d+\s+\d+\.\d+x\s+(\d\.\d{4})$")
    assert ours < 0.1 and ours <= 1.05 * peer + 1e-3, (ours, peer)


def test_bench_sequence(capfd):
    out = run_here(capfd, "bench_sequence.py", "--tiny")
    line_matching(out, r"^100 x 100 ds=10 .*" + RATIO)
    line_matching(out, r"^100 x 1,000 \(full\) ds=10 .*" + RATIO)
    # Both searches run on the same similarities (ours rounded to float32): only a near-tie,
    # broken the other way by that rounding, can part them; allowed: one query in 100.
    agree = re.findall(r"best match agrees with numpy for (\d+\.\d)% of queries", out)
    assert len(agree) == 2 and all(float(a) >= 99.0 for a in agree), agree


def test_bench_autoencoders(capfd):
    out = run_here(capfd, "bench_autoencoders.py", "--tiny")
    assert "Encode 100 database + 100 query images" in out
    assert "Training: 270 images, batch 16 (16 steps/epoch)" in out
    for model in ("FAE hidden 256", "CAE fast (24,48) s2d2", "CAE quick (16,32)", "CAE calc"):
        line_matching(out, "^" + re.escape(model) + r".*\d+\.\d{4}x\s+(yes|NO)$")  # encode
        line_matching(out, "^" + re.escape(model) + r".*2/16 \(extrapolated\).*\d+\.\d{5}$")
    line_matching(out, r"^total \d+\.\d s$")


def test_peers():
    """A peer alone, on the tiny data its benchmark builds: one JSON line."""
    out = run_script("peers.py", "fastica_256", "--tiny", "--repeats", "1")
    report = json.loads(out.strip().splitlines()[-1])
    assert report["task"] == "fastica_256"
    assert report["seconds"] > 0 and report["first"] > 0 and report["blas"]


def test_scaling(tmp_path, capfd):
    plot = tmp_path / "scaling.png"
    out = run_here(capfd, "scaling.py", "--tiny", "--plot", str(plot))
    for n, queries in ((200, 20), (400, 40)):
        line_matching(out, rf"matching n={n} \({queries} queries\): \d+\.\d+ s, working memory")
        line_matching(out, rf"raw\+pca sweep n={n}: \d+\.\d s, peak RSS \d+\.\d+ GiB")
    for fit in ("matching time", "matching memory", "sweep time", "sweep peak RSS"):
        line_matching(out, rf"^{fit} ~ n\^-?\d+\.\d+ ")
    assert plot.stat().st_size > 0


def test_cluster(cluster_benchmark):
    """The five rows, the three speed-ups against their goals and both projections, each
    from its sweep.log (the rows of its two processes' run: test_sharding.py; its workers'
    run at threads=share, a core each, may round otherwise: test_cluster.py compares rows)."""
    out, _ = cluster_benchmark
    runs = ("one process", "1 worker on 1 core", "1 core each", "threads=node", "2 processes")
    for run in runs:
        line_matching(out, rf"{run}.* +\d+\.\d s$")
    line_matching(out, r"speed-up, 2 workers over 1 worker: ratio +\d+\.\d\dx \(goal >= 1\.7x")
    line_matching(out, r"speed-up, 2 workers over one process: ratio +\d+\.\d\dx \(goal >= 1x")
    line_matching(out, r"speed-up, 2 workers \(threads=node\) over one process: ratio +\d")
    # raw; pca, whose fit serves both removed counts; ica at each removed count and the
    # FAE, two seeds each
    assert len(re.findall(r"projection, .*: 8 fits, ", out)) == 2, out
    for n in (4, 16, 64):
        assert len(re.findall(rf"^ +{n} workers: at least +\d+\.\d s", out, re.M)) == 2


def test_match_exactness(tmp_path, capfd):
    root = write_folders(tmp_path / "data", n=100)
    out = run_here(capfd, "match_exactness.py", str(root), "--tiny")
    for case in ("raw pixels", "PCA, 10 components removed"):
        # Every rank position that differs is a tie (scores within 1e-6), so is every best
        # match that differs; allowed: one query in 100.
        top_1 = number(
            out,
            re.escape(case) + r": 100 queries x 100 database, top-10: \d+ of 1,000 rank "
            r"positions differ, 0 of them not ties; top-1 identical for (\d+\.\d{4})% of queries$",
        )
        assert top_1 >= 99.0, (case, top_1)


def test_real_data(tmp_path, capfd):
    root = write_folders(tmp_path / "data", n=100)  # --tiny's split takes 94 frames
    out = run_here(
        capfd,
        "real_data.py",
        str(root),
        "--tiny",
        "--logdir",
        str(tmp_path / "runs"),
        "methods=[raw,pca]",
        f"train.checkpoint_dir={tmp_path / 'checkpoints'}",
    )
    assert "| method | objective | k | recall@1 [95% CI] |" in out
    number = r"\d\.\d{3}"
    line_matching(out, rf"^\| raw \|  \|  \| {number} \[{number}, {number}\] \|")
    # the selected removed-PC count, and the recall@1 of sequences of ten at its own
    line_matching(
        out,
        rf"^\| pca \|  \| [05] \| {number} \[{number}, {number}\] \|.*"
        rf"\| {number} \(k=[05]\) \| [05]: {number} \|",
    )
    assert (tmp_path / "runs" / "results.csv").is_file()


def test_device_check_compares_cell_by_cell(monkeypatch):
    """The comparison sees a recall@1 beyond 0.005, another chosen setting and a missing
    cell, and names the kept epochs where they differ."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    from device_check import compare

    from vpr_jax.outputs.results import ResultRow

    def row(run, recall, selected=1, kept=None):
        fields = dict.fromkeys(ResultRow._fields, 0)
        return ResultRow(
            **{
                **fields,
                "run": run,
                "recall_at_1": recall,
                "selected": selected,
                "val_recall_at_1": 0.5,
                "kept_epoch": kept,
            }
        )

    device = [row("a/pca_k000", 0.500), row("a/fae", 0.600, kept=3), row("a/pca_k005", 0.7, 0)]
    cpu = [row("a/pca_k000", 0.504), row("a/fae", 0.590, kept=0), row("a/pca_k005", 0.7, 1)]
    assert compare(device, cpu, 0.005) == [
        "a/fae: recall@1 0.6000 on the device, 0.5900 on the CPU (+0.0100); kept epoch 3 on "
        "the device, 0 on the CPU",
        "a/pca_k005: chosen on validation on the CPU only (validation recall@1 0.5000 / 0.5000)",
    ]
    assert compare(device[:1], cpu, 0.005) == [
        "cell a/fae only on the CPU",
        "cell a/pca_k005 only on the CPU",
    ]


def test_every_script_is_tested():
    """A new script in benchmarks/ gets a test here (common.py is the scripts' helpers;
    halves.py is tested in test_benchmarks.py)."""
    tested = {
        name.removeprefix("test_") + ".py"
        for name, value in globals().items()
        if name.startswith("test_") and callable(value)
    }
    scripts = {p.name for p in BENCHMARKS.glob("*.py")} - {"common.py", "halves.py"}
    assert scripts <= tested, sorted(scripts - tested)
