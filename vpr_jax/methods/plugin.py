"""A user's method (``methods=[...,package.module:name]``) through the runner's protocol.

The named object has ``fit(train, aligned, key, **settings) -> state`` and a pure
``encode(state, images) -> (n, d)``:

- ``train``: float32 ``(n, 32, 64)`` in [0, 1], the training images of both seasons of the
  pair (the preprocessing of the sweep applied);
- ``aligned``: ``None``, or ``(database_season, query_season)``, two float32 ``(m, 32, 64)``
  arrays whose row i shows one place (the pair's aligned training places);
- ``key``: a ``jax.random`` key of the sweep's ``seed`` and the method's name;
- ``settings``: ``plugin.<name>.<key>=<value>`` from the command line;
- ``state``: any pytree of arrays (dicts, lists, tuples, NamedTuples);
- ``encode`` runs under ``jax.jit``; its output rows are the descriptors, compared by cosine.

Whatever goes wrong inside the user's code stops the sweep with one line naming the method
(exit code 2, the cells already finished kept); the traceback goes to sweep.log.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable, Iterator

import jax
import jax.numpy as jnp

from vpr_jax.config import SweepConfig
from vpr_jax.data.pair import PairData
from vpr_jax.errors import UserError, first_line
from vpr_jax.method_table import MethodInfo, load_plugin
from vpr_jax.methods.descriptors import (
    Descriptors,
    Fitted,
    MethodContext,
    describe,
    method_key,
    timed,
)


def _fails(info: MethodInfo, step: str, err: Exception) -> UserError:
    return UserError(
        f"method {info.name} ({info.plugin}): {step} raised {first_line(err)}: fix it and "
        "rerun the same command, the finished cells are kept (the traceback is in sweep.log)",
        detail=traceback.format_exc(),
    )


def checked_encode(info: MethodInfo, encode: Callable) -> Callable:
    """``encode`` jitted, its output checked: one row per image, two dimensions, finite."""
    jitted = jax.jit(encode)

    def run(state, images):
        try:
            out = jitted(state, jnp.asarray(images))
        except Exception as err:  # the user's code
            raise _fails(info, "encode", err) from None
        shape = getattr(out, "shape", None)
        if shape is None or len(shape) != 2 or shape[0] != len(images):
            raise UserError(
                f"method {info.name} ({info.plugin}): encode gave shape {shape} for "
                f"{len(images)} images: return one row per image, (n, d)"
            )
        if not bool(jnp.isfinite(out).all()):
            raise UserError(
                f"method {info.name} ({info.plugin}): encode gave NaN or infinite descriptors "
                f"for {len(images)} images: check its state and its arithmetic"
            )
        return out

    return run


def describe_plugin(
    info: MethodInfo, pair: PairData, cfg: SweepConfig, ctx: MethodContext
) -> Iterator[Descriptors]:
    """Fit the user's method on the pair's training images (and its aligned places, when the
    pair has them), then encode the database, queries and validation places."""
    obj = load_plugin(info.plugin)
    aligned = pair.aligned_train if pair.aligned_training else None
    settings = dict(cfg.plugin.get(info.name, {}))
    key = method_key(cfg.seed, info.name)
    try:
        state, fit_s = timed(lambda: obj.fit(pair.train, aligned, key, **settings))
    except Exception as err:  # the user's code
        raise _fails(info, "fit", err) from None
    encode = checked_encode(info, obj.encode)
    fitted = Fitted(folder=info.name, encode="plugin", state=state)
    yield describe(info.name, lambda x: encode(state, x), pair, fit_seconds=fit_s, fitted=fitted)
