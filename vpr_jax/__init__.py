"""Condition-invariant visual place recognition across seasons, in JAX/Flax."""


def load_encoder(checkpoint_dir):
    """``(encode_fn, params)`` of a trained auto-encoder checkpoint folder.

    ``encode_fn(params, images) -> (n, code)`` is pure and jitted. See
    ``vpr_jax.encoders.saved.load_encoder``.
    """
    from vpr_jax.encoders.saved import load_encoder as _load  # jax/flax only when used

    return _load(checkpoint_dir)
