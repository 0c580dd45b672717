"""One colour per method in every view of a sweep: TensorBoard's method-by-method runs and
the figures.

TensorBoard (2.x) colours runs in its SCALARS and PR CURVES dashboards by their position in
its run list (ordered by each run's first event, then by name) from the 7-colour palette
below; nothing in an event file can choose a colour. So the runs of ``LOGDIR/compare`` are
written one after another in ``compare_labels`` order, run i shows ``TB_PALETTE[i % 7]``
when TensorBoard opens on that folder, and the figures draw label i in that same colour.
From the eighth label on TensorBoard repeats its colours, so each run's tags name its
family's chart group (``chart_groups``: linear methods, auto-encoders, yours; at most seven
runs a group, consecutive in the list): every chart shows each colour once. The figures,
which draw every label on one axes, draw the eighth and later dashed. A method's colour
there follows its place in the sweep's list of labels, not a fixed one.

The learning-curve figure is no TensorBoard view: its lines keep one colour whatever else
a sweep runs (``curve_styles``), a hue per method in the method table's order and a shade
and dash per objective, every line of a figure a colour of its own.
"""

from __future__ import annotations

from vpr_jax.method_table import NAMES, model_label
from vpr_jax.outputs.results import ResultRow, natural_order, plain_setting

# tensorboardColorBlindAssist, the palette of TensorBoard's SCALARS and PR CURVES dashboards
TB_PALETTE = ("#ff7043", "#0077bb", "#cc3311", "#33bbee", "#ee3377", "#009988", "#bbbbbb")
OBJECTIVE_ORDER = ("", "reconstruct", "cross_season", "contrastive", "augment_contrastive")
# The learning curves' hues (matplotlib's tab10, reordered): one per method of the method
# table in its order, then users' methods and outside sets by name.
CURVE_HUES = (
    *("#7f7f7f", "#1f77b4", "#ff7f0e", "#8c564b", "#9467bd", "#2ca02c", "#d62728"),
    *("#e377c2", "#17becf", "#bcbd22"),
)
# Per objective (``OBJECTIVE_ORDER``): how far its shade goes towards black (< 0) or white
# (> 0), and its dash. The paper's objective and methods without one: the hue itself.
_SHADES = (0.0, 0.0, -0.45, 0.4, -0.7)
_DASHES = ("-", "-", "--", "-.", ":")
# Where two lines of one figure would share a colour (a user's objectives, more than three
# users' methods): the next of these not yet used (tab20's light half, then black).
_SPARE = (
    *("#aec7e8", "#ffbb78", "#98df8a", "#ff9896", "#c5b0d5", "#c49c94", "#f7b6d2"),
    *("#c7c7c7", "#dbdb8d", "#9edae5", "#000000"),
)


def curve_label(row: ResultRow) -> str:
    """A results row's method and objective, whatever setting validation chose: a learning
    curve's line (``pca``, ``fae_contrastive``), one across every training places value."""
    return model_label(row.method, row.objective, "")


def label_of(row: ResultRow) -> str:
    """A results row's method as the method-by-method runs and the legends name it, every
    seed of it together (``model_label``): ``pca``, ``fae_cross_season``,
    ``ica_n_components=64``, a user's method or outside set by its name; every training
    places value of a learning curve together."""
    return model_label(row.method, row.objective, plain_setting(row))


def _rank(row: ResultRow) -> tuple:
    method = NAMES.index(row.method) if row.method in NAMES else len(NAMES)
    objective = OBJECTIVE_ORDER.index(row.objective) if row.objective in OBJECTIVE_ORDER else 9
    return method, row.method, objective, row.objective, natural_order(row.setting)


def compare_labels(rows: list[ResultRow], label=label_of) -> list[str]:
    """Every label of ``rows`` once, in the method table's order (users' methods and outside
    sets after the built-in ones, by name; the paper's objective first)."""
    return list(dict.fromkeys(label(r) for r in sorted(rows, key=_rank)))


def family_of(row: ResultRow) -> str:
    """The method family a row's compare run is charted with: ``linear`` (the built-in
    methods without an objective), ``autoencoders`` (with one), ``yours`` (users' methods
    and outside sets): in ``compare_labels`` order each family's labels are consecutive."""
    if row.method not in NAMES:
        return "yours"
    return "autoencoders" if row.objective else "linear"


def chart_groups(rows: list[ResultRow], label=label_of) -> dict[str, str]:
    """label -> the chart group of its compare run's tags: its family, cut into groups of
    at most ``len(TB_PALETTE)`` labels in ``compare_labels`` order (``linear_1``,
    ``linear_2`` where a family has more). A group's runs are consecutive in TensorBoard's
    run list, so its charts never show one colour twice."""
    family = {label(r): family_of(r) for r in rows}
    labels = compare_labels(rows, label)
    sizes = {f: sum(family[name] == f for name in labels) for f in set(family.values())}
    seen: dict[str, int] = {}
    out = {}
    for name in labels:
        f = family[name]
        i = seen.get(f, 0)
        seen[f] = i + 1
        chunk = len(TB_PALETTE)
        out[name] = f if sizes[f] <= chunk else f"{f}_{i // chunk + 1}"
    return out


def styles(rows: list[ResultRow], label=label_of) -> dict[str, dict]:
    """label -> matplotlib line style: TensorBoard's colour of its compare run, dashed
    after the palette's seventh (``label``: what names a line, ``label_of`` or
    ``curve_label``)."""
    return {
        name: {
            "color": TB_PALETTE[i % len(TB_PALETTE)],
            "linestyle": "-" if i < len(TB_PALETTE) else "--",
        }
        for i, name in enumerate(compare_labels(rows, label))
    }


def _shade(hue: str, amount: float) -> str:
    """``hue`` (#rrggbb) moved ``amount`` of the way towards black (< 0) or white (> 0)."""
    target = 255 if amount > 0 else 0
    channels = (int(hue[i : i + 2], 16) for i in (1, 3, 5))
    return "#" + "".join(f"{round(c + abs(amount) * (target - c)):02x}" for c in channels)


def curve_styles(lines: list[tuple[str, str]]) -> dict[str, dict]:
    """The learning-curve figure's line styles by ``curve_label``, for its (method,
    objective) ``lines``: the method's hue (``CURVE_HUES``: the method table's order, users'
    methods and outside sets after it by name), the objective's shade and dash; the same
    whatever else a sweep runs, and never one colour for two lines of a figure."""
    others = sorted({m for m, _ in lines if m not in NAMES})
    out, used = {}, set()
    for method, objective in sorted(set(lines), key=_line_rank):
        name = model_label(method, objective, "")
        if name in out:  # "" and the paper's objective: one name, one line
            continue
        hue = NAMES.index(method) if method in NAMES else len(NAMES) + others.index(method)
        shade = OBJECTIVE_ORDER.index(objective) if objective in OBJECTIVE_ORDER else 0
        color = _shade(CURVE_HUES[hue % len(CURVE_HUES)], _SHADES[shade])
        spare = (c for c in _SPARE if c not in used)
        color = color if color not in used else next(spare, color)
        used.add(color)
        out[name] = {"color": color, "linestyle": _DASHES[shade]}
    return out


def _line_rank(line: tuple[str, str]) -> tuple:
    method, objective = line
    rank = NAMES.index(method) if method in NAMES else len(NAMES)
    shade = OBJECTIVE_ORDER.index(objective) if objective in OBJECTIVE_ORDER else 9
    return rank, method, shade, objective
