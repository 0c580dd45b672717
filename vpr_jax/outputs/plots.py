"""Sweep figures, like the paper's Figs 7-12: PR curves per pair and fractions of correct
matches (at the sweep's shortest sequence length, single images unless told otherwise), and
recall@1 against the sequence length ds. Built from results.csv rows and each cell's saved
curve, so a resumed sweep draws every cell, not only those it computed this time. Each
method has the colour TensorBoard gives its method-by-method run (``palette``). A method
fitted with several seeds is one line or bar: the mean of its seeds' recall@1 (the bar's
whisker their range) and the PR curve of all their queries pooled."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; no display on clusters or CI
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from vpr_jax.files import atomic_open  # noqa: E402
from vpr_jax.outputs.palette import curve_label, label_of, styles  # noqa: E402
from vpr_jax.outputs.results import (  # noqa: E402
    ResultRow,
    best_objectives,
    selected_rows,
    sweep_labels,
    training_places,
)


def _label(rows: list[ResultRow], best: set[str] = frozenset()) -> str:
    """The legend's name of a method's rows (its seeds): its count where it has one, the
    number of seeds where there are several; "best" on the objective a method's validation
    recall prefers (``best_objectives``)."""
    row = rows[0]
    k = "".join(f" ({text})" for text in sweep_labels(row))
    seeds = f", {len(rows)} seeds" if len(rows) > 1 else ""
    return label_of(row) + k + seeds + (" best" if row.run in best else "")


def by_label(rows: list[ResultRow]) -> dict[tuple[str, str], list[ResultRow]]:
    """(pair, label) -> its rows: a method's seeds together."""
    out: dict[tuple[str, str], list[ResultRow]] = {}
    for row in rows:
        out.setdefault((row.season_pair, label_of(row)), []).append(row)
    return out


def _mean(rows: list[ResultRow], metric: str) -> float:
    return float(np.mean([getattr(r, metric) for r in rows]))


def _save(fig, path: Path) -> None:
    """Write the figure as PNG, all or nothing, its legend entries in the file's
    Description text (any PNG reader shows which methods a figure holds without looking at
    it), and close it, also when drawing fails."""
    try:
        fig.tight_layout()
        entries = [
            text.get_text()
            for ax in fig.axes
            if ax.get_legend()
            for text in ax.get_legend().get_texts()
        ]
        metadata = {"Description": "; ".join(dict.fromkeys(entries))}
        with atomic_open(path, "wb") as f:
            fig.savefig(f, format="png", dpi=120, metadata=metadata)
    finally:
        plt.close(fig)


def _shortest_sequences(rows: list[ResultRow]) -> list[ResultRow]:
    shortest = min(r.ds for r in rows)
    return [r for r in rows if r.ds == shortest]


def pr_curves_figure(
    rows: list[ResultRow], load_curve: Callable[[list[ResultRow]], tuple], path: Path
):
    """One panel per season pair, one line per method (PCA at its validation-selected
    removed-PC count). ``load_curve(rows)``: (precision, recall) of a method's rows."""
    best = by_label(selected_rows(_shortest_sequences(rows)))
    preferred = best_objectives(rows)
    pairs = list(dict.fromkeys(r.season_pair for r in rows))  # sweep order
    style = styles(rows)
    fig, axes = plt.subplots(1, len(pairs), figsize=(4.2 * len(pairs), 3.8), squeeze=False)
    for ax, pair in zip(axes[0], pairs, strict=True):
        for label in (x for x in style if (pair, x) in best):
            mine = best[pair, label]
            precision, recall = load_curve(mine)
            name = _label(mine, preferred)
            auc = _mean(mine, "auc_pr")
            ax.plot(recall, precision, label=f"{name}  AUC {auc:.2f}", **style[label])
        ax.set(title=pair, xlabel="recall", ylabel="precision", xlim=(0, 1.01), ylim=(0, 1.02))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="lower left")
    _save(fig, path)


def _range(rows: list[ResultRow], mean: float) -> list[float]:
    """(below, above) the mean of a method's seeds' recall@1: the bar's whisker. Never below
    zero: seeds that tie give a mean a rounding away from their value."""
    if len(rows) < 2:
        return [0.0, 0.0]
    recalls = [r.recall_at_1 for r in rows]
    return [max(mean - min(recalls), 0.0), max(max(recalls) - mean, 0.0)]


def correct_matches_figure(rows: list[ResultRow], path: Path):
    """Grouped bars: fraction of correct matches (recall@1) per pair and method (and
    objective; a swept setting at its validation-selected value), in each method's colour
    of the compare runs."""
    best = by_label(selected_rows(_shortest_sequences(rows)))
    pairs = list(dict.fromkeys(r.season_pair for r in rows))  # sweep order
    style = {
        label: line for label, line in styles(rows).items() if any(k[1] == label for k in best)
    }
    width = 0.8 / len(style)
    fig, ax = plt.subplots(figsize=(3.0 + 0.25 * len(style) * len(pairs), 3.8))
    for m, (method, line) in enumerate(style.items()):
        mine = [best.get((p, method), []) for p in pairs]
        x = np.arange(len(pairs)) + (m - (len(style) - 1) / 2) * width
        heights = [_mean(r, "recall_at_1") if r else np.nan for r in mine]
        whiskers = np.array([_range(r, h) for r, h in zip(mine, heights, strict=True)]).T
        bars = ax.bar(
            x,
            heights,
            width,
            label=method,
            color=line["color"],
            hatch="//" if line["linestyle"] == "--" else None,
            yerr=whiskers if whiskers.any() else None,
        )
        ax.bar_label(bars, fmt="%.2f", fontsize=7)
    ax.set_xticks(np.arange(len(pairs)), pairs)
    ax.set(ylabel="fraction of correct matches", ylim=(0, 1.08))
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))  # beside the bars
    _save(fig, path)


def _recall_lines(ax, rows, pair: str, style: dict, label: Callable, x: Callable) -> None:
    """A line on ``ax`` per ``style`` label: the mean recall@1 (over seeds) of ``pair``'s
    ``rows`` of that label at each value of ``x(row)``."""
    for name, line in style.items():
        by_x: dict[int, list[ResultRow]] = {}
        for r in rows:
            if r.season_pair == pair and label(r) == name:
                by_x.setdefault(x(r), []).append(r)
        points = sorted((v, _mean(mine, "recall_at_1")) for v, mine in by_x.items())
        if points:
            ax.plot(*zip(*points, strict=True), marker="o", label=name, **line)


def recall_vs_ds_figure(rows: list[ResultRow], path: Path):
    """One panel per season pair: recall@1 against the sequence length ds, a line per method
    (PCA and ICA at their validation-selected removed-PC count for each ds, as in results.md)."""
    best = selected_rows(rows)
    pairs = list(dict.fromkeys(r.season_pair for r in rows))  # sweep order
    style = styles(rows)
    fig, axes = plt.subplots(1, len(pairs), figsize=(4.2 * len(pairs), 3.8), squeeze=False)
    for ax, pair in zip(axes[0], pairs, strict=True):
        _recall_lines(ax, best, pair, style, label_of, lambda r: r.ds)
        ax.set(
            title=pair,
            xlabel="sequence length ds (frames)",
            ylabel="recall@1",
            ylim=(0, 1.02),
            xticks=sorted({r.ds for r in rows}),
        )
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="lower right")
    _save(fig, path)


def learning_curves_figure(rows: list[ResultRow], path: Path):
    """One panel per season pair: recall@1 against the training places a method was fitted
    on (``split.train_places``, log scale), a line per method at its validation-selected
    setting for each value, whichever it is (single images; several seeds: their mean);
    the legend beside the last panel."""
    shortest = min(r.ds for r in rows)
    best = [r for r in selected_rows(rows) if r.ds == shortest and training_places(r) is not None]
    pairs = list(dict.fromkeys(r.season_pair for r in best))  # sweep order
    style = styles(best, curve_label)
    fig, axes = plt.subplots(1, len(pairs), figsize=(4.2 * len(pairs) + 2, 3.8), squeeze=False)
    for ax, pair in zip(axes[0], pairs, strict=True):
        _recall_lines(ax, best, pair, style, curve_label, training_places)
        ax.set(
            title=pair,
            xlabel="training places a season (log scale)",
            ylabel="recall@1",
            ylim=(0, 1.02),
            xscale="log",
        )
        ticks = sorted({training_places(r) for r in best})
        ax.set_xticks(ticks, [str(t) for t in ticks])
        ax.minorticks_off()
        ax.grid(alpha=0.3)
    axes[0][-1].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    _save(fig, path)
