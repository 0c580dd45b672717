"""One colour per method in every view of a sweep: TensorBoard's method-by-method runs and
the figures.

TensorBoard (2.x) colours runs in its SCALARS and PR CURVES dashboards by their position in
its run list (ordered by each run's first event, then by name) from the 7-colour palette
below; nothing in an event file can choose a colour. So the runs of ``LOGDIR/compare`` are
written one after another in ``compare_labels`` order, run i shows ``TB_PALETTE[i % 7]``
when TensorBoard opens on that folder, and the figures draw label i in that same colour.
From the eighth label on TensorBoard repeats its colours; the figures draw those labels
dashed so they stay apart there.
"""

from __future__ import annotations

from vpr_jax.method_table import NAMES, model_label
from vpr_jax.outputs.results import ResultRow, natural_order, plain_setting

# tensorboardColorBlindAssist, the palette of TensorBoard's SCALARS and PR CURVES dashboards
TB_PALETTE = ("#ff7043", "#0077bb", "#cc3311", "#33bbee", "#ee3377", "#009988", "#bbbbbb")
_OBJECTIVE_ORDER = ("", "reconstruct", "cross_season", "contrastive", "augment_contrastive")


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
    objective = _OBJECTIVE_ORDER.index(row.objective) if row.objective in _OBJECTIVE_ORDER else 9
    return method, row.method, objective, row.objective, natural_order(row.setting)


def compare_labels(rows: list[ResultRow], label=label_of) -> list[str]:
    """Every label of ``rows`` once, in the method table's order (users' methods and outside
    sets after the built-in ones, by name; the paper's objective first)."""
    return list(dict.fromkeys(label(r) for r in sorted(rows, key=_rank)))


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
