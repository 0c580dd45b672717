"""Sweep figures, like the paper's Figs 7-12: PR curves per pair and fractions of correct
matches (at the sweep's shortest sequence length, single images unless told otherwise), and
recall@1 against the sequence length ds. Built from results.csv rows and each cell's saved
curve, so a resumed sweep draws every cell, not only those it computed this time. Each
method has the colour TensorBoard gives its method-by-method run (``palette``); the
learning curves, a colour per method and objective of their own. A method
fitted with several seeds is one line or bar: the mean of its seeds' recall@1 (the bar's
whisker their range) and the PR curve of all their queries pooled."""

from __future__ import annotations

import textwrap
from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; no display on clusters or CI
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from vpr_jax.files import atomic_open  # noqa: E402
from vpr_jax.method_table import model_label  # noqa: E402
from vpr_jax.outputs.palette import curve_label, curve_styles, label_of, styles  # noqa: E402
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


# (pair, method, objective, training places) -> why that point was not scored
NotScored = dict[tuple[str, str, str, int], str]


def learning_curves_figure(rows: list[ResultRow], path: Path, not_scored: NotScored = None):
    """One panel per season pair: recall@1 against the training places a method was fitted
    on (``split.train_places``, log scale), a line per method at its validation-selected
    setting for each value, whichever it is (single images; several seeds: their mean), its
    95% interval as whiskers (several seeds: from their lowest bound to their highest); a
    colour per method and objective of its own (``palette.curve_styles``), the y axis
    fitted to what is drawn; a point ``not_scored`` gives a reason for is an x at the
    panel's foot, its reason under the panel. The legend beside the last panel."""
    shortest = min(r.ds for r in rows)
    best = [r for r in selected_rows(rows) if r.ds == shortest and training_places(r) is not None]
    missing = not_scored or {}
    pairs = list(dict.fromkeys([*(r.season_pair for r in best), *(k[0] for k in missing)]))
    style = curve_styles([(r.method, r.objective) for r in best] + [k[1:3] for k in missing])
    ticks = sorted({training_places(r) for r in best} | {k[3] for k in missing})
    fig, axes = plt.subplots(1, len(pairs), figsize=(4.2 * len(pairs) + 2, 4.4), squeeze=False)
    for ax, pair in zip(axes[0], pairs, strict=True):
        drawn = _curve_lines(ax, [r for r in best if r.season_pair == pair], style)
        low = _fit_y(ax, drawn)
        _mark_missing(ax, {k: v for k, v in missing.items() if k[0] == pair}, style)
        ax.set(title=pair, xlabel="training places a season (log scale)", xscale="log")
        ax.set_ylabel("recall@1" + (f" (axis from {low:.2f}, not 0)" if low > 0 else ""))
        ax.set_xticks(ticks, [str(t) for t in ticks])
        ax.set_xlim(ticks[0] / 1.25, ticks[-1] * 1.25)
        ax.minorticks_off()
        ax.grid(alpha=0.3)
    axes[0][-1].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    _save(fig, path)


def _nudge(index: int, count: int) -> float:
    """A factor on the x of line ``index`` of ``count``: their whiskers side by side."""
    return 1.025 ** (index - (count - 1) / 2)


def _curve_lines(ax, rows: list[ResultRow], style: dict) -> list[float]:
    """A line per ``style`` label with rows on ``ax``: mean recall@1 at each value of
    training places, the 95% interval as whiskers. Returns every value drawn."""
    drawn = []
    for i, (name, line) in enumerate(style.items()):
        by_x: dict[int, list[ResultRow]] = {}
        for r in (r for r in rows if curve_label(r) == name):
            by_x.setdefault(training_places(r), []).append(r)
        if not by_x:
            continue
        x = sorted(by_x)
        y = np.array([_mean(by_x[v], "recall_at_1") for v in x])
        low = np.array([min(r.recall_at_1_ci_low for r in by_x[v]) for v in x])
        high = np.array([max(r.recall_at_1_ci_high for r in by_x[v]) for v in x])
        whiskers = np.nan_to_num(np.stack([y - low, high - y]), nan=0.0).clip(min=0.0)
        nudged = np.array(x) * _nudge(i, len(style))
        ax.errorbar(
            nudged,
            y,
            yerr=whiskers,
            marker="o",
            markersize=4,
            capsize=2,
            label=name,
            elinewidth=0.8,
            **line,
        )
        drawn += [*y, *low[~np.isnan(low)], *high[~np.isnan(high)]]
    return drawn


def _fit_y(ax, values: list[float]) -> float:
    """The y axis around ``values`` (recall@1 and its intervals), a margin below for the
    points not scored; within 0 and 1. Returns its lower end."""
    top, bottom = (max(values), min(values)) if values else (1.0, 0.0)
    margin = max(0.04, 0.08 * (top - bottom))
    low = max(0.0, bottom - 1.5 * margin)
    low = 0.0 if low < 0.05 else low  # not worth a broken axis
    ax.set_ylim(low, min(1.02, top + margin))
    return low


def _mark_missing(ax, missing: NotScored, style: dict) -> None:
    """An x at the panel's foot in the line's colour for each point not scored, and under
    the panel a line per point saying why."""
    names, notes = list(style), []
    bottom, top = ax.get_ylim()
    y = bottom + 0.03 * (top - bottom)
    for (_, method, objective, places), why in sorted(missing.items()):
        name = model_label(method, objective, "")
        line = style[name]
        x = places * _nudge(names.index(name), len(names))
        shown = name in ax.get_legend_handles_labels()[1]
        ax.plot(
            [x],
            [y],
            marker="x",
            markersize=7,
            color=line["color"],
            linestyle="none",
            label=None if shown else name,  # a line never scored: its entry in the legend
        )
        ax.annotate(
            "not scored",
            (x, y),
            xytext=(0, 6),
            textcoords="offset points",
            fontsize=6,
            ha="center",
            color=line["color"],
        )
        notes.append(f"\u00d7 {name} at {places} places: not scored: {why}")
    if notes:
        text = "\n".join(textwrap.fill(n, 70, subsequent_indent="   ") for n in notes)
        ax.text(0.0, -0.2, text, transform=ax.transAxes, fontsize=6.5, va="top")
