"""lda: within-place whitening inside the leading principal components of the pair's shared
PCA fit: a place's two seasons vary equally in every direction (a learnt Mahalanobis metric,
``vpr_jax.encoders.lda``)."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax.numpy as jnp

from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import lda
from vpr_jax.errors import UserError
from vpr_jax.methods.contract import Method, PCAFit, Report, TrainingSet
from vpr_jax.methods.inputs import check_input, with_input
from vpr_jax.methods.rectify import rectifiable


@dataclasses.dataclass(frozen=True)
class Settings:
    """``lda.*``."""

    n_components: int = 200  # leading principal components of the pair's PCA fit whitened in
    shrinkage: float = 0.1  # towards trace/m x identity: 0 plain whitening, 1 PCA coordinates
    rectify: bool = False  # [relu(z), relu(-z)] (vpr_jax.methods.rectify): a fit per value
    # what the method sees (vpr_jax.methods.inputs): pixels, standardised, patchnorm,
    # gradients, or parts joined by + (a list: an axis); whitened inside the pair's shared
    # PCA fit of that input
    input: str = "pixels"

    def __post_init__(self):
        check_input(self, "lda")
        if self.n_components < 1:
            raise UserError(f"lda.n_components={self.n_components} must be >= 1")
        if not 0 <= self.shrinkage <= 1:
            raise UserError(
                f"lda.shrinkage={self.shrinkage} is not in [0, 1]: use e.g. 0.1 (0: plain "
                "whitening)"
            )


class Standardised(NamedTuple):
    """An lda fit of standardised images, whitened in a PCA fit of its own, as the setting
    ``lda.standardise`` made them before ``lda.input=standardised`` replaced it: saved
    folders of it still encode."""

    state: lda.LDAState


def fit(train, aligned, key, *, pca_fit: PCAFit, n_components: int, shrinkage: float):
    """In all the components the training images hold, when they hold fewer (the shared
    fit keeps only its numerical rank)."""
    m = min(n_components, len(pca_fit.state.components))
    return lda.fit_lda(pca_fit.state, *aligned, m, shrinkage)


def encode(state, images):
    if isinstance(state, Standardised):
        return lda.encode(state.state, ae.standardise(jnp.asarray(images, jnp.float32)))
    return lda.encode(state, images)


def check(settings: Settings, training: TrainingSet, log) -> Settings:
    """With fewer components than asked, lda whitens in all (a note); the shared fit must
    hold what it whitens in."""
    limit = training.pca_limit
    if settings.n_components > limit:
        log(
            f"note: lda.n_components={settings.n_components} exceeds the {limit} principal "
            f"components of {training.n_images} training images: lda whitens in all {limit}"
        )
    training.check_pca_components("lda", min(settings.n_components, limit))
    return settings


def _report(state, settings: dict) -> Report:
    state = state.state if isinstance(state, Standardised) else state
    held, asked = len(state.transform), settings["n_components"]
    warning = None
    if held < asked:
        warning = (
            f"lda whitens in the {held} principal components the training images hold (their "
            f"numerical rank), not lda.n_components={asked}"
        )
    return Report(basis=state.transform, basis_name="invariant_directions", warning=warning)


method = rectifiable(
    with_input(
        Method(
            fit=fit,
            encode=encode,
            settings=Settings,
            needs=("aligned", "pca_fit"),
            random=False,
            check=check,
            report=_report,
        )
    )
)
