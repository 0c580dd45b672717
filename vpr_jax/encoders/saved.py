"""Every fitted method as an encoder you can take away: ``load_encoder(folder)`` gives
``(encode_fn, params)`` for raw, pca, diff_pca, ica, lda, the auto-encoders and a user's
``module:name`` method, from the folders a sweep saves under ``train.checkpoint_dir``.

A folder holds the fitted state (``fitted_state``; the auto-encoders: their training
checkpoint), ``fit.json`` (what was fitted, written when the fit ends) and ``encoder.json``
(the description a user reads, written with the pair's summary: the method, objective,
pair, the validation-selected removed-PC count, its validation recall@1, the
preprocessing). ``encode_fn(params, images)`` is pure and jitted and includes every step
after reading: images float32 ``(n, 32, 64)`` in [0, 1] (grey, resized to 64x32 with
OpenCV's area interpolation, divided by 255), then patch normalisation when the sweep used
it (float32 here, float64 in the sweep: the descriptors agree to about 1e-5 relative).
"""

from __future__ import annotations

import functools
import importlib.metadata
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from vpr_jax.data.preprocess import patch_normalize_jax
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import checkpoints, ica, lda, pca
from vpr_jax.encoders.fitted_state import restore_state, save_state
from vpr_jax.errors import UserError
from vpr_jax.files import atomic_write_text
from vpr_jax.method_table import load_plugin

FORMAT = 1  # of encoder.json and fit.json; a newer one is refused
ENCODER_JSON, FIT_JSON = "encoder.json", "fit.json"


# How a saved state encodes: ``encode(state, images, removed_pcs) -> (n, d)``, the
# descriptors the sweep compared by cosine. A method names its function in its ``Fitted``
# (``"vpr_jax.encoders.saved:encode_centred"``); fit.json keeps the name.


def encode_centred(state, images, removed_pcs):
    """Raw pixels: flattened, the training mean subtracted."""
    return pca.flatten(images) - state["mean"]


def encode_suffix(state, images, removed_pcs):
    """PCA or diff_pca, ``removed_pcs`` removed: the suffix ``[k:]`` of its coefficients and
    residual (``pca.suffix_descriptors``)."""
    return pca.suffix_descriptors(state, images)[:, removed_pcs:]


def encode_pixels(state, images, removed_pcs):
    """PCA with ``pca.output=pixels``: the change-removed image itself."""
    return pca.encode(state, images, removed_pcs, "pixels")


def encode_ica(state, images, removed_pcs):
    return ica.encode(state, images)


def encode_lda(state, images, removed_pcs):
    return lda.encode(state, images)


def _encode_function(name: str, folder: Path) -> Callable:
    module, _, function = name.partition(":")
    if not module.startswith("vpr_jax.") or not function:
        raise UserError(f"{folder / FIT_JSON} names encode {name!r}: not one of vpr_jax's")
    try:
        return getattr(importlib.import_module(module), function)
    except (ImportError, AttributeError):
        raise UserError(f"{folder} needs {name}, which this vpr_jax lacks: update it") from None


def read_description(folder: Path, name: str = ENCODER_JSON) -> dict:
    """``encoder.json`` (or ``fit.json``) of a folder; one that is missing, unreadable or of
    a newer suite: UserError naming the folder."""
    path = Path(folder).expanduser() / name
    try:
        description = json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(
            f"{path.parent} holds no encoder ({name} is missing): point at a folder a finished "
            "sweep saved (python -m experiments.encoders LOGDIR lists them)"
        ) from None
    except (OSError, ValueError) as err:
        raise UserError(f"{path} cannot be read ({err}): rerun the sweep that wrote it") from None
    found = description.get("format") if isinstance(description, dict) else None
    if found != FORMAT:
        raise UserError(
            f"{path} is of format {found}, this suite reads {FORMAT}: "
            + ("update vpr_jax" if isinstance(found, int) and found > FORMAT else "refit it")
        )
    return description


def suite_version() -> str:
    """The installed vpr_jax's version, as descriptions record it."""
    try:
        return importlib.metadata.version("vpr_jax")
    except importlib.metadata.PackageNotFoundError:  # run from a checkout, not installed
        return "unknown"


def save_fitted(folder: Path, encode: str, state: Any, description: dict) -> None:
    """Save a fitted state and its ``fit.json`` (``description`` and how it encodes: a
    ``"module:function"``, ``"autoencoder"`` or ``"plugin"``) as ``folder``; an
    auto-encoder's state is its training checkpoint, already in ``folder``."""
    text = json.dumps({"format": FORMAT, "encode": encode, **description}, indent=1)
    if encode == "autoencoder":
        atomic_write_text(Path(folder) / FIT_JSON, text)
    else:
        save_state(folder, state, {FIT_JSON: text})


def describe_encoder(folder: Path, selection: dict) -> dict:
    """Write ``encoder.json``: the folder's ``fit.json`` and ``selection`` (the chosen count,
    its validation and test recall@1, its run). Returns it."""
    description = {**read_description(folder, FIT_JSON), **selection}
    atomic_write_text(Path(folder) / ENCODER_JSON, json.dumps(description, indent=1))
    return description


def _preprocess(description: dict) -> Callable[[jax.Array], jax.Array]:
    norm = description.get("preprocessing", {}).get("patchnorm")
    if not norm:
        return lambda images: images
    return functools.partial(patch_normalize_jax, size=norm["size"], rounded=norm["rounded"])


def _served(description: dict, removed_pcs: int | None, folder: Path) -> int:
    counts = description.get("counts", [0])
    k = description.get("removed_pcs", counts[0]) if removed_pcs is None else int(removed_pcs)
    if k not in counts:
        raise UserError(
            f"{folder} serves removed_pcs {counts}, not {k}: pass one of them (or None for the "
            "count chosen on the validation places)"
        )
    return k


def _autoencoder(folder: Path):
    """The trained model's encoder and its best parameters (from its training checkpoint)."""
    meta = checkpoints.read_meta(folder)
    try:
        spec = ae.spec_from_json(meta["spec"])
    except (KeyError, TypeError, ValueError) as err:
        raise UserError(f"{folder} holds no auto-encoder this suite knows ({err})") from None
    graphdef, like = ae.build(spec, jax.random.key(0), tuple(meta["image_shape"]))
    model_encode = ae.make_encode(graphdef)
    return (lambda params, images, k: model_encode(params, images)), checkpoints.restore_model(
        folder, like
    )


class StoredEncoder(NamedTuple):
    """A saved folder's parts: ``encode(params, images)`` on preprocessed images, as the
    sweep called it (not jitted as a whole: the sweep's own jitted steps, so its descriptors
    come back bit for bit), the fitted state and the preprocessing the sweep applied."""

    encode: Callable
    params: Any
    preprocess: Callable[[jax.Array], jax.Array]


def stored_encoder(folder: str | Path, removed_pcs: int | None = None) -> StoredEncoder:
    """The parts ``load_encoder`` composes (see there for the arguments)."""
    folder = Path(folder).expanduser().resolve()
    if not (folder / ENCODER_JSON).exists() and checkpoints.has_checkpoint(folder):
        description = {"encode": "autoencoder"}  # a model fit_autoencoder trained, as it is
    else:
        description = read_description(folder)
    how = str(description.get("encode"))
    k = _served(description, removed_pcs, folder)
    if how == "autoencoder":
        encode, params = _autoencoder(folder)
    elif how == "plugin":
        user_encode = jax.jit(load_plugin(description["method"]).encode)
        encode, params = (
            (lambda state, images, _: user_encode(state, images)),
            restore_state(folder),
        )
    else:
        encode, params = _encode_function(how, folder), restore_state(folder)
    return StoredEncoder(
        encode=functools.partial(lambda fn, p, x: fn(p, x, k), encode),
        params=jax.tree.map(jnp.asarray, params),
        preprocess=_preprocess(description),
    )


def load_encoder(folder: str | Path, removed_pcs: int | None = None):
    """``(encode_fn, params)`` of a folder a sweep saved: ``encode_fn(params, images) -> (n,
    d)`` is pure and jitted (use it in your own jitted code, vmap it, differentiate through
    it); ``params`` is the fitted state. ``removed_pcs``: for pca, diff_pca (one fit serves
    every count the sweep ran) the count to remove; None: the one chosen on the validation
    places. A checkpoint folder of ``fit_autoencoder`` (no sweep around it) loads too."""
    stored = stored_encoder(folder, removed_pcs)
    encode, pre = stored.encode, stored.preprocess

    @jax.jit
    def encode_fn(params, images):
        return encode(params, pre(jnp.asarray(images, jnp.float32)))

    return encode_fn, stored.params
