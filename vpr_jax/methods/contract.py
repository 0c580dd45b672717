"""The one shape of a method, built-in or a user's (optax's ``GradientTransformation`` is the
model: a NamedTuple of pure functions):

    fit(train, aligned, key, **settings, **resources) -> state
    encode(state, images, **served) -> (n, d)

``train``: float32 ``(n, 32, 64)`` in [0, 1], both seasons' training images; ``aligned``:
None or ``(database season, query season)`` with row i one place; ``key``: a ``jax.random``
key of one of the sweep's ``seeds``; ``settings``: the method's settings of this fit (a
list given for one is a sweep axis, ``vpr_jax.methods.settings``); ``resources``: what the
method ``needs`` from the runner. ``state`` is a pytree of arrays and ``encode`` is pure and
jittable; its rows are compared by cosine.

Beside ``fit`` and ``encode`` a method declares at most six things, each read by the runner
instead of the method's name (docs/methods.md, "Your own method"): its ``settings``, how its
settings vary (``axes``), what it ``needs``, whether it is ``random``, how it ``check``-s
its settings against the training set and the devices, and what it ``report``-s.
``as_method`` reads them from any object (a user's class with static methods and class
attributes has the same shape as a built-in ``Method``).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from vpr_jax.errors import UserError

# How a setting's values relate to fits (``axes``); a setting not named there is a fit per
# value, chosen among on the validation places (a list given for it is a sweep axis).
SERVED = "served"  # one fit serves every value: encode takes it, fit does not
SUFFIX = "suffix"  # ... and one encoding: value v's descriptors are encode(state, x)[:, v:]
ROWS = "rows"  # every value is rows of its own, never chosen among (the objectives)
AXIS_KINDS = (SERVED, SUFFIX, ROWS)
# What a method may need (``needs``): aligned training places, and what its fit takes from
# the runner by keyword.
ALIGNED = "aligned"
RESOURCES = ("pca_fit", "validation", "training", "mesh", "outside")
NEEDS = (ALIGNED, *RESOURCES)


class NotScored(Exception):
    """Raised by a method's ``fit`` (for every cell of the fit) or ``report`` (for that
    cell) when this pair's training set cannot serve it, e.g. a removed count beyond the
    numerical rank of repeated frames: the runner leaves those cells out with the message
    as a note and goes on. Nothing is scored that the data cannot define."""


class Report(NamedTuple):
    """What a fit found beyond its state: results.csv's fit columns, the run log, the
    TensorBoard run's basis images."""

    n_iter: int = 0  # iterations of an iterative fit (epochs when trained); 0: closed form
    converged: bool = True  # False: an iterative fit stopped at its limit
    stopped_early: bool = False  # training ended before its last epoch
    fit_seconds: float | None = None  # its own count (training over every session); None:
    # the runner's clock around fit
    warning: str | None = None  # one line for the run log
    basis: np.ndarray | None = None  # (m, 32 * 64): what the fit removed or learned
    basis_name: str = "basis"  # its TensorBoard tag: basis/<basis_name>
    validation: bool = True  # False: the state cannot describe the validation places (NaN
    # validation scores: nothing is chosen on them)
    kept_epoch: int | None = None  # a trained fit: the epoch whose weights it kept (0: its
    # start, untouched by training); None: the fit does not train
    epochs_trained: int | None = None  # a trained fit: the epochs it trained
    start: str = ""  # a trained fit: what it started from, e.g. "lda in 256 directions"
    start_state: Any = None  # a trained fit that kept a later epoch: its start as a state
    # ``encode`` takes, scored on the same queries (results.md's trained-against-start)


class TrainingSet(NamedTuple):
    """What a method's ``check`` may ask before anything is fitted: the training set, the
    devices, and how its settings were given."""

    n_images: int  # both seasons' training images of a pair
    n_pixels: int
    aligned: bool  # whether the pair has aligned training places
    swept: dict[str, tuple]  # the values of each of the method's settings given as a list
    given: frozenset[str]  # the method's settings named on the command line
    asked: frozenset[str]  # ... or by a preset that names its data (what it asks for by name)
    pca_components: int = 0  # components the pair's shared PCA fit holds
    devices: int = 1  # devices a training batch is split over

    @property
    def pca_limit(self) -> int:
        """Principal components of the training images: min(n - 1, pixels)."""
        return min(self.n_images - 1, self.n_pixels)


class Method(NamedTuple):
    """A method: ``fit`` and ``encode`` and what the runner needs to know about them."""

    fit: Callable[..., Any]
    encode: Callable[..., Any]
    settings: type | None = None  # a frozen dataclass: names, defaults and checks of the
    # settings; None: any keyword settings (a user's plugin.<name>.*), unchecked
    axes: dict[str, str] | Callable[[Any], dict[str, str]] = {}  # setting -> SERVED,
    # SUFFIX or ROWS (a callable: of the settings)
    needs: tuple[str, ...] | Callable[[Any], tuple[str, ...]] = ()  # of NEEDS (a callable:
    # of the settings)
    random: bool = True  # fit draws from its key: fitted once per seed of ``seeds``
    check: Callable[[Any, TrainingSet, Callable], Any] | None = None  # (settings, training
    # set, log) -> the settings fitted to it (notes in the log), None to leave this
    # combination out (with a note), or UserError
    report: Callable[[Any, dict], Report] | None = None  # (state, this cell's settings)


class PCAFit(NamedTuple):
    """The pair's shared PCA fit (resource ``pca_fit``): its state and what it cost."""

    state: Any  # vpr_jax.encoders.pca.PCAState
    seconds: float
    asked: int = 0  # components asked for; the state holds fewer where the training
    # images' numerical rank is lower (vpr_jax.encoders.pca.numerical_rank)


class SharedFit(NamedTuple):
    """A fit a pair shares with every method that needs it, declared by the method that
    offers it (``vpr_jax.method_table.OFFERS``). It holds a count of components that
    depends on the data and its own settings only, never on which methods use it (each
    takes the leading ones it needs): a method's numbers do not depend on what else is in
    ``methods``, and its shapes (so its compiled code) not on its own settings."""

    components: Callable[[Any, int, int], int]  # (settings, n_images, n_pixels) -> the
    # components the fit holds
    fit: Callable[..., Any]  # (train, n_components, settings, mesh, seed) -> its state
    fix: str  # how a user gets more components than it holds (an error's advice)


class Validation(NamedTuple):
    """The validation places (resource ``validation``), scored as the sweep scores them:
    what the auto-encoders pick epochs by."""

    images: np.ndarray  # both seasons' validation places, database season first (aligned
    # pairs), or a benchmark's held-out queries
    scores: Callable[..., list[tuple[float, float]]]  # (encode, starts=(0,)) ->
    # (recall@1, margin) per feature-suffix start of encode's descriptors: the sweep's
    # selection key (the larger tuple wins; results.py)

    def recall_at_1(self, encode: Callable, starts: tuple[int, ...] = (0,)) -> list[float]:
        """Recall@1 per feature-suffix start of ``encode``'s descriptors."""
        return [recall for recall, _ in self.scores(encode, starts)]


class Training(NamedTuple):
    """Where a trained method keeps its checkpoints and reports (resource ``training``)."""

    folder: Path | None  # this fit's checkpoint folder (None: nothing saved)
    log: Callable[[str], Any]  # suffix -> a training log (encoders.train.TrainingLog)
    identity: dict  # what besides its settings decides the weights: data, split, seed, pair
    name: str  # how progress lines call this fit, e.g. "summer-fall fae_cross_season"
    checkpoint_every_s: float  # seconds between an epoch's checkpoints (train.*)


# The declarations of the contract before 2026-12-05 and what replaces each.
_REPLACED = {
    "serves": "axes={'<setting>': 'served'}",
    "suffix": "axes={'<setting>': 'suffix'}",
    "sweeps": "a removed_pcs setting (the sweep hands removed_pcs to methods that have one)",
    "variants": "axes={'<setting>': 'rows'}",
    "uses": "needs=(...)",
    "needs_alignment": "needs=('aligned', ...)",
    "most_removed": "check (return None to leave a combination out)",
    "pca_components": "check (training.pca_components says what the shared fit holds)",
    "check_devices": "check (training.devices)",
    "shared_fit": "a SharedFit in the offering method's module, named in method_table.OFFERS",
}


def _names(value: Any, allowed: tuple[str, ...], what: str, ref: str) -> tuple[str, ...]:
    names = (value,) if isinstance(value, str) else tuple(value)
    if not all(isinstance(n, str) for n in names) or set(names) - set(allowed):
        raise UserError(
            f"method {ref}: {what}={value!r} is not a tuple of names of {', '.join(allowed)}"
        )
    return names


def _axes(value: Any, ref: str) -> dict[str, str]:
    if not isinstance(value, dict) or not all(
        isinstance(k, str) and v in AXIS_KINDS for k, v in value.items()
    ):
        raise UserError(
            f"method {ref}: axes={value!r} is not a dict of setting names to "
            f"{', '.join(repr(k) for k in AXIS_KINDS)}"
        )
    return dict(value)


def as_method(obj: Any, ref: str) -> Method:
    """``obj``'s fit, encode and declarations as a ``Method`` (absent ones: the defaults);
    UserError naming ``ref`` when they cannot serve."""
    if isinstance(obj, Method):
        return obj
    missing = [a for a in ("fit", "encode") if not callable(getattr(obj, a, None))]
    if missing:
        raise UserError(
            f"method {ref} has no callable {' or '.join(missing)}: give it fit(train, "
            "aligned, key) -> state and encode(state, images) -> (n, d) (docs/methods.md)"
        )
    old = [name for name in _REPLACED if hasattr(obj, name)]
    if old:
        raise UserError(
            f"method {ref} declares {old[0]}, which the contract no longer has: use "
            f"{_REPLACED[old[0]]} (docs/methods.md, 'Your own method')"
        )
    method = Method(**{f: getattr(obj, f) for f in Method._fields if hasattr(obj, f)})
    return method._replace(
        axes=method.axes if callable(method.axes) else _axes(method.axes, ref),
        needs=method.needs if callable(method.needs) else _names(method.needs, NEEDS, "needs", ref),
    )


def axes_of(method: Method, settings: Any) -> dict[str, str]:
    """How the method's settings vary, for these settings."""
    return method.axes(settings) if callable(method.axes) else method.axes


def needs_of(method: Method, settings: Any) -> tuple[str, ...]:
    """What the method needs, for these settings."""
    return method.needs(settings) if callable(method.needs) else method.needs


def needs_alignment(method: Method, settings: Any) -> bool:
    return ALIGNED in needs_of(method, settings)


def report_of(method: Method, state: Any, settings: dict) -> Report:
    return method.report(state, settings) if method.report is not None else Report()
