"""Trained auto-encoders from their checkpoint folders, as a pure encoder and its parameters."""

from __future__ import annotations

from pathlib import Path

import jax

from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import checkpoints
from vpr_jax.errors import UserError


def load_encoder(checkpoint_dir: str | Path):
    """``(encode_fn, params)`` of a trained auto-encoder checkpoint folder (its best epoch).

    ``encode_fn(params, images) -> (n, code)`` is jitted and pure: use it inside your own
    jitted functions, vmap it, differentiate through it.
    """
    checkpoint_dir = Path(checkpoint_dir)
    meta = checkpoints.read_meta(checkpoint_dir)
    try:
        spec = ae.spec_from_json(meta["spec"])
    except (KeyError, TypeError, ValueError) as err:
        raise UserError(
            f"{checkpoint_dir} holds no auto-encoder this suite knows ({err})"
        ) from None
    graphdef, like = ae.build(spec, jax.random.key(0), tuple(meta["image_shape"]))
    return ae.make_encode(graphdef), checkpoints.restore_model(checkpoint_dir, like)
