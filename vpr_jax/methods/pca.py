"""pca: PCA change removal (Lowry & Milford): the first k principal components of both
seasons' training images removed, for every k of ``removed_pcs`` from one fit.

Its fit is the pair's shared PCA fit (``shared_fit``, made by the runner with pca's
settings, ``experiments.fitting``), which every method that ``needs`` ``pca_fit`` receives
too (ica whitens with it, lda whitens inside it, a residual-input auto-encoder removes its
leading components). The shared fit
solves every component exactly (``covariance`` or ``gram``), or, where that is too large
(``FULL_SOLVE_LIMIT``) or ``pca.solver=subspace`` asks, a fixed ``pca.subspace_components``;
every user gets that whole fit and takes the leading components it needs, so no method's
numbers depend on which others share the sweep. With a list for a ``pca.*`` setting, pca's
cells get a shared fit per value; the methods that need it, the first value's.

The descriptor of count k is the suffix ``[k:]`` of ``pca.suffix_descriptors`` (the
coefficients on every component of the fit, then the residual; ``vpr_jax.encoders.pca``),
so one encoding and one matching pass score every count; ``pca.output=pixels`` encodes
each count in pixel space instead, as the paper did (the same similarities, slower).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from vpr_jax.encoders import pca
from vpr_jax.errors import UserError
from vpr_jax.methods.contract import (
    SERVED,
    SUFFIX,
    Method,
    NotScored,
    PCAFit,
    Report,
    TrainingSet,
)
from vpr_jax.methods.inputs import check_input, with_input
from vpr_jax.methods.rectify import rectifiable

OUTPUTS = ("coefficients", "pixels")


@dataclasses.dataclass(frozen=True)
class Settings:
    """``pca.*``: how the pair's PCA fit is solved, and the descriptor's form."""

    solver: str = "auto"  # auto | covariance | gram | subspace (vpr_jax.encoders.pca)
    output: str = "coefficients"  # coefficients | pixels (the paper's back-projection)
    subspace_components: int = 512  # what the subspace solver fits, whichever methods use it
    removed_pcs: int = 0  # leading components removed (the sweep's removed_pcs: one fit)
    # 0: the change-removal descriptor; c > 0: after the removed ones, c components each
    # scaled to unit variance, nothing else (PCA whitening: what ica rotates)
    whiten: int = 0
    rectify: bool = False  # [relu(z), relu(-z)] (vpr_jax.methods.rectify): a fit per value
    # what the method sees (vpr_jax.methods.inputs): pixels, standardised, patchnorm,
    # gradients, or parts joined by + (a list: an axis)
    input: str = "pixels"

    def __post_init__(self):
        check_input(self, "pca")
        if self.whiten < 0:
            raise UserError(
                f"pca.whiten={self.whiten} is negative: use 0 (no whitening) or a count"
            )
        if self.whiten and self.output == "pixels":
            raise UserError(
                "pca.whiten describes coefficients: use it with pca.output=coefficients"
            )
        if self.subspace_components < 1:
            raise UserError(
                f"pca.subspace_components={self.subspace_components} must be at least 1"
            )
        if self.solver not in pca.SOLVERS:
            raise UserError(f"pca.solver={self.solver} is unknown: use {', '.join(pca.SOLVERS)}")
        if self.output not in OUTPUTS:
            raise UserError(f"pca.output={self.output} is unknown: use {' or '.join(OUTPUTS)}")


class InPixels(NamedTuple):
    """A PCA fit that describes images in pixel space (``pca.output=pixels``)."""

    fit: pca.PCAState


class Whitened(NamedTuple):
    """A PCA fit that describes images by the ``pca.whiten`` components after the removed
    ones, each scaled to unit variance."""

    fit: pca.PCAState
    kept: jax.Array  # (whiten,) int: 0, 1, ...: the descriptor's width, as a shape


# Above this many components (min(N - 1, D)), auto solves only the leading
# pca.subspace_components: an exact solve's eigh grows as the cube (4,096: 6.7 s measured
# on the 2-core box, 2026-12-04; 8,192 would take about a minute).
FULL_SOLVE_LIMIT = 4096


def _solver(settings: Settings, n_images: int, n_pixels: int) -> str:
    """The solver of the shared fit: ``pca.solver``; ``auto``: an exact one up to
    ``FULL_SOLVE_LIMIT`` components, else ``subspace``."""
    if settings.solver != "auto":
        return settings.solver
    if pca.rank_limit(n_images, n_pixels) > FULL_SOLVE_LIMIT:
        return "subspace"
    return pca.choose_solver(n_images, n_pixels)


def shared_components(settings: Settings, n_images: int, n_pixels: int) -> int:
    """The components the pair's fit holds: every one, or ``pca.subspace_components``."""
    limit = pca.rank_limit(n_images, n_pixels)
    if _solver(settings, n_images, n_pixels) == "subspace":
        return min(settings.subspace_components, limit)
    return limit


def shared_fit(train, n_components: int, settings: Settings, mesh, seed: int) -> pca.PCAState:
    """The pair's PCA fit of ``n_components`` (``shared_components``), or fewer where the
    training images' numerical rank is lower."""
    n_pixels = int(np.prod(np.shape(train)[1:]))
    solver = _solver(settings, len(train), n_pixels)
    try:
        return pca.fit_pca(train, n_components, solver=solver, mesh=mesh, seed=seed)
    except pca.NotOrthonormal as err:
        other = "covariance" if solver != "covariance" else "gram"
        raise UserError(f"{err} on {len(train)} training images: set pca.solver={other}") from None


def fit(train, aligned, key, *, pca_fit: PCAFit, output: str, whiten: int, **shared_settings):
    """The pair's shared fit is PCA's own (``shared_settings`` shaped it)."""
    if whiten:
        return Whitened(pca_fit.state, jnp.arange(whiten, dtype=jnp.int32))
    return InPixels(pca_fit.state) if output == "pixels" else pca_fit.state


def encode(state, images: Float[Array, "n h w"], removed_pcs: int = 0) -> Float[Array, "n e"]:
    """The images with their first ``removed_pcs`` principal components removed (whitened:
    the next ``pca.whiten`` of them at unit variance, nothing else: a count whose window
    goes beyond the fit's components is not scored, ``_report``)."""
    if isinstance(state, InPixels):
        return pca.encode(state.fit, images, removed_pcs, "pixels")
    if isinstance(state, Whitened):
        coefficients = pca.project(state.fit, images) * jax.lax.rsqrt(state.fit.explained_variance)
        width = state.kept.shape[0]
        return jax.lax.dynamic_slice_in_dim(coefficients, removed_pcs, width, axis=1)
    return pca.suffix_descriptors(state, images)[:, removed_pcs:]


def beyond_rank(k: int, held: int, what: str) -> NotScored:
    """Why a removed count beyond a fit's components is not scored."""
    return NotScored(
        f"removed_pcs={k} is beyond the {held} {what} the training images hold (their "
        f"numerical rank in float32); counts up to {held} are scored"
    )


def _report(state, settings: dict) -> Report:
    k = settings["removed_pcs"]
    fitted = state if isinstance(state, pca.PCAState) else state.fit
    components = np.asarray(fitted.components)
    if k + settings["whiten"] > len(components):  # not defined by these images
        raise beyond_rank(k + settings["whiten"], len(components), "principal components")
    return Report(basis=components[:k] if k else None, basis_name="removed_components")


def removed_count_fits(who: str, k: int, limit: int, why: str, training: TrainingSet, log) -> bool:
    """Whether ``who``'s removed count is below ``limit`` (``why`` says what sets it): a
    count the command line names is refused beyond it, a default or a preset's is left out
    with a note."""
    if k < limit:
        return True
    if "removed_pcs" in training.given:
        raise UserError(
            f"removed_pcs={list(training.swept.get('removed_pcs', (k,)))} is too large for "
            f"{who}: {why}, so use counts up to {limit - 1}"
        )
    log(f"note: {who} removed_pcs={k} left out: {why} (set removed_pcs to choose)")
    return False


def check(settings: Settings, training: TrainingSet, log) -> Settings | None:
    """Counts the training images serve, and no more than the shared fit holds."""
    k, limit = settings.removed_pcs, training.pca_limit
    why = f"PCA of {training.n_images} training images has {limit} components"
    if settings.whiten:
        why += f", {settings.whiten} of them whitened (pca.whiten)"
    # at least one component is left, or all ``whiten`` of them
    below = limit - max(settings.whiten - 1, 0)
    if not removed_count_fits("pca", k, below, why, training, log):
        return None
    own = shared_components(settings, training.n_images, training.n_pixels)  # its own fit
    training._replace(pca_components=own).check_pca_components("pca", max(1, k + settings.whiten))
    return settings


method = rectifiable(
    with_input(
        Method(
            fit=fit,
            encode=encode,
            settings=Settings,
            # one fit serves every removed count; in coefficients, one encoding too (a suffix each)
            axes=lambda s: {"removed_pcs": SERVED if s.output == "pixels" or s.whiten else SUFFIX},
            needs=("pca_fit",),
            random=False,
            check=check,
            report=_report,
        )
    )
)
