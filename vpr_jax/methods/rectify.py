"""A rectified code for any method whose descriptors are signed coordinates (pca, diff_pca,
ica, lda, a user's linear code): ``[relu(z), relu(-z)]``, the setting ``rectify``.

The cosine of two rectified codes sums ``a_i b_i`` only over the coordinates where both
images have the same sign, over the full norms (``|relu(z)|^2 + |relu(-z)|^2 = |z|^2``): a
coordinate that flips between seasons adds nothing instead of counting against the match.
It is the code an auto-encoder's linear start computes (each direction a ReLU unit beside
its negative, ``vpr_jax.encoders.autoencoders.linear_start``).

``rectifiable(method)`` gives a method the setting: its fit keeps the flag with its state
(``Rectified``: a fit per value, so a list ``[false,true]`` is an axis chosen on validation,
and ``load_encoder`` gives the same code back), its encode rectifies. A setting served as a
feature suffix (pca's removed count) is served one value at a time when rectified: a suffix
of a rectified code is not the rectified suffix.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from vpr_jax.methods.contract import SERVED, SUFFIX, Method, as_method


class Rectified(NamedTuple):
    """A fitted state whose code is rectified."""

    state: Any  # the method's own state


def rectified(z: Float[Array, "n d"]) -> Float[Array, "n 2d"]:
    """``[relu(z), relu(-z)]``: each coordinate's positive part, then its negative part."""
    return jnp.concatenate([jax.nn.relu(z), jax.nn.relu(-z)], axis=-1)


def _rectify(settings: Any) -> bool:
    """The ``rectify`` setting of a settings dataclass or dict (None: unset)."""
    if isinstance(settings, dict):
        return bool(settings.get("rectify", False))
    return bool(getattr(settings, "rectify", False))


def rectifiable(obj: Any) -> Method:
    """``obj`` (a ``Method`` or any object of the contract) with the setting ``rectify``: a
    settings dataclass of the method needs the field ``rectify: bool = False``."""
    method = as_method(obj, getattr(obj, "__name__", "rectifiable"))

    def fit(train, aligned, key, *, rectify: bool = False, **settings):
        state = method.fit(train, aligned, key, **settings)
        return Rectified(state) if rectify else state

    def encode(state, images, **served):
        if isinstance(state, Rectified):
            return rectified(method.encode(state.state, images, **served))
        return method.encode(state, images, **served)

    def axes(settings: Any) -> dict[str, str]:
        kinds = method.axes(settings)
        if not _rectify(settings):
            return kinds
        return {name: SERVED if kind == SUFFIX else kind for name, kind in kinds.items()}

    def report(state, settings: dict):
        return method.reported(state.state if isinstance(state, Rectified) else state, settings)

    return method._replace(fit=fit, encode=encode, axes=axes, report=report)
