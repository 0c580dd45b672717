"""``input``: what a method is fitted on and encodes, one setting for every method that takes
it (``with_input``), so a list is an axis chosen on the validation places like any other.

The values are ``vpr_jax.encoders.inputs``'s parts (``pixels``, ``standardised``,
``patchnorm``, ``gradients``) or a combination of them joined by ``+``. ``pixels`` is the
method as it always was: its fit and its state unchanged, so a saved folder and the rows of
a sweep that never names an input stay as they were. Any other input is fitted on the
training images (a combination's scales) and kept with the method's state (``WithInput``):
the method fits and encodes the input's values, and ``load_encoder`` gives back the whole,
image to code, one pure jittable function. The options of the parts that have them
(``gradients.*``, ``patchnorm.*``) come from the runner (the resource ``input_options``).
"""

from __future__ import annotations

from typing import Any, NamedTuple

from vpr_jax.encoders import input_parts
from vpr_jax.errors import UserError
from vpr_jax.methods.contract import Method, as_method

PIXELS = "pixels"


class WithInput(NamedTuple):
    """A fitted state that encodes the input ``input`` of the images."""

    input: Any  # vpr_jax.encoders.inputs.InputState
    state: Any  # the method's own state, fitted on the input's values


def input_of(settings: Any) -> str:
    """The ``input`` setting of a settings dataclass or dict (``pixels`` where unset)."""
    if isinstance(settings, dict):
        return str(settings.get("input", PIXELS))
    return str(getattr(settings, "input", PIXELS))


def seen(state, images, aligned):
    """The training images and the aligned places as the input shows them (``state``: an
    ``InputState``)."""
    from vpr_jax.encoders import inputs

    pairs = None if aligned is None else tuple(inputs.apply(state, x) for x in aligned)
    return inputs.apply(state, images), pairs


def with_input(obj: Any) -> Method:
    """``obj`` (a ``Method`` or any object of the contract) with the setting ``input``: a
    settings dataclass of the method needs the field ``input: str = "pixels"``."""
    method = as_method(obj, getattr(obj, "__name__", "with_input"))

    def fit(train, aligned, key, *, input: str = PIXELS, input_options=None, **settings):
        if input == PIXELS:
            return method.fit(train, aligned, key, **settings)
        from vpr_jax.encoders import inputs  # JAX: not before a fit

        state = inputs.fit(input, train, input_options or inputs.DEFAULTS)
        train, aligned = seen(state, train, aligned)
        return WithInput(state, method.fit(train, aligned, key, **settings))

    def encode(state, images, **served):
        if isinstance(state, WithInput):
            from vpr_jax.encoders import inputs

            return method.encode(state.state, inputs.apply(state.input, images), **served)
        return method.encode(state, images, **served)

    def needs(settings: Any) -> tuple[str, ...]:
        own = tuple(method.needs(settings))
        return own if input_of(settings) == PIXELS else (*own, "input_options")

    def report(state, settings: dict):
        return method.reported(state.state if isinstance(state, WithInput) else state, settings)

    return method._replace(fit=fit, encode=encode, needs=needs, report=report)


def check_input(settings: Any, group: str) -> None:
    """The ``input`` of ``settings`` names known parts, each once; else a UserError naming
    the fix."""
    name = input_of(settings)
    try:
        input_parts.parts_of(name)
    except ValueError as err:
        raise UserError(
            f"{group}.input={name}: {err}: use one of {', '.join(input_parts.PARTS)}, or parts "
            "joined by + (standardised+gradients)"
        ) from None
