"""Sweep figures, like the seed's Figs 7-12: PR curves per pair and fractions of correct
matches (at the sweep's shortest sequence length, single images unless told otherwise), and
recall@1 against the sequence length ds. Built from results.csv rows and each cell's saved
curve, so a resumed sweep draws every cell, not only those it computed this time. Each
method has the colour TensorBoard gives its method-by-method run (``palette``)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; no display on clusters or CI
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from vpr_jax.method_table import SWEEPS_REMOVED_PCS  # noqa: E402
from vpr_jax.outputs.palette import label_of, styles  # noqa: E402
from vpr_jax.outputs.results import ResultRow, best_objectives, selected_rows  # noqa: E402


def _label(row: ResultRow, best: set[str] = frozenset()) -> str:
    """The legend's name of a row: its count where it has one; "best" on the objective a
    method's validation recall prefers (``best_objectives``)."""
    k = f" (k={row.removed_pcs})" if row.method in SWEEPS_REMOVED_PCS else ""
    return label_of(row) + k + (" best" if row.run in best else "")


def _save(fig, path: Path) -> None:
    """Write the figure as PNG, its legend entries in the file's Description text (any PNG
    reader shows which methods a figure holds without looking at it), and close it."""
    fig.tight_layout()
    entries = [
        text.get_text()
        for ax in fig.axes
        if ax.get_legend()
        for text in ax.get_legend().get_texts()
    ]
    fig.savefig(path, dpi=120, metadata={"Description": "; ".join(dict.fromkeys(entries))})
    plt.close(fig)


def _shortest_sequences(rows: list[ResultRow]) -> list[ResultRow]:
    shortest = min(r.ds for r in rows)
    return [r for r in rows if r.ds == shortest]


def pr_curves_figure(rows: list[ResultRow], load_curve: Callable[[ResultRow], tuple], path: Path):
    """One panel per season pair, one line per method (PCA at its validation-selected
    removed-PC count)."""
    best = selected_rows(_shortest_sequences(rows))
    preferred = best_objectives(best)
    pairs = list(dict.fromkeys(r.season_pair for r in rows))  # sweep order
    style = styles(rows)
    fig, axes = plt.subplots(1, len(pairs), figsize=(4.2 * len(pairs), 3.8), squeeze=False)
    for ax, pair in zip(axes[0], pairs, strict=True):
        mine = {label_of(r): r for r in best if r.season_pair == pair}
        for label in (x for x in style if x in mine):
            row = mine[label]
            precision, recall = load_curve(row)
            name = _label(row, preferred)
            ax.plot(recall, precision, label=f"{name}  AUC {row.auc_pr:.2f}", **style[label])
        ax.set(title=pair, xlabel="recall", ylabel="precision", xlim=(0, 1.01), ylim=(0, 1.02))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="lower left")
    _save(fig, path)


def correct_matches_figure(rows: list[ResultRow], path: Path):
    """Grouped bars: fraction of correct matches (recall@1) per pair and method (and
    objective)."""
    best = selected_rows(_shortest_sequences(rows))
    pairs = list(dict.fromkeys(r.season_pair for r in rows))  # sweep order
    style = styles(rows)
    width = 0.8 / len(style)
    fig, ax = plt.subplots(figsize=(3.0 + 0.25 * len(style) * len(pairs), 3.8))
    for m, (method, line) in enumerate(style.items()):
        by_pair = {r.season_pair: r for r in best if label_of(r) == method}
        x = np.arange(len(pairs)) + (m - (len(style) - 1) / 2) * width
        heights = [by_pair[p].recall_at_1 if p in by_pair else np.nan for p in pairs]
        hatch = "//" if line["linestyle"] == "--" else None
        bars = ax.bar(x, heights, width, label=method, color=line["color"], hatch=hatch)
        ax.bar_label(bars, fmt="%.2f", fontsize=7)
    ax.set_xticks(np.arange(len(pairs)), pairs)
    ax.set(ylabel="fraction of correct matches", ylim=(0, 1.08))
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))  # beside the bars
    _save(fig, path)


def recall_vs_ds_figure(rows: list[ResultRow], path: Path):
    """One panel per season pair: recall@1 against the sequence length ds, a line per method
    (PCA and ICA at their validation-selected removed-PC count for each ds, as in results.md)."""
    best = selected_rows(rows)
    pairs = list(dict.fromkeys(r.season_pair for r in rows))  # sweep order
    style = styles(rows)
    fig, axes = plt.subplots(1, len(pairs), figsize=(4.2 * len(pairs), 3.8), squeeze=False)
    for ax, pair in zip(axes[0], pairs, strict=True):
        for method, line in style.items():
            points = sorted(
                (r.ds, r.recall_at_1)
                for r in best
                if r.season_pair == pair and label_of(r) == method
            )
            if points:
                ax.plot(*zip(*points, strict=True), marker="o", label=method, **line)
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
