"""The one shape of a method, built-in or a user's (optax's ``GradientTransformation`` is the
model: a NamedTuple of pure functions):

    fit(train, aligned, key, **settings, **resources) -> state
    encode(state, images, **served) -> (n, d)

``train``: float32 ``(n, 32, 64)`` in [0, 1], both seasons' training images; ``aligned``:
None or ``(database season, query season)`` with row i one place; ``key``: a ``jax.random``
key of one of the sweep's ``seeds``; ``settings``: the method's settings of this fit (a
list given for one is a sweep axis, ``vpr_jax.methods.settings``); ``resources``: what the
method ``uses`` from the runner (``Resources``). ``state`` is a pytree of arrays and
``encode`` is pure and jittable; its rows are compared by cosine.

Everything beside ``fit`` and ``encode`` is an optional declaration the runner reads
instead of checking the method's name; ``as_method`` reads them from any object (a user's
class with static methods and class attributes has the same shape as a built-in
``Method``). docs/methods.md, "Your own method", documents each with an example.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from vpr_jax.errors import UserError

# What a method's fit may ask the runner for, by keyword (``uses``).
RESOURCES = ("pca_fit", "validation", "training", "mesh")
SWEEP_AXES = ("removed_pcs",)  # the sweep's own axes a method may take (``sweeps``)


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


class TrainingSet(NamedTuple):
    """What a method's ``check`` may ask of the training set before anything is fitted."""

    n_images: int  # both seasons' training images of a pair
    n_pixels: int
    aligned: bool  # whether the pair has aligned training places
    removed_pcs: tuple[int, ...]  # the sweep's removed counts, trimmed to the training set
    given: frozenset[str]  # the method's settings named on the command line
    asked: frozenset[str]  # ... or by a preset that names its data (what it asks for by name)

    @property
    def pca_limit(self) -> int:
        """Principal components of the training images: min(n - 1, pixels)."""
        return min(self.n_images - 1, self.n_pixels)


class SharedFit(NamedTuple):
    """The fit a pair shares with every method that ``uses`` ``pca_fit``. It holds a count
    of components that depends on the data and its own settings only, never on which
    methods use it (each takes the leading ones it needs): a method's numbers do not depend
    on what else is in ``methods``, and its shapes (so its compiled code) not on its own
    settings."""

    components: Callable[[Any, int, int], int]  # (settings, n_images, n_pixels) -> the
    # components the fit holds
    fit: Callable[..., Any]  # (train, n_components, settings, mesh, seed) -> its state
    fix: str  # how a user gets more components than it holds (an error's advice)


class Method(NamedTuple):
    """A method: ``fit`` and ``encode`` and what the runner needs to know about them."""

    fit: Callable[..., Any]
    encode: Callable[..., Any]
    settings: type | None = None  # a frozen dataclass: names, defaults and checks of the
    # settings; None: any keyword settings (a user's plugin.<name>.*), unchecked
    sweeps: tuple[str, ...] = ()  # the sweep's own axes it takes as settings (removed_pcs)
    serves: tuple[str, ...] = ()  # settings one fit serves: encode takes them, fit does not
    suffix: str | Callable[[Any], str] = ""  # a served setting v whose descriptors are
    # encode(state, x)[:, v:]: one encoding and one matching pass serve every value (a
    # callable: of the settings)
    needs_alignment: bool = False  # fit needs ``aligned`` (refused on data without it)
    uses: tuple[str, ...] = ()  # resources fit takes by keyword (RESOURCES)
    random: bool = True  # fit draws from its key: fitted once per seed of ``seeds``
    variants: str = ""  # a setting whose values are rows of their own, never chosen among
    check: Callable[[Any, TrainingSet, Callable], Any] | None = None  # (settings, training
    # set, log) -> the settings fitted to it (notes in the log), or UserError
    most_removed: Callable[[Any, TrainingSet], tuple[int, str]] | None = None  # (settings,
    # training set) -> the largest removed count it serves there, and why (trims removed_pcs)
    pca_components: Callable[[Any, TrainingSet], int] | None = None  # (settings, training
    # set) -> leading components of the pair's PCA fit it needs (0: none)
    report: Callable[[Any, dict], Report] | None = None  # (state, this cell's settings)
    check_devices: Callable[[Any, Any, Any], None] | None = None  # (settings, train.*, the
    # device mesh): what the devices must allow, checked before anything is written
    shared_fit: SharedFit | None = None  # the fit a pair shares with every method that
    # uses pca_fit (the method vpr_jax.method_table.SHARED_FIT names offers it)


class PCAFit(NamedTuple):
    """The pair's shared PCA fit (resource ``pca_fit``): its state and what it cost."""

    state: Any  # vpr_jax.encoders.pca.PCAState
    seconds: float
    removed_pcs: tuple[int, ...]  # the sweep's removed counts (what a residual input picks from)
    asked: int = 0  # components asked for; the state holds fewer where the training
    # images' numerical rank is lower (vpr_jax.encoders.pca.numerical_rank)


class Validation(NamedTuple):
    """The validation places (resource ``validation``), scored as the sweep scores them:
    what the auto-encoders pick epochs by and residual inputs pick a count by."""

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
    settings: Any  # the sweep's train.* (vpr_jax.config.TrainConfig)


def _tuple_of_names(value: Any, allowed: tuple[str, ...] | None, what: str, ref: str) -> tuple:
    names = (value,) if isinstance(value, str) else tuple(value)
    if not all(isinstance(n, str) for n in names) or (
        allowed is not None and set(names) - set(allowed)
    ):
        known = f": use names of {', '.join(allowed)}" if allowed else ""
        raise UserError(f"method {ref}: {what}={value!r} is not a tuple of names{known}")
    return names


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
    found = {f: getattr(obj, f) for f in Method._fields if hasattr(obj, f)}
    method = Method(**found)
    return method._replace(
        sweeps=_tuple_of_names(method.sweeps, SWEEP_AXES, "sweeps", ref),
        serves=_tuple_of_names(method.serves, None, "serves", ref),
        uses=_tuple_of_names(method.uses, RESOURCES, "uses", ref),
    )


def suffix_of(method: Method, settings: Any) -> str:
    """The served setting whose values are feature suffixes for these settings ('' none)."""
    return method.suffix(settings) if callable(method.suffix) else method.suffix


def report_of(method: Method, state: Any, settings: dict) -> Report:
    return method.report(state, settings) if method.report is not None else Report()
