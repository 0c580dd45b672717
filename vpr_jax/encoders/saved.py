"""The folders a sweep saves every fitted method in, under ``train.checkpoint_dir``: written
and read here; ``vpr_jax.methods.loading.load_encoder`` turns one back into ``(encode_fn,
params)``.

A folder holds the fitted state (``state/``, ``fitted_state``), ``fit.json`` (what was
fitted: the method's ``module:object``, its settings, the values one fit serves such as
pca's removed counts; written when the fit ends), ``encoder.json`` (the description a user
reads, written with the pair's report: the served value chosen on the validation places,
its validation recall@1, the preprocessing) and, for a trained model, its training
checkpoints. ``encode_fn(params, images)`` is pure and jitted and includes every step after
reading: images float32 ``(n, 32, 64)`` in [0, 1] (grey, resized to 64x32 with OpenCV's
area interpolation, divided by 255), then patch normalisation when the sweep used it
(float32 here, float64 in the sweep: the descriptors agree to about 1e-5 relative).
"""

from __future__ import annotations

import importlib.metadata
import json
from pathlib import Path
from typing import Any

from vpr_jax.encoders.fitted_state import save_state
from vpr_jax.errors import UserError
from vpr_jax.files import atomic_write_text

FORMAT = 2  # of encoder.json and fit.json; another is refused
ENCODER_JSON, FIT_JSON, STATE = "encoder.json", "fit.json", "state"


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


def save_fitted(folder: Path, state: Any, description: dict) -> None:
    """Save a fitted state (``folder/state``, whole) and then its ``fit.json``
    (``description``: the method's ``module:object`` as ``method``, what it serves)."""
    save_state(Path(folder) / STATE, state)
    text = json.dumps({"format": FORMAT, **description}, indent=1)
    atomic_write_text(Path(folder) / FIT_JSON, text)


def describe_encoder(folder: Path, selection: dict) -> dict:
    """Write ``encoder.json``: the folder's ``fit.json`` and ``selection`` (the chosen count,
    its validation and test recall@1, its run). Returns it."""
    description = {**read_description(folder, FIT_JSON), **selection}
    atomic_write_text(Path(folder) / ENCODER_JSON, json.dumps(description, indent=1))
    return description
