"""cae: the convolutional auto-encoder; its code is the descriptor. Trained as
``vpr_jax.methods.autoencoder`` describes, once per objective.

``cae.model`` names an architecture (``MODELS``); ``cae.channels``, ``cae.kernel_sizes``,
``cae.code_channels`` and ``cae.space_to_depth`` override its parts.
"""

from __future__ import annotations

import dataclasses

from vpr_jax.encoders import autoencoders as ae
from vpr_jax.errors import UserError
from vpr_jax.methods import autoencoder, training
from vpr_jax.shapes import IMAGE_SHAPE

# fast: 2x2 pixel blocks to channels (no convolution at full resolution), two 3x3 levels of
# 24 and 48 channels, a 4x8x32 = 1,024-value code. calc: the CAE sized like CALC's encoder
# (5x5x64, 4x4x128, a 8x16x8 = 1,024-value code), far slower to train on a CPU
# (docs/speed.md, "Auto-encoders").
MODELS = {
    "fast": {
        "channels": (24, 48),
        "kernel_sizes": (3, 3),
        "code_channels": 32,
        "space_to_depth": 2,
    },
    "calc": {
        "channels": (64, 128),
        "kernel_sizes": (5, 4),
        "code_channels": 8,
        "space_to_depth": 1,
    },
}


@dataclasses.dataclass(frozen=True)
class Settings(autoencoder.TrainingSettings):
    """``cae.*`` (and its training settings, ``train.*``'s where not given): optionally
    f x f pixel blocks to channels, then per level a conv (ReLU) + 2x2 max-pool, a 3x3 conv
    to the code; a mirrored decoder."""

    model: str = "fast"  # fast | calc: a named architecture (MODELS); the keys below override
    channels: tuple[int, ...] | None = None  # widths, one per level
    kernel_sizes: tuple[int, ...] | None = None  # one per level
    code_channels: int | None = None  # code = (32 / 2^levels / f) x (64 / ...) x this values
    space_to_depth: int | None = None  # f: f x f pixel blocks become channels first (1: none)
    objective: tuple[str, ...] = ("reconstruct", "cross_season")  # as fae.objective
    # as fae.input; pixels and residual_pixels: the image as it is (no centring)
    input: str = "standardised"
    residual_pcs: int = 10  # as fae.residual_pcs
    # random: the convolutions alone, drawn; pca, whitened_pca or lda: a linear branch of
    # linear_units units beside them, started as fae.init starts the FAE, and the code
    # convolution scaled down (ae.CONV_START_SCALE), so the CAE starts at the linear
    # solution's score and its convolutions add what validation recall rewards.
    init: str = "random"
    linear_units: int = 512  # the linear branch's units (code values), with an init

    def __post_init__(self):
        autoencoder.check_common("cae", self)
        if self.linear_units < 2:
            raise UserError(f"cae.linear_units={self.linear_units} must be >= 2")
        if self.model not in MODELS:
            raise UserError(f"cae.model={self.model} is unknown: use {' or '.join(MODELS)}")
        a = architecture(self)
        if not len(a["channels"]) == len(a["kernel_sizes"]) >= 1:
            raise UserError(
                f"cae.channels={list(a['channels'])} and cae.kernel_sizes="
                f"{list(a['kernel_sizes'])} need one entry per level, at least one level"
            )
        if min(*a["channels"], *a["kernel_sizes"], a["code_channels"]) < 1:
            raise UserError("cae.channels, cae.kernel_sizes and cae.code_channels must be >= 1")
        h, w = IMAGE_SHAPE
        f = a["space_to_depth"]
        down = 2 ** len(a["channels"]) * f
        if f < 1 or h % down or w % down:
            raise UserError(
                f"cae: {len(a['channels'])} levels after {f}x{f} blocks do not tile {h}x{w} "
                "images: use fewer levels or cae.space_to_depth=1"
            )


def architecture(settings) -> dict:
    """The named model's parts with the ones set overriding them."""
    return {
        key: default if getattr(settings, key) is None else getattr(settings, key)
        for key, default in MODELS[settings.model].items()
    }


def _model(train, aligned, s: dict) -> autoencoder.Model:
    """The named architecture with the parts set overriding it; with an ``init``, a linear
    branch started there."""
    a = architecture(Settings(**{**s, "objective": (s["objective"],)}))
    return autoencoder.Model(
        spec=lambda removed: ae.CAESpec(
            channels=tuple(a["channels"]),
            kernel_sizes=tuple(a["kernel_sizes"]),
            code_channels=a["code_channels"],
            space_to_depth=a["space_to_depth"],
            standardise=training.is_standardised(s["input"]),
            removed=removed,
            linear=s["linear_units"] if s["init"] != "random" else 0,
        ),
        start=autoencoder.start_of(s["init"], train, aligned),
    )


def _report(state, settings: dict):
    """The training record; a linear start sets the linear branch's units."""
    return autoencoder.report(state, settings, units=settings["linear_units"])


method = autoencoder.autoencoder_method("cae", _model, Settings, _report)
