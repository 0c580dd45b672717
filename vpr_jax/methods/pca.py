"""pca: PCA change removal (Lowry & Milford): the first k principal components of both
seasons' training images removed, for every k of ``removed_pcs`` from one fit.

Its fit is the pair's shared PCA fit (``shared_fit``), which every method that ``uses``
``pca_fit`` receives too (ica whitens with it, lda whitens inside it, a residual-input
auto-encoder removes its leading components). The descriptor of count k is the suffix
``[k:]`` of ``pca.suffix_descriptors``, coefficients then residual (``vpr_jax.encoders.pca``),
so one encoding and one matching pass score every count; ``pca.output=pixels`` encodes
each count in pixel space instead, as the seed did (the same similarities, slower).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
from jaxtyping import Array, Float

from vpr_jax.encoders import pca
from vpr_jax.errors import UserError
from vpr_jax.methods.contract import Method, PCAFit, Report

OUTPUTS = ("coefficients", "pixels")


@dataclasses.dataclass(frozen=True)
class Settings:
    """``pca.*``: how the pair's PCA fit is solved, and the descriptor's form."""

    solver: str = "auto"  # auto | covariance | gram | subspace (vpr_jax.encoders.pca)
    output: str = "coefficients"  # coefficients | pixels (the seed's back-projection)

    def __post_init__(self):
        if self.solver not in pca.SOLVERS:
            raise UserError(f"pca.solver={self.solver} is unknown: use {', '.join(pca.SOLVERS)}")
        if self.output not in OUTPUTS:
            raise UserError(f"pca.output={self.output} is unknown: use {' or '.join(OUTPUTS)}")


class InPixels(NamedTuple):
    """A PCA fit that describes images in pixel space (``pca.output=pixels``)."""

    fit: pca.PCAState


def shared_fit(train, n_components: int, settings: Settings, mesh, seed: int) -> pca.PCAState:
    """The pair's PCA fit: its leading ``n_components`` (what its users need)."""
    return pca.fit_pca(train, n_components, solver=settings.solver, mesh=mesh, seed=seed)


def fit(train, aligned, key, *, pca_fit: PCAFit, solver: str, output: str):
    """The pair's shared fit is PCA's own."""
    return InPixels(pca_fit.state) if output == "pixels" else pca_fit.state


def encode(state, images: Float[Array, "n h w"], removed_pcs: int = 0) -> Float[Array, "n e"]:
    """The images with their first ``removed_pcs`` principal components removed."""
    if isinstance(state, InPixels):
        return pca.encode(state.fit, images, removed_pcs, "pixels")
    return pca.suffix_descriptors(state, images)[:, removed_pcs:]


def _report(state, settings: dict) -> Report:
    k = settings["removed_pcs"]
    components = np.asarray((state.fit if isinstance(state, InPixels) else state).components)
    return Report(basis=components[:k] if k else None, basis_name="removed_components")


method = Method(
    fit=fit,
    encode=encode,
    settings=Settings,
    sweeps=("removed_pcs",),
    serves=("removed_pcs",),  # one fit, a suffix per count
    suffix=lambda s: "" if s.output == "pixels" else "removed_pcs",
    uses=("pca_fit",),
    random=False,
    pca_components=lambda s, training: max(training.removed_pcs),
    report=_report,
    shared_fit=shared_fit,
)
