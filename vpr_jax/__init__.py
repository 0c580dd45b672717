"""Condition-invariant visual place recognition across seasons, in JAX/Flax."""


def load_encoder(folder, *, plugins=(), **served):
    """``(encode_fn, params)`` of any method a sweep fitted: the folder it saved under
    ``train.checkpoint_dir`` (``python -m experiments.encoders LOGDIR`` lists them), or a
    trained auto-encoder's checkpoint folder.

    ``encode_fn(params, images) -> (n, d)`` is pure and jitted, images float32 ``(n, 32, 64)``
    in [0, 1]; ``served`` picks a value of a setting one fit served, e.g. ``removed_pcs=5``
    of a PCA or diff_pca fit (not given: the one chosen on the validation places). A folder
    is data only: a method of your own is imported when ``plugins=["module:name"]`` names
    it, never because a file says so. See ``vpr_jax.methods.loading.load_encoder``.
    """
    from vpr_jax.methods.loading import load_encoder as _load  # jax/flax only when used

    return _load(folder, plugins=plugins, **served)
