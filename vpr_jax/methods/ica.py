"""ica: symmetric FastICA (the paper's headline method) on the images whitened with the pair's
shared PCA fit after removing its first k components, a fit per k of ``removed_pcs``."""

from __future__ import annotations

import dataclasses

import numpy as np

from vpr_jax.encoders import ica
from vpr_jax.errors import UserError
from vpr_jax.methods.contract import Method, NotScored, PCAFit, Report, TrainingSet
from vpr_jax.methods.inputs import check_input, with_input
from vpr_jax.methods.pca import removed_count_fits
from vpr_jax.methods.rectify import rectifiable


@dataclasses.dataclass(frozen=True)
class Settings:
    """``ica.*``: scikit-learn's names."""

    n_components: int | str = 128  # independent components; "all": every one the data allow
    fun: str = "logcosh"  # logcosh | exp | cube: the contrast G
    alpha: float = 1.0  # logcosh only: G(u) = log cosh(alpha u) / alpha, alpha in [1, 2]
    max_iter: int = 200  # fixed-point updates at most
    tol: float = 1e-4  # stop when max |abs(diag(W_new W^T)) - 1| < tol
    n_init: int = 1  # random initialisations run at once; the best negentropy is kept
    removed_pcs: int = 0  # leading components removed before whitening (the sweep's
    # removed_pcs: a fit per count)
    rectify: bool = False  # [relu(z), relu(-z)] (vpr_jax.methods.rectify): a fit per value
    # what the method sees (vpr_jax.methods.inputs): pixels, standardised, patchnorm,
    # gradients, or parts joined by + (a list: an axis)
    input: str = "pixels"

    def __post_init__(self):
        check_input(self, "ica")
        n = self.n_components
        checks = (
            (
                n == "all" or (isinstance(n, int) and n >= 1),
                f"ica.n_components={n} is not a count: use a number >= 1 or all",
            ),
            (self.fun in ica.FUNS, f"ica.fun={self.fun} is unknown: use {', '.join(ica.FUNS)}"),
            (
                self.fun != "logcosh" or 1.0 <= self.alpha <= 2.0,
                f"ica.alpha={self.alpha} must lie in [1, 2]",
            ),
            (self.max_iter >= 1, f"ica.max_iter={self.max_iter} must be >= 1"),
            (self.tol > 0, f"ica.tol={self.tol} must be > 0"),
            (self.n_init >= 1, f"ica.n_init={self.n_init} must be >= 1"),
        )
        for ok, message in checks:
            if not ok:
                raise UserError(message)


def fit(train, aligned, key, *, pca_fit: PCAFit, removed_pcs: int, **settings) -> ica.ICAState:
    """FastICA of the images less ``removed_pcs`` components, whitened by the shared fit."""
    rank = ica.data_rank(pca_fit.state, len(train))
    try:
        ica.resolve_n_components(settings["n_components"], removed_pcs, rank)
    except ValueError as err:  # a numerical rank below the plan's limit
        raise NotScored(str(err)) from None
    return ica.fit_ica(train, key, removed_pcs=removed_pcs, pca_state=pca_fit.state, **settings)


def encode(state: ica.ICAState, images):
    return ica.encode(state, images)


def _served_counts(settings: Settings, training: TrainingSet) -> tuple[int, str]:
    """(the count a removed count must stay below, why): the training images' components,
    less those a named ``n_components`` takes where the removed counts are defaults (named
    counts and a named size that do not fit are refused below, never changed)."""
    n, limit = settings.n_components, training.pca_limit
    named = {"n_components", "removed_pcs"} <= training.given
    if n == "all" or "n_components" not in training.given or named:
        return limit, f"PCA of {training.n_images} training images has {limit} components"
    return limit - n + 1, (
        f"PCA of {training.n_images} training images has {limit} components, {n} of them "
        "for ICA (ica.n_components)"
    )


def check(settings: Settings, training: TrainingSet, log) -> Settings | None:
    """Removed counts beyond the training set are left out (named ones refused); the
    default count of components is capped to what the largest removed count leaves (one
    note); a count named on the command line that does not fit is refused; the shared fit
    must hold what the whitening reaches."""
    n, limit, k = settings.n_components, training.pca_limit, settings.removed_pcs
    most, why = _served_counts(settings, training)
    if not removed_count_fits("ica", k, most, why, training, log):
        return None
    counts = [c for c in training.swept.get("removed_pcs", (k,)) if c < most]
    top = max(counts)
    if n != "all" and "n_components" not in training.given and n > limit - top >= 1:
        log(
            f"note: ica.n_components={n} capped to {limit - top}: PCA of "
            f"{training.n_images} training images has {limit} components and removed_pcs "
            f"goes up to {top} (set ica.n_components to choose)"
        )
        settings = dataclasses.replace(settings, n_components=limit - top)
        n = settings.n_components
    if n != "all" and top + n > limit:
        raise UserError(
            f"ica.n_components={n} with removed_pcs up to {top} needs {top + n} components "
            f"but PCA of {training.n_images} training images has {limit}: use "
            f"ica.n_components <= {limit - top}, ica.n_components=all, or smaller removed_pcs"
        )
    training.check_pca_components("ica", limit if n == "all" else k + n)
    return settings


def _report(state: ica.ICAState, settings: dict) -> Report:
    converged = bool(state.converged)
    warning = None
    if not converged:
        warning = (
            f"ICA ({state.unmixing.shape[0]} components, removed_pcs="
            f"{settings['removed_pcs']}) did not converge: stopped at ica.max_iter="
            f"{settings['max_iter']} above ica.tol={settings['tol']}; raise ica.max_iter or "
            "ica.tol, or lower ica.n_components"
        )
    return Report(
        n_iter=int(state.n_iter),
        converged=converged,
        warning=warning,
        basis=np.asarray(ica.mixing(state)).T,
        basis_name="independent_components",
    )


method = rectifiable(
    with_input(
        Method(
            fit=fit,
            encode=encode,
            settings=Settings,
            needs=("pca_fit",),
            random=True,
            check=check,
            report=_report,
        )
    )
)
