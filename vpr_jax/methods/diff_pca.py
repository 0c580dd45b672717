"""diff_pca: supervised change removal (Lowry & Milford): the first k principal directions
of the aligned training places' season differences removed from every image, for every k of
``removed_pcs`` from one fit (the suffix ``[k:]`` of ``diff_pca.suffix_descriptors``)."""

from __future__ import annotations

import dataclasses

import numpy as np
from jaxtyping import Array, Float

from vpr_jax.encoders import diff_pca, pca
from vpr_jax.errors import UserError
from vpr_jax.methods.contract import Method, Report, TrainingSet
from vpr_jax.methods.pca import beyond_rank


@dataclasses.dataclass(frozen=True)
class Settings:
    """``diff_pca.*``."""

    solver: str = "auto"  # auto | covariance | gram | subspace: PCA of the differences

    def __post_init__(self):
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


def _changes(training: TrainingSet) -> int:
    """Directions the season differences of the aligned places can span."""
    return min(training.n_images // 2, training.n_pixels)


def most_removed(settings: Settings, training: TrainingSet) -> tuple[int, str]:
    n = training.n_images // 2
    most = min(training.pca_limit - 1, _changes(training))
    return most, f" and {n} aligned places span at most that many changes"


def check(settings: Settings, training: TrainingSet, log) -> Settings:
    most = _changes(training)
    if max(training.removed_pcs) > most:
        raise UserError(
            f"removed_pcs up to {max(training.removed_pcs)} for diff_pca, but the season "
            f"differences of {training.n_images // 2} aligned training places span at most "
            f"{most} directions: use counts up to {most}, or leave diff_pca out of methods"
        )
    return settings


def _report(state, settings: dict) -> Report:
    k = settings["removed_pcs"]
    components = np.asarray(state.components)  # host slices: a count compiles nothing
    if k > len(components):
        raise beyond_rank(k, len(components), "directions of change")
    return Report(basis=components[:k] if k else None, basis_name="removed_changes")


method = Method(
    fit=fit,
    encode=encode,
    settings=Settings,
    sweeps=("removed_pcs",),
    serves=("removed_pcs",),
    suffix="removed_pcs",
    needs_alignment=True,
    uses=("mesh",),
    random=False,
    check=check,
    most_removed=most_removed,
    report=_report,
)
