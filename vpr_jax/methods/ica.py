"""ica: symmetric FastICA (the seed's headline method) on the images whitened with the pair's
shared PCA fit after removing its first k components, a fit per k of ``removed_pcs``."""

from __future__ import annotations

import dataclasses

import numpy as np

from vpr_jax.encoders import ica
from vpr_jax.errors import UserError
from vpr_jax.methods.contract import Method, NotScored, PCAFit, Report, TrainingSet


@dataclasses.dataclass(frozen=True)
class Settings:
    """``ica.*``: scikit-learn's names."""

    n_components: int | str = 128  # independent components; "all": every one the data allow
    fun: str = "logcosh"  # logcosh | exp | cube: the contrast G
    alpha: float = 1.0  # logcosh only: G(u) = log cosh(alpha u) / alpha, alpha in [1, 2]
    max_iter: int = 200  # fixed-point updates at most
    tol: float = 1e-4  # stop when max |abs(diag(W_new W^T)) - 1| < tol
    n_init: int = 1  # random initialisations run at once; the best negentropy is kept

    def __post_init__(self):
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
    except ValueError as err:  # a rank below the plan's limit: repeated or constant frames
        raise NotScored(str(err)) from None
    return ica.fit_ica(train, key, removed_pcs=removed_pcs, pca_state=pca_fit.state, **settings)


def encode(state: ica.ICAState, images):
    return ica.encode(state, images)


def most_removed(settings: Settings, training: TrainingSet) -> tuple[int, str]:
    """A count of components named on the command line takes precedence over the default
    removed counts: those it leaves no room for are dropped."""
    n = settings.n_components
    if n == "all" or "n_components" not in training.given:
        return training.pca_limit - 1, ""
    return training.pca_limit - n, f", {n} of them for ICA (ica.n_components)"


def check(settings: Settings, training: TrainingSet, log) -> Settings:
    """The default count of components is capped to what the removed counts leave (one
    note); a count named on the command line that does not fit is refused."""
    n, limit, most = settings.n_components, training.pca_limit, max(training.removed_pcs)
    if n == "all":
        return settings
    if "n_components" not in training.given and n > limit - most >= 1:
        log(
            f"note: ica.n_components={n} capped to {limit - most}: PCA of "
            f"{training.n_images} training images has {limit} components and removed_pcs "
            f"goes up to {most} (set ica.n_components to choose)"
        )
        return dataclasses.replace(settings, n_components=limit - most)
    if most + n > limit:
        raise UserError(
            f"ica.n_components={n} with removed_pcs up to {most} needs {most + n} components "
            f"but PCA of {training.n_images} training images has {limit}: use "
            f"ica.n_components <= {limit - most}, ica.n_components=all, or smaller removed_pcs"
        )
    return settings


def pca_components(settings: Settings, training: TrainingSet) -> int:
    """The components its whitening reaches: every one for ``n_components=all``."""
    if settings.n_components == "all":
        return training.pca_limit
    return max(training.removed_pcs) + settings.n_components


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


method = Method(
    fit=fit,
    encode=encode,
    settings=Settings,
    sweeps=("removed_pcs",),
    uses=("pca_fit",),
    random=True,
    check=check,
    most_removed=most_removed,
    pca_components=pca_components,
    report=_report,
)
