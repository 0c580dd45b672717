"""Condition-invariant visual place recognition across seasons, in JAX/Flax."""


def load_encoder(folder, removed_pcs=None):
    """``(encode_fn, params)`` of any method a sweep fitted: the folder it saved under
    ``train.checkpoint_dir`` (``python -m experiments.encoders LOGDIR`` lists them), or a
    trained auto-encoder's checkpoint folder.

    ``encode_fn(params, images) -> (n, d)`` is pure and jitted, images float32 ``(n, 32, 64)``
    in [0, 1]; ``removed_pcs`` picks a count of a PCA or diff_pca fit (None: the one chosen on
    the validation places). See ``vpr_jax.encoders.saved.load_encoder``.
    """
    from vpr_jax.encoders.saved import load_encoder as _load  # jax/flax only when used

    return _load(folder, removed_pcs)
