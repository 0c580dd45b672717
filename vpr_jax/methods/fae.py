"""fae: the fundamental auto-encoder, one hidden layer (2,048 pixels -> ``hidden`` ReLU units
-> 2,048); the hidden layer is the descriptor. Trained as ``vpr_jax.methods.autoencoder``
describes, once per objective."""

from __future__ import annotations

import dataclasses

import numpy as np

from vpr_jax.encoders import autoencoders as ae
from vpr_jax.errors import UserError
from vpr_jax.methods import autoencoder, training
from vpr_jax.methods.contract import Report


@dataclasses.dataclass(frozen=True)
class Settings(autoencoder.TrainingSettings):
    """``fae.*``: its own and its training settings (``train.*``'s where not given)."""

    hidden: int = 256  # code length: the place descriptor
    # One cell per objective: reconstruct (the paper's), cross_season and/or contrastive
    # (see vpr_jax.encoders.objectives); one value or a list.
    objective: tuple[str, ...] = ("reconstruct", "cross_season")
    # standardised: each image to zero mean and std 1/4 (a season's brightness and contrast
    # gone); pixels: each image centred at input_centre; residual: the images less the
    # pair's leading residual_pcs principal components (the code cannot be spent on the
    # condition PCA change removal throws away), then standardised; residual_pixels: the
    # residual centred (training.INPUTS)
    input: str = "standardised"
    residual_pcs: int = 10  # components a residual input removes (a list: an axis)
    # random: drawn weights; pca: the linear start, the hidden layer at the PCA solution of
    # its own inputs for hidden // 2 components, each unit beside its negative
    # (vpr_jax.encoders.autoencoders.pca_start): training keeps only what beats it;
    # whitened_pca: the same with every component scaled to unit variance; lda: within-place
    # whitening of its inputs in hidden // 2 components (the lda method's descriptor; needs
    # aligned training places).
    init: str = "random"
    # Subtracted from every pixel before the hidden layer (input=pixels or residual_pixels);
    # 0 is the paper's layer, on which most ReLU units die (vpr_jax.encoders.autoencoders.FAE)
    input_centre: float = 0.5
    # all: every weight trains; scale: the hidden layer stays at its start (init) and only
    # a scale and a shift per unit train on top of it: 2 x hidden numbers that cannot
    # memorise the places (a list: an axis, validation chooses)
    update: str = "all"

    def __post_init__(self):
        autoencoder.check_common("fae", self)
        checks = (
            (self.hidden >= 1, f"fae.hidden={self.hidden} must be >= 1"),
            (
                self.update in ae.UPDATES,
                f"fae.update={self.update} is unknown: use {' or '.join(ae.UPDATES)}",
            ),
            (
                0 <= self.input_centre <= 1,
                f"fae.input_centre={self.input_centre} is not a grey level in [0, 1]: use "
                "0.5 (mid-grey) or 0 (the paper's layer)",
            ),
        )
        for ok, message in checks:
            if not ok:
                raise UserError(message)


def _model(train, aligned, s: dict) -> autoencoder.Model:
    """One hidden layer of ``hidden`` units; the linear start, where asked, from ``train``
    (``lda``: its aligned places)."""
    return autoencoder.Model(
        spec=lambda removed: ae.FAESpec(
            hidden=s["hidden"],
            centre=s["input_centre"],
            standardise=training.is_standardised(s["input"]),
            removed=removed,
            update=s["update"],
        ),
        start=autoencoder.start_of(s["init"], train, aligned),
    )


def _report(state: ae.ModelState, settings: dict) -> Report:
    """What each hidden unit looks for: its weights as an image."""
    kernel = np.asarray(state.params["encoder"]["kernel"]).T
    return autoencoder.report(state, settings, kernel, units=settings["hidden"])


method = autoencoder.autoencoder_method("fae", _model, Settings, _report)
