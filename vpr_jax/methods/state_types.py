"""The table of types a saved folder may name: every class a built-in method's fitted state
is made of, by the name its ``skeleton.json`` gives it (``module:qualname``), and, only when
the user names their method, the state types of that method's module.

Restoring a folder looks its classes up here and never imports what a file names
(docs/guide.md, "Files you did not make"). Folders saved by earlier versions name classes as
they were then: a class that moves or is renamed keeps its old name here as a second key
(tests/data/format2_encoders holds a folder of each kind, saved before this table).
"""

from __future__ import annotations

import dataclasses
from types import ModuleType

from vpr_jax.encoders import autoencoders, diff_pca, ica, inputs, lda, pca
from vpr_jax.encoders.fitted_state import type_name
from vpr_jax.methods import inputs as inputs_method
from vpr_jax.methods import lda as lda_method
from vpr_jax.methods import pca as pca_method
from vpr_jax.methods import rectify

BUILTIN_STATE_TYPES: tuple[type, ...] = (
    pca.PCAState,
    pca_method.InPixels,
    pca_method.Whitened,
    diff_pca.DiffPCAState,
    ica.ICAState,
    lda.LDAState,
    lda_method.Standardised,
    rectify.Rectified,
    inputs.InputState,
    inputs.Options,
    inputs_method.WithInput,
    autoencoders.ModelState,
    autoencoders.FAESpec,
    autoencoders.CAESpec,
)


def _is_state_type(value: object) -> bool:
    """A NamedTuple class or a dataclass: the classes a fitted state is made of."""
    if not isinstance(value, type):
        return False
    return (issubclass(value, tuple) and hasattr(value, "_fields")) or dataclasses.is_dataclass(
        value
    )


def state_types(plugin_modules: tuple[ModuleType, ...] = ()) -> dict[str, type]:
    """``type_name`` -> class: the built-in state types, and every NamedTuple and dataclass
    at the top level of each of ``plugin_modules`` (a user's method's module, imported
    because the user named it)."""
    table = {type_name(kind): kind for kind in BUILTIN_STATE_TYPES}
    for module in plugin_modules:
        for value in vars(module).values():
            if _is_state_type(value):
                table.setdefault(type_name(value), value)
    return table
