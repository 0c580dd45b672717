"""How a learning curve is reported (issue 56): the figure's colours by method and objective,
its intervals and fitted y axis, the points not scored and why (in the figure and in
results.md, read from sweep.log's notes), one best objective per method, why there are no
paired differences, and the settings other than the defaults."""

from PIL import Image

from experiments.report import changed_settings, not_scored
from experiments.results_md import markdown_table
from tests.conftest import TINY_ROUTE, run_here
from vpr_jax.command_line import parse_config
from vpr_jax.method_table import NAMES, model_label
from vpr_jax.outputs import plots
from vpr_jax.outputs.palette import (
    OBJECTIVE_ORDER,
    TB_PALETTE,
    chart_groups,
    compare_labels,
    curve_styles,
    label_of,
)
from vpr_jax.outputs.results import ResultRow, swept_columns

PAIR = "summer-fall"
OBJECTIVES = OBJECTIVE_ORDER[1:]
WHY = "ica.n_components=128 with removed_pcs=0 needs 128 components but the data have rank 126"


def _row(method: str, places: int, recall: float, objective: str = "", val: float = 0.9):
    """A selected row of a learning curve at ``places`` training places."""
    columns = swept_columns({"train_places": places})
    return ResultRow(
        **{
            **dict.fromkeys(ResultRow._fields, 0),
            **columns,
            "season_pair": PAIR,
            "method": method,
            "objective": objective,
            "ds": 1,
            "n_test": 100,
            "ground_truth": "+-2 frames",
            "protocol": "p",
            "recall_at_1": recall,
            "recall_at_1_ci_low": recall - 0.1,
            "recall_at_1_ci_high": recall + 0.1,
            "val_recall_at_1": val,
            "selected": 1,
            "converged": 1,
            "kept_epoch": None,
            "start": "",
            "run": f"{PAIR}/{model_label(method, objective, columns['setting'])}",
        }
    )


def _curve_rows() -> list[ResultRow]:
    """raw, pca and cae contrastive (raw's orange in TensorBoard's palette by position) at
    66 and 132 places, in 0.67-0.75; ica only at 132."""
    rows = [_row("ica", 132, 0.70)]
    for places, shift in ((66, 0.0), (132, 0.02)):
        rows += [
            _row("raw", places, 0.67 + shift),
            _row("pca", places, 0.70 + shift),
            _row("cae", places, 0.73 + shift, "contrastive"),
        ]
    return rows


def test_learning_curve_colours_are_fixed_by_method_and_objective_and_all_distinct():
    every = [(m, "") for m in NAMES] + [(m, o) for m in NAMES for o in OBJECTIVES]
    every += [("edges", ""), ("netvlad", ""), ("zz_set", "")]  # users' methods, outside sets
    styles = curve_styles(every)
    colours = [s["color"] for s in styles.values()]
    assert len(colours) == len(set(colours))  # raw and fae: one name for "" and reconstruct
    few = curve_styles([("raw", ""), ("cae", "contrastive")])
    assert few["raw"]["color"] != few["cae_contrastive"]["color"]
    for name, style in few.items():  # whatever else the sweep runs
        assert style == styles[name]


def test_every_compare_chart_shows_each_of_tensorboards_colours_once():
    """The compare runs are coloured by position (run i: TB_PALETTE[i % 7]); a chart shows
    one chart group's runs: each group's positions are consecutive and at most seven, so no
    chart repeats a colour, whatever the sweep runs (here 13 linear labels, the four
    auto-encoder models, a user's method)."""
    rows = [_row(m, 132, 0.7) for m in ("raw", "pca", "diff_pca", "ica", "lda", "edges")]
    rows += [_row(m, 132, 0.7, o) for m in ("fae", "cae") for o in ("reconstruct", "contrastive")]
    lda = _row("lda", 132, 0.7)
    rows += [  # eight more lda labels, one per swept value
        lda._replace(**swept_columns({"n_components": n, "train_places": 132}))
        for n in range(10, 18)
    ]
    labels = compare_labels(rows)
    groups = chart_groups(rows)
    assert set(groups) == set(labels) and len(labels) == 18
    for group in set(groups.values()):
        positions = [i for i, name in enumerate(labels) if groups[name] == group]
        assert positions == list(range(positions[0], positions[0] + len(positions))), group
        colours = [TB_PALETTE[i % len(TB_PALETTE)] for i in positions]
        assert len(colours) == len(set(colours)), group
    assert {groups[label_of(r)] for r in rows if r.objective} == {"autoencoders"}
    assert groups["edges"] == "yours"
    assert {groups[n] for n in labels if groups[n].startswith("linear")} == {"linear_1", "linear_2"}


def test_learning_curve_figure_fits_its_axis_draws_intervals_and_marks_a_point_not_scored(
    monkeypatch, tmp_path
):
    drawn = []
    monkeypatch.setattr(plots, "_save", lambda fig, path: drawn.append(fig))
    missing = {(PAIR, "ica", "", 66): WHY}
    plots.learning_curves_figure(_curve_rows(), tmp_path / "curves.png", missing)
    ax = drawn[0].axes[0]
    lines = [c.lines[0] for c in ax.containers]  # an errorbar per method: its line, whiskers
    assert len(lines) == 4 and all(c.has_yerr for c in ax.containers)
    colours = [line.get_color() for line in lines]
    assert len(set(colours)) == len(colours)
    low, high = ax.get_ylim()
    assert 0.4 < low < 0.57 and 0.84 < high <= 1.02  # around 0.57-0.85, the intervals
    assert f"axis from {low:.2f}, not 0" in ax.get_ylabel()
    texts = [t.get_text() for t in ax.texts]
    assert "not scored" in texts
    assert any(t.startswith("\u00d7 ica at 66 places: not scored: ica.n_components") for t in texts)


def test_results_md_says_why_a_point_was_not_scored():
    md = markdown_table(_curve_rows(), not_scored={(PAIR, "ica", "", 66): WHY})
    table = md.split("## Learning curves", 1)[1].split("\n## ", 1)[0]
    ica = next(line for line in table.splitlines() if line.startswith(f"| {PAIR} | ica |"))
    assert ica.endswith(f"| not scored ({WHY}) | 0.700 [0.600, 0.800] |")


def test_not_scored_reads_sweep_log_notes_by_run_name(tmp_path):
    """A note's runs matched to their method and objective (the longest name), each run
    once (a resumed sweep notes it again), the first reason with the count; a point with a
    row is scored; a curve with no row at all still gets its points."""
    log = tmp_path / "sweep.log"
    notes = [
        f"note: {PAIR} ica_train_places=66_k000: not scored: {WHY}",
        f"note: {PAIR} ica_train_places=66_k005: not scored: other",
        f"note: {PAIR} ica_train_places=66_k000: not scored: {WHY}",  # resumed
        f"note: {PAIR} ica_train_places=132_k005: not scored: only one k",  # 132 has a row
        f"note: {PAIR} fae_cross_season_train_places=66, fae_train_places=66: not scored: few",
        f"note: {PAIR} pca_k005: not scored: no learning curve",
        "[3/9] summer-fall pca: recall@1 0.5",
    ]
    log.write_text("\n".join(notes) + "\n")
    rows = _curve_rows() + [_row("fae", 132, 0.6, "reconstruct")]
    assert not_scored(log, rows, NAMES) == {
        (PAIR, "ica", "", 66): f"{WHY}; 2 runs, sweep.log has each",
        (PAIR, "fae", "cross_season", 66): "few",
        (PAIR, "fae", "reconstruct", 66): "few",
    }
    assert not_scored(tmp_path / "none.log", rows, NAMES) == {}


def test_one_best_objective_per_method_at_the_largest_training_places():
    """cross_season wins on validation at 66 places, reconstruct at 132: only 132's marked."""
    rows = [
        _row("fae", 66, 0.6, "reconstruct", val=0.5),
        _row("fae", 66, 0.6, "cross_season", val=0.7),
        _row("fae", 132, 0.7, "reconstruct", val=0.8),
        _row("fae", 132, 0.6, "cross_season", val=0.6),
    ]
    md = markdown_table(rows)
    best = [line for line in md.splitlines() if " best" in line and line.startswith("|")]
    assert len(best) == 1 and "| reconstruct best |" in best[0] and "train_places=132" in best[0]
    assert f"(marked best; a learning curve's at its largest training places): {PAIR} fae " in md


def test_results_md_says_why_there_are_no_paired_differences():
    rows = [_row("fae", 66, 0.6, "reconstruct")]
    md = markdown_table(rows, {}, None, wanted="pca")
    assert "| n/a: no PCA in this sweep |" in md
    assert "the baseline, PCA (baseline=pca)" in md and "add pca to methods" in md


def test_results_md_names_the_settings_other_than_the_defaults():
    cfg = parse_config(["pca.whiten=64", "ica.n_components=[64,128]", "fae.objective=contrastive"])
    changed = changed_settings(cfg, {"pca", "ica", "fae"})
    assert changed["pca"] == "whiten=64"  # the axis and the objective have columns
    assert "ica" not in changed and "objective" not in changed.get("fae", "")
    assert changed_settings(parse_config([]), {"pca", "ica"}) == {}
    md = markdown_table(_curve_rows(), changed=changed)
    assert "Settings other than the defaults" in md and ": pca whiten=64" in md


def test_a_learning_curve_point_not_scored_is_marked_in_results_md_and_the_figure(tmp_path):
    """ICA's 64 components need more than 20 places' 40 images: its 20-place point is
    missing, and results.md's table and the figure's description say why."""
    logdir = tmp_path / "runs"
    proc = run_here(
        *TINY_ROUTE,
        f"season_pairs={PAIR}",
        "methods=[raw,ica]",
        "removed_pcs=[0]",
        "ica.n_components=64",
        "split.train_places=[20,60]",
        f"logdir={logdir}",
    )
    assert proc.returncode == 0, proc.stderr
    md = (logdir / "results.md").read_text()
    table = md.split("## Learning curves", 1)[1].split("\n## ", 1)[0]
    ica = next(line for line in table.splitlines() if line.startswith(f"| {PAIR} | ica |"))
    assert "| not scored (ica.n_components=64 with removed_pcs=0 needs 64 components" in ica
    assert "n/a: no PCA in this sweep" in md
    assert "Settings other than the defaults" in md and "ica n_components=64" in md
    legend = Image.open(logdir / "figures" / "learning_curves.png").text["Description"]
    assert legend == "raw; ica"
