"""The one table of methods: every built-in method is one line here and one module under
``vpr_jax/methods/``, and a user's ``module:name`` joins them as the same kind of object.

A line names the method's object as ``"module:object"``: ``fit``, ``encode`` and the
declarations the runner reads instead of checking names (``vpr_jax.methods.contract``).
JAX-free: config validates ``methods=[...]`` against the table before JAX loads; the plan
imports the objects (``experiments.resolve``). Adding a built-in: a module with its
``Settings`` and ``method``, and one line in ``BUILTIN`` (docs/methods.md, "Adding a
built-in method"); its place here gives its hue in the learning-curve figure.

And descriptors computed elsewhere, read from ``.npy`` files
(``precomputed.<name>.database=PATH``, ``precomputed.<name>.queries=PATH``): each set is a
method of its own named ``<name>`` (``outside_info``), the one object ``OUTSIDE``
(``vpr_jax.methods.precomputed``) that keeps and looks up the set's rows.
"""

from __future__ import annotations

import importlib
import re
from typing import Any, NamedTuple

from vpr_jax.errors import UserError, first_line


class MethodInfo(NamedTuple):
    name: str  # results.csv's method column; its runs' and fitted states' folder names
    method: str  # "module:object" with fit, encode and declarations (methods.contract)
    plugin: bool = False  # a user's method (methods=[...,module:name])
    precomputed: bool = False  # a set of descriptors made elsewhere (precomputed.<name>.*)


BUILTIN: tuple[MethodInfo, ...] = (
    MethodInfo(name="raw", method="vpr_jax.methods.raw:method"),
    MethodInfo(name="pca", method="vpr_jax.methods.pca:method"),
    MethodInfo(name="diff_pca", method="vpr_jax.methods.diff_pca:method"),
    MethodInfo(name="ica", method="vpr_jax.methods.ica:method"),
    MethodInfo(name="lda", method="vpr_jax.methods.lda:method"),
    MethodInfo(name="fae", method="vpr_jax.methods.fae:method"),
    MethodInfo(name="cae", method="vpr_jax.methods.cae:method"),
)
METHODS: dict[str, MethodInfo] = {m.name: m for m in BUILTIN}
NAMES: tuple[str, ...] = tuple(METHODS)
# The method whose settings shape the pair's shared PCA fit (resource ``pca_fit``): its
# module's ``shared_fit``, made by the runner (experiments.fitting).
SHARED_PCA = "pca"
PRECOMPUTED = "precomputed"  # the methods entry that asks for outside descriptors only
OUTSIDE = "vpr_jax.methods.precomputed:method"  # the method every set of them is

# What a method that learns from aligned places is told on data without them.
ALIGNED_FIX = (
    "set data.train_source and data.train_root to an aligned route to learn from (e.g. "
    "Nordland's training places), or leave them out"
)
_PLUGIN = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$")
_SET_NAME = re.compile(r"^[A-Za-z_]\w*$")


def is_plugin(method: str) -> bool:
    """Whether a ``methods=`` entry names a user's method (``module:name``)."""
    return ":" in method


def plugin_name(spec: str) -> str:
    """The name a user's method goes by: the part after the colon."""
    return spec.rsplit(":", 1)[1]


def model_name(method: str, objective: str = "") -> str:
    """``fae`` for the paper's objective (and methods without one), ``fae_cross_season``
    otherwise: names the cell's run, the model's folder, its training run, its
    method-by-method run and its legend entry."""
    return method if objective in ("", "reconstruct") else f"{method}_{objective}"


def model_label(
    method: str, objective: str = "", setting: str = "", seed: int | None = None
) -> str:
    """A fitted model's name in runs, folders and legends: ``fae``, ``fae_cross_season``,
    ``ica_n_components=64``, ``fae_seed1`` (a seed only where it is not the data's)."""
    name = model_name(method, objective)
    if setting:
        name += f"_{run_suffix(setting)}"
    return name if seed is None else f"{name}_seed{seed}"


def run_suffix(setting: str) -> str:
    """A setting's label as part of a run or folder name: ``n_components=64``,
    ``hidden=256_init=pca``, ``channels=16-32`` for ``channels=[16,32]``; other characters a
    file name should not hold become ``-``."""
    plain = setting.replace(" ", "_").replace(",", "-").replace("[", "").replace("]", "")
    return re.sub(r"[^A-Za-z0-9._=+-]", "-", plain)


def check_methods(methods: tuple[str, ...]) -> str | None:
    """What is wrong with ``methods=[...]`` (built-in names and ``module:name`` entries), as
    one line naming the fix, or None."""
    unknown = [m for m in methods if not is_plugin(m) and m not in (*METHODS, PRECOMPUTED)]
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
    names = [plugin_name(m) for m in methods if is_plugin(m)]
    clash = [n for n in names if n in NAMES]
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


def check_precomputed(names: tuple[str, ...], methods: tuple[str, ...]) -> str | None:
    """What is wrong with the names of ``precomputed.<name>`` sets, as one line, or None:
    each a plain name that no built-in method or user's method of ``methods`` has."""
    taken = {*NAMES, *(plugin_name(m) for m in methods if is_plugin(m))}
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


def outside_info(name: str) -> MethodInfo:
    """A set of outside descriptors (``precomputed.<name>.*``) as a row of the table."""
    return MethodInfo(name=name, method=OUTSIDE, precomputed=True)


def info_of(entry: str) -> MethodInfo:
    """A ``methods=`` entry as a row of the table: a built-in's line, or a user's method."""
    if is_plugin(entry):
        return MethodInfo(name=plugin_name(entry), method=entry, plugin=True)
    return METHODS[entry]


def known_info(reference: str, plugins: tuple[str, ...] = ()) -> MethodInfo | None:
    """The row of a method a file names (``module:object``), found only by exact name: a
    built-in's line (or outside descriptors'), or a user's method that ``plugins`` names
    (its ``module:name`` or its module); None for anything else, which is never imported."""
    if not isinstance(reference, str):
        return None
    for info in (*BUILTIN, outside_info("")):
        if info.method == reference:
            return info
    module = reference.rsplit(":", 1)[0]
    if _PLUGIN.match(reference) and (reference in plugins or module in plugins):
        return MethodInfo(name=plugin_name(reference), method=reference, plugin=True)
    return None


def load_object(info: MethodInfo) -> Any:
    """The object a row names, imported now; a user's that cannot be: UserError (one line)."""
    module_name, name = info.method.rsplit(":", 1)
    try:
        module = importlib.import_module(module_name)
    except Exception as err:  # the user's module: any failure is theirs to see
        if not info.plugin:
            raise
        raise UserError(
            f"method {info.method}: module {module_name} does not import ({first_line(err)}): "
            f"put its folder on PYTHONPATH, and see its traceback with python -c 'import "
            f"{module_name}'"
        ) from None
    obj = getattr(module, name, None)
    if obj is None:
        raise UserError(
            f"method {info.method}: module {module_name} ({getattr(module, '__file__', '?')}) "
            f"has no {name}: name the object that has fit and encode"
        )
    return obj
