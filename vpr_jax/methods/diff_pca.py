"""diff_pca: supervised change removal (Lowry & Milford): the first k principal directions
of the aligned training places' season differences removed from every image, for every k of
``removed_pcs`` from one fit (the suffix ``[k:]`` of ``diff_pca.suffix_descriptors``)."""

from __future__ import annotations

import dataclasses

import numpy as np
from jaxtyping import Array, Float

from vpr_jax.encoders import diff_pca, pca
from vpr_jax.errors import UserError
from vpr_jax.methods.contract import SUFFIX, Method, Report, TrainingSet
from vpr_jax.methods.inputs import check_input, with_input
from vpr_jax.methods.pca import beyond_rank, removed_count_fits
from vpr_jax.methods.rectify import rectifiable


@dataclasses.dataclass(frozen=True)
class Settings:
    """``diff_pca.*``."""

    solver: str = "auto"  # auto | covariance | gram | subspace: PCA of the differences
    removed_pcs: int = 0  # leading change directions removed (the sweep's removed_pcs: one fit)
    rectify: bool = False  # [relu(z), relu(-z)] (vpr_jax.methods.rectify): a fit per value
    # what the method sees (vpr_jax.methods.inputs): pixels, standardised, patchnorm,
    # gradients, or parts joined by + (a list: an axis)
    input: str = "pixels"

    def __post_init__(self):
        check_input(self, "diff_pca")
        if self.solver not in pca.SOLVERS:
            raise UserError(
                f"diff_pca.solver={self.solver} is unknown: use {', '.join(pca.SOLVERS)}"
            )


def fit(train, aligned, key, *, mesh, solver: str) -> diff_pca.DiffPCAState:
    """Every change direction: shapes that do not depend on the removed counts."""
    return diff_pca.fit_diff_pca(*aligned, solver=solver, mesh=mesh)


def encode(state, images: Float[Array, "n h w"], removed_pcs: int = 0) -> Float[Array, "n e"]:
    """The images with their first ``removed_pcs`` directions of change removed."""
    return diff_pca.suffix_descriptors(state, images)[:, removed_pcs:]


def check(settings: Settings, training: TrainingSet, log) -> Settings | None:
    """Counts the training images serve (below their PCA's components) and the season
    differences of the aligned places span (up to one per place)."""
    k, limit, places = settings.removed_pcs, training.pca_limit, training.n_images // 2
    changes = min(places, training.n_pixels)
    why = f"PCA of {training.n_images} training images has {limit} components"
    if not removed_count_fits("diff_pca", k, limit, why, training, log):
        return None
    why = f"the season differences of {places} aligned training places span {changes} directions"
    if not removed_count_fits("diff_pca", k, changes + 1, why, training, log):
        return None
    return settings


def _report(state, settings: dict) -> Report:
    k = settings["removed_pcs"]
    components = np.asarray(state.components)  # host slices: a count compiles nothing
    if k > len(components):
        raise beyond_rank(k, len(components), "directions of change")
    return Report(basis=components[:k] if k else None, basis_name="removed_changes")


method = rectifiable(
    with_input(
        Method(
            fit=fit,
            encode=encode,
            settings=Settings,
            axes={"removed_pcs": SUFFIX},  # one fit and one encoding serve every count
            needs=("aligned", "mesh"),
            random=False,
            check=check,
            report=_report,
        )
    )
)
