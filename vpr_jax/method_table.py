"""The one table of methods: every built-in method named once, with what the rest of the
suite asks of it, and how a user's ``module:name`` joins them.

JAX-free (config validates ``methods=[...]`` against it before JAX loads); a method's code
is named by a ``"module:function"`` string and imported only when the sweep runs it.

Two ways in, one list of methods:
- a built-in method is a ``describe(pair, cfg, ctx)`` generator of ``Descriptors`` (the
  runner's protocol: validation images, the pair's shared PCA fit, checkpoints, the device
  mesh; ``vpr_jax.methods``). Adding one: a module under ``vpr_jax/methods/`` and one line in
  ``BUILTIN`` (docs/methods.md, "Adding a method");
- a user's method is ``methods=[...,package.module:name]``: an object with ``fit(train,
  aligned, key, **settings) -> state`` and ``encode(state, images) -> (n, d)``
  (``vpr_jax.methods.plugin``). Its row, run and folder are named ``name``.

And one source of descriptors that is not a fitted method: ``PRECOMPUTED``, descriptors
computed elsewhere and read from ``.npy`` files (``precomputed.<name>.database=PATH``,
``precomputed.<name>.queries=PATH``; ``vpr_jax.methods.precomputed``). Each set is a row
named ``<name>``; it fits nothing, so nothing is saved or exported as an encoder.
"""

from __future__ import annotations

import importlib
import re
from typing import Any, NamedTuple

from vpr_jax.errors import UserError, first_line


class MethodInfo(NamedTuple):
    name: str  # results.csv's method column; the runs' and fitted states' folder names
    describe: str  # "module:function" of its describe(pair, cfg, ctx) -> Descriptors
    sweeps_removed_pcs: bool = False  # one cell per removed-PC count (one fit serves them)
    needs_alignment: bool = False  # learns from aligned training places of two seasons
    uses_pca_fit: bool = False  # its context carries the pair's shared PCA fit
    trained: bool = False  # an auto-encoder: an objective axis, epochs, training checkpoints
    plugin: str = ""  # a user's method: its "module:name"; "" for the built-in ones
    precomputed: bool = False  # descriptors made elsewhere: nothing fitted, saved or exported


_LINEAR, _AE = "vpr_jax.methods.linear", "vpr_jax.methods.autoencoders"
BUILTIN: tuple[MethodInfo, ...] = (
    MethodInfo(
        name="raw",
        describe=f"{_LINEAR}:describe_raw",
    ),
    MethodInfo(
        name="pca",
        describe=f"{_LINEAR}:describe_pca",
        sweeps_removed_pcs=True,
        uses_pca_fit=True,
    ),
    MethodInfo(
        name="diff_pca",
        describe=f"{_LINEAR}:describe_diff_pca",
        sweeps_removed_pcs=True,
        needs_alignment=True,
    ),
    MethodInfo(
        name="ica",
        describe=f"{_LINEAR}:describe_ica",
        sweeps_removed_pcs=True,
        uses_pca_fit=True,
    ),
    MethodInfo(
        name="lda",
        describe=f"{_LINEAR}:describe_lda",
        needs_alignment=True,
        uses_pca_fit=True,
    ),
    MethodInfo(
        name="fae",
        describe=f"{_AE}:describe_fae",
        trained=True,
    ),
    MethodInfo(
        name="cae",
        describe=f"{_AE}:describe_cae",
        trained=True,
    ),
)
# Descriptors computed elsewhere: a source, not a method the suite fits (see the docstring).
PRECOMPUTED = MethodInfo(
    name="precomputed",
    describe="vpr_jax.methods.precomputed:describe_precomputed",
    precomputed=True,
)
METHODS: dict[str, MethodInfo] = {m.name: m for m in BUILTIN}
NAMES: tuple[str, ...] = tuple(METHODS)
SWEEPS_REMOVED_PCS = frozenset(m.name for m in BUILTIN if m.sweeps_removed_pcs)
NEEDS_ALIGNED = tuple(m.name for m in BUILTIN if m.needs_alignment)
TRAINED = frozenset(m.name for m in BUILTIN if m.trained)
PLUGIN_DESCRIBE = "vpr_jax.methods.plugin:describe_plugin"

# What a method that learns from aligned places is told on data without them.
ALIGNED_FIX = (
    "set data.train_source and data.train_root to an aligned route to learn from (e.g. "
    "Nordland's training places), or leave them out"
)
_PLUGIN = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$")


def is_plugin(method: str) -> bool:
    """Whether a ``methods=`` entry names a user's method (``module:name``)."""
    return ":" in method


def model_name(method: str, objective: str = "") -> str:
    """``fae`` for the seed's objective (and methods without one), ``fae_cross_season``
    otherwise: names the cell's run, the model's checkpoint folder, its training run, its
    method-by-method run and its legend entry."""
    return method if objective in ("", "reconstruct") else f"{method}_{objective}"


def plugin_name(spec: str) -> str:
    """The name a user's method goes by: the part after the colon."""
    return spec.rsplit(":", 1)[1]


def check_methods(methods: tuple[str, ...], objectives: tuple[str, ...]) -> str | None:
    """What is wrong with ``methods=[...]`` (built-in names and ``module:name`` entries), as
    one line naming the fix, or None. ``objectives``: the auto-encoders' objectives, whose
    run names (``fae_cross_season``) a plugin may not take."""
    unknown = [m for m in methods if not is_plugin(m) and m not in (*METHODS, PRECOMPUTED.name)]
    if unknown:
        return (
            f"methods={list(methods)} names unknown {unknown}: choose from {', '.join(NAMES)}, "
            "or name your own as module:name (docs/methods.md)"
        )
    malformed = [m for m in methods if is_plugin(m) and not _PLUGIN.match(m)]
    if malformed:
        return (
            f"methods entry {malformed[0]!r} is not module:name: write e.g. "
            "my_package.my_module:my_method"
        )
    taken = {*NAMES, *(f"{m}_{o}" for m in TRAINED for o in objectives)}
    names = [plugin_name(m) for m in methods if is_plugin(m)]
    clash = [n for n in names if n in taken]
    if clash:
        return (
            f"your method {clash[0]!r} has the name of a built-in method or run: rename the "
            "object in its module (its name is what results.csv and the runs call it)"
        )
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        return f"two of your methods are called {twice[0]!r}: give them different names"
    repeated = sorted({m for m in methods if methods.count(m) > 1})
    if repeated:
        return f"methods names {repeated[0]!r} twice: name each method once"
    return None


_SET_NAME = re.compile(r"^[A-Za-z_]\w*$")


def check_precomputed(names: tuple[str, ...], methods: tuple[str, ...], objectives) -> str | None:
    """What is wrong with the names of ``precomputed.<name>`` sets, as one line, or None:
    each a plain name that no built-in method, run or user's method of ``methods`` has."""
    taken = {*NAMES, *(f"{m}_{o}" for m in TRAINED for o in objectives)}
    taken |= {plugin_name(m) for m in methods if is_plugin(m)}
    for name in names:
        if not _SET_NAME.match(name):
            return (
                f"precomputed set name {name!r} is not a plain name: use letters, digits and "
                "_ (precomputed.netvlad.database=PATH)"
            )
        if name in taken:
            return (
                f"precomputed set {name!r} has the name of a method of this sweep: name it "
                "another way (precomputed.name=NAME, or precomputed.<NAME>.database=PATH)"
            )
    return None


def precomputed_info(name: str) -> MethodInfo:
    """A set of outside descriptors as a row of the table."""
    return PRECOMPUTED._replace(name=name)


def plugin_info(spec: str, needs_alignment: bool) -> MethodInfo:
    """A user's method as a row of the table."""
    name = plugin_name(spec)
    return MethodInfo(
        name=name,
        describe=PLUGIN_DESCRIBE,
        needs_alignment=needs_alignment,
        plugin=spec,
    )


def load_plugin(spec: str) -> Any:
    """The object ``module:name`` names, checked for ``fit`` and ``encode``; UserError (one
    line) when it cannot serve."""
    module_name, name = spec.rsplit(":", 1)
    try:
        module = importlib.import_module(module_name)
    except Exception as err:  # the user's module: any failure is theirs to see
        raise UserError(
            f"method {spec}: module {module_name} does not import ({first_line(err)}): put its "
            f"folder on PYTHONPATH, and see its traceback with python -c 'import {module_name}'"
        ) from None
    obj = getattr(module, name, None)
    if obj is None:
        raise UserError(
            f"method {spec}: module {module_name} ({getattr(module, '__file__', '?')}) has no "
            f"{name}: name the object that has fit and encode"
        )
    missing = [a for a in ("fit", "encode") if not callable(getattr(obj, a, None))]
    if missing:
        raise UserError(
            f"method {spec} has no callable {' or '.join(missing)}: give it fit(train, "
            "aligned, key) -> state and encode(state, images) -> (n, d) (docs/methods.md)"
        )
    return obj


def resolve_methods(
    methods: tuple[str, ...], aligned: bool, source: str, precomputed: tuple[str, ...] = ()
) -> tuple[MethodInfo, ...]:
    """The table rows of ``methods=[...]``, users' methods imported and checked, then the
    ``precomputed`` sets' rows; a method that needs aligned training places on data without
    them (``aligned`` False) is refused the way a named diff_pca is."""
    out = []
    for method in methods:
        if not is_plugin(method):
            out.append(METHODS[method])
            continue
        needs = bool(getattr(load_plugin(method), "needs_alignment", False))
        if needs and not aligned:
            raise UserError(
                f"method {method} learns from aligned training places (needs_alignment), "
                f"which data.source={source} does not have: {ALIGNED_FIX}"
            )
        out.append(plugin_info(method, needs))
    return (*out, *(precomputed_info(name) for name in precomputed))


def describe_function(info: MethodInfo):
    """The runner's ``describe(pair, cfg, ctx)`` of a table row, imported now."""
    module_name, name = info.describe.split(":")
    function = getattr(importlib.import_module(module_name), name)
    if info.plugin or info.precomputed:
        return lambda pair, cfg, ctx: function(info, pair, cfg, ctx)
    return function
