"""Every fitted method as an encoder you can take away: ``load_encoder(folder)`` gives
``(encode_fn, params)`` for raw, pca, diff_pca, ica, lda, the auto-encoders and a user's
``module:name`` method alike, from the folders a sweep saves (``vpr_jax.encoders.saved``).

``encode_fn(params, images)`` is pure and jitted and includes every step after reading:
images float32 ``(n, 32, 64)`` in [0, 1] (grey, resized to 64x32 with OpenCV's area
interpolation, divided by 255), then patch normalisation when the sweep used it (float32
here, float64 in the sweep: the descriptors agree to about 1e-5 relative).
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from vpr_jax.data.preprocess import patch_normalize_jax
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import checkpoints
from vpr_jax.encoders.fitted_state import restore_state
from vpr_jax.encoders.saved import ENCODER_JSON, FIT_JSON, STATE, read_description
from vpr_jax.errors import UserError
from vpr_jax.method_table import known_info, load_object
from vpr_jax.methods.state_types import state_types
from vpr_jax.precision import with_float32_products
from vpr_jax.untrusted import check_claim

Plugins = tuple[str, ...]  # users' methods named to be imported: module:name, or module


def _preprocess(description: dict) -> Callable[[jax.Array], jax.Array]:
    norm = description.get("preprocessing", {}).get("patchnorm")
    if not norm:
        return lambda images: images
    return functools.partial(patch_normalize_jax, size=norm["size"], rounded=norm["rounded"])


def _served(description: dict, asked: dict, folder: Path) -> dict:
    """The served values to encode with: the ones chosen on the validation places (or the
    first of each), each of ``asked`` where given (one the fit served)."""
    serves: dict[str, list] = {}
    for cell in description.get("cells", []):
        for name, value in cell.get("served", {}).items():
            serves.setdefault(name, []).append(value)
    chosen = {name: values[0] for name, values in serves.items()}
    chosen.update(description.get("chosen", {}))
    for name, value in asked.items():
        if value is None:
            continue
        if value not in serves.get(name, []):
            raise UserError(
                f"{folder} serves {name} {serves.get(name, [])}, not {value}: pass one of them "
                "(or None for the value chosen on the validation places)"
            )
        chosen[name] = value
    return chosen


def _checkpointed_model(folder: Path):
    """A model ``fit_autoencoder`` trained, as its checkpoint holds it: its encoder and its
    best parameters."""
    meta = checkpoints.read_meta(folder)
    try:
        spec = ae.spec_from_json(meta["spec"])
        image_shape = tuple(int(n) for n in meta["image_shape"])
        shapes = jax.eval_shape(lambda: ae.build(spec, jax.random.key(0), image_shape)[1])
    except (KeyError, TypeError, ValueError) as err:
        raise UserError(f"{folder} holds no auto-encoder this suite knows ({err})") from None
    claimed = sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(shapes))
    check_claim(claimed, f"{folder}'s model", "load only checkpoints a sweep or fit wrote")
    graphdef, like = ae.build(spec, jax.random.key(0), image_shape)
    model_encode = ae.make_encode(graphdef)
    return (lambda params, images: model_encode(params, images)), checkpoints.restore_model(
        folder, like
    )


MAX_NAMED = 20  # of the pair's folders, in the line refusing a folder that is not one


def _chosen_folder(folder: Path) -> Path:
    """``<pair>/<model>`` names a model whose fits have folders of their own
    (``ica_k005``, ``fae_hidden=1024``): the one chosen on the validation places. A name
    no fit of the pair has (``fae`` when only the contrastive objective was swept, whose
    folder is ``fae_contrastive``): UserError naming the pair's folders."""
    found = []
    for candidate in sorted(folder.parent.glob(f"{folder.name}*/{ENCODER_JSON}")):
        description = read_description(candidate.parent)
        if description.get("model") == folder.name and description.get("selected"):
            found.append((description.get("seed", 0), candidate.parent))
    if found:
        return min(found)[1]
    names = sorted(p.parent.name for p in folder.parent.glob(f"*/{ENCODER_JSON}"))
    if not names:
        raise UserError(
            f"{folder} holds no encoder and names none of the pair's: point at a folder a "
            "finished sweep saved (python -m experiments.encoders LOGDIR lists them)"
        )
    shown = ", ".join(names[:MAX_NAMED])
    if len(names) > MAX_NAMED:
        shown += f", ... ({len(names)} in all)"
    raise UserError(
        f"no fitted encoder in {folder}: this pair's folders are {shown}: pass one of them "
        "(python -m experiments.encoders LOGDIR lists them)"
    )


class StoredEncoder(NamedTuple):
    """A saved folder's parts: ``encode(params, images)`` on preprocessed images, as the
    sweep called it (not jitted as a whole: the method's own jitted steps, so its
    descriptors come back bit for bit), the fitted state and the preprocessing the sweep
    applied."""

    encode: Callable
    params: Any
    preprocess: Callable[[jax.Array], jax.Array]


def _method_of(description: dict, folder: Path, plugins: Plugins):
    """The method a folder's description names and the table of state types its state may
    be made of, found by exact name: a built-in, or a user's method ``plugins`` names.
    Anything else: UserError, nothing imported."""
    reference = description.get("method")
    info = known_info(reference, plugins)
    if info is None:
        raise UserError(
            f"{folder / ENCODER_JSON} names the method {reference!r}, not one of vpr_jax's: "
            "nothing imported; if it is a method of your own you trust, name it: "
            f"load_encoder(folder, plugins=[{reference!r}])"
        )
    try:
        method = load_object(info)
    except (ImportError, AttributeError):
        raise UserError(
            f"{folder} needs {reference}, which this vpr_jax lacks: update it"
        ) from None
    module = sys.modules[info.method.rsplit(":", 1)[0]]
    return method, state_types((module,) if info.plugin else ())


def stored_encoder(
    folder: str | Path, served: dict | None = None, plugins: Plugins = (), **asked
) -> StoredEncoder:
    """The parts ``load_encoder`` composes (see there for ``asked`` and ``plugins``);
    ``served``: the served values to encode with, as fit.json lists a cell's (the
    export's)."""
    folder = Path(folder).expanduser().resolve()
    if not (folder / FIT_JSON).exists() and checkpoints.has_checkpoint(folder):
        encode, params = _checkpointed_model(folder)  # a model trained without a sweep
        return StoredEncoder(encode, jax.tree.map(jnp.asarray, params), lambda images: images)
    if not folder.exists():
        folder = _chosen_folder(folder)
    description = read_description(folder)
    served = _served(description, asked, folder) if served is None else dict(served)
    plugins = (plugins,) if isinstance(plugins, str) else tuple(plugins)
    method, types = _method_of(description, folder, plugins)
    method_encode = method.encode
    return StoredEncoder(
        # as the sweep scored it: a user's products that state no precision at float32
        encode=with_float32_products(
            functools.partial(lambda fn, p, x: fn(p, x, **served), method_encode)
        ),
        params=jax.tree.map(jnp.asarray, restore_state(folder / STATE, types)),
        preprocess=_preprocess(description),
    )


def load_encoder(folder: str | Path, *, plugins: Plugins = (), **served):
    """``(encode_fn, params)`` of a folder a sweep saved: ``encode_fn(params, images) -> (n,
    d)`` is pure and jitted (use it in your own jitted code, vmap it, differentiate through
    it); ``params`` is the fitted state. ``served``: a value of a setting one fit served to
    encode with (``removed_pcs=5`` for pca and diff_pca, whose one fit serves every count
    the sweep ran); not given or None: the one chosen on the validation places.
    ``<pair>/<model>`` without a folder of that name (ica, whose fits are ``ica_k005``, ...,
    or a model with swept settings) gives the fit chosen on the validation places. A
    checkpoint folder of ``fit_autoencoder`` (no sweep around it) loads too.

    A folder is read as data only: its method and the classes of its state are found by
    exact name among vpr_jax's own; a method of your own (``methods=[...,module:name]`` in
    the sweep) is imported only when ``plugins`` names it, ``plugins=["module:name"]`` (or
    its module). Anything else a folder asks for is refused in one line, nothing run."""
    stored = stored_encoder(folder, plugins=plugins, **served)
    encode, pre = stored.encode, stored.preprocess

    @jax.jit
    def encode_fn(params, images):
        return encode(params, pre(jnp.asarray(images, jnp.float32)))

    return encode_fn, stored.params
