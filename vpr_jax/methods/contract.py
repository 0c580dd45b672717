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
RESOURCES = ("pca_fit", "validation", "training", "mesh", "outside", "input_options")
NEEDS = (ALIGNED, *RESOURCES)


class NotScored(Exception):
    """Raised by a method's ``fit`` (for every cell of the fit) or ``report`` (for that
    cell) when this pair's training set cannot serve it, e.g. a removed count beyond the
    numerical rank of repeated frames: the runner leaves those cells out with the message
    as a note and goes on. Nothing is scored that the data cannot define."""


class Report(NamedTuple):
    """What a fit found beyond its state: results.csv's fit columns (``REPORT_COLUMNS``,
    carried whole into each row), the run log's warning, the TensorBoard run's basis
    images."""

    n_iter: int = 0  # iterations of an iterative fit (epochs when trained); 0: closed form
    converged: bool = True  # False: an iterative fit stopped at its limit
    stopped_early: bool = False  # training ended before its last epoch
    kept_epoch: int | None = None  # a trained fit: the epoch whose weights it kept (0: its
    # start, untouched by training); None: the fit does not train
    start: str = ""  # a trained fit: what it started from, e.g. "lda in 256 directions"
    fit_seconds: float | None = None  # its own count (training over every session); None:
    # the runner's clock around fit
    warning: str | None = None  # one line for the run log
    basis: np.ndarray | None = None  # (m, 32 * 64): what the fit removed or learned
    basis_name: str = "basis"  # its TensorBoard tag: basis/<basis_name>
    validation: bool = True  # False: the state cannot describe the validation places (NaN
    # validation scores: nothing is chosen on them)
    start_state: Any = None  # a trained fit that kept a later epoch: its start as a state
    # ``encode`` takes, scored on the same queries (results.md's trained-against-start)

    @property
    def epochs_trained(self) -> int | None:
        """A trained fit's epochs (its ``n_iter``); None for a fit that does not train."""
        return None if self.kept_epoch is None else self.n_iter


# What of a report results.csv holds, each a column of that name (outputs.results).
REPORT_COLUMNS = ("n_iter", "converged", "stopped_early", "kept_epoch", "epochs_trained", "start")


class TrainingSet(NamedTuple):
    """What a method's ``check`` may ask before anything is fitted: the training set, the
    devices, and how its settings were given."""

    n_images: int  # both seasons' training images of a pair
    n_pixels: int
    aligned: bool  # whether the pair has aligned training places
    swept: dict[str, tuple]  # the values of each of the method's settings given as a list
    given: frozenset[str]  # the method's settings named on the command line
    pca_components: int = 0  # components the pair's shared PCA fit holds
    devices: int = 1  # devices a training batch is split over

    @property
    def pca_limit(self) -> int:
        """Principal components of the training images: min(n - 1, pixels)."""
        return min(self.n_images - 1, self.n_pixels)

    def check_pca_components(self, method: str, need: int) -> None:
        """UserError when ``method`` needs more leading components of the pair's shared PCA
        fit than it holds."""
        if need > self.pca_components:
            raise UserError(
                f"method {method} needs {need} components of the pair's PCA fit, which holds "
                f"{self.pca_components}: set pca.solver=covariance (every component), or a "
                "larger pca.subspace_components"
            )


def _no_axes(settings: Any) -> dict[str, str]:
    return {}


def _no_needs(settings: Any) -> tuple[str, ...]:
    return ()


class Method(NamedTuple):
    """A method: ``fit`` and ``encode`` and what the runner needs to know about them."""

    fit: Callable[..., Any]
    encode: Callable[..., Any]
    settings: type | None = None  # a frozen dataclass: names, defaults and checks of the
    # settings; None: any keyword settings (a user's plugin.<name>.*), unchecked
    axes: Callable[[Any], dict[str, str]] = _no_axes  # settings -> {setting: SERVED,
    # SUFFIX or ROWS}; given as the dict, ``as_method`` makes it this function
    needs: Callable[[Any], tuple[str, ...]] = _no_needs  # settings -> names of NEEDS; given
    # as the tuple, ``as_method`` makes it this function
    random: bool = True  # fit draws from its key: fitted once per seed of ``seeds``
    check: Callable[[Any, TrainingSet, Callable], Any] | None = None  # (settings, training
    # set, log) -> the settings fitted to it (notes in the log), None to leave this
    # combination out (with a note), or UserError
    report: Callable[[Any, dict], Report] | None = None  # (state, this cell's settings)

    def needs_alignment(self, settings: Any) -> bool:
        return ALIGNED in self.needs(settings)

    def reported(self, state: Any, settings: dict) -> Report:
        return self.report(state, settings) if self.report is not None else Report()


class PCAFit(NamedTuple):
    """The pair's shared PCA fit (resource ``pca_fit``): its state and what it cost."""

    state: Any  # vpr_jax.encoders.pca.PCAState
    seconds: float


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
    """``obj``'s fit, encode and declarations as a ``Method`` (absent ones: the defaults; a
    dict of ``axes`` or a tuple of ``needs``, checked now, as the function of the settings
    the runner reads: a declaration has that one form past here); UserError naming ``ref``
    when they cannot serve."""
    missing = [a for a in ("fit", "encode") if not callable(getattr(obj, a, None))]
    if missing:
        raise UserError(
            f"method {ref} has no callable {' or '.join(missing)}: give it fit(train, "
            "aligned, key) -> state and encode(state, images) -> (n, d) (docs/methods.md)"
        )
    method = (
        obj
        if isinstance(obj, Method)
        else Method(**{f: getattr(obj, f) for f in Method._fields if hasattr(obj, f)})
    )
    axes, needs = method.axes, method.needs
    if not callable(axes):
        checked_axes = _axes(axes, ref)
        axes = lambda settings: checked_axes  # noqa: E731
    if not callable(needs):
        checked_needs = _names(needs, NEEDS, "needs", ref)
        needs = lambda settings: checked_needs  # noqa: E731
    return method._replace(axes=axes, needs=needs)
