"""The linear methods, each a function ``(pair, cfg, ctx) -> Descriptors`` as they finish:
raw pixels, PCA change removal, supervised change removal (diff_pca), within-place
whitening (lda) and ICA, around the pair's one shared PCA fit (``fit_pair_pca``)."""

from __future__ import annotations

from collections.abc import Iterator

import jax
import numpy as np
from jax.sharding import Mesh

from vpr_jax.config import SweepConfig
from vpr_jax.data.pair import PairData
from vpr_jax.encoders import diff_pca, ica, lda, pca
from vpr_jax.encoders.saved import encode_centred
from vpr_jax.errors import UserError
from vpr_jax.method_table import TRAINED, MethodInfo
from vpr_jax.methods.descriptors import (
    Descriptors,
    Fitted,
    MethodContext,
    PCAFit,
    as_images,
    describe,
    timed,
)

SAVED = "vpr_jax.encoders.saved"  # where a saved state's encode functions live


def uses_pca_fit(method: MethodInfo, cfg: SweepConfig) -> bool:
    """Whether a method's context needs the pair's PCA fit: the linear methods built on it,
    and an auto-encoder whose input is the PCA residual (``fae.input=residual``)."""
    return method.uses_pca_fit or (method.trained and getattr(cfg, method.name).input == "residual")


def _residual_inputs(cfg: SweepConfig) -> bool:
    return any(m in cfg.methods and getattr(cfg, m).input == "residual" for m in TRAINED)


def pca_components_needed(cfg: SweepConfig, n_samples: int, n_features: int) -> int | None:
    """How many leading components the pair's PCA fit must hold for the methods that use it:
    the largest removed count (pca, a residual-input auto-encoder), that plus
    ``ica.n_components`` (ica; None for "all", which needs every component),
    ``lda.n_components`` (lda); at least 1, at most the rank limit. From the configured
    counts, not the ones still to do, so a resumed sweep fits the same components."""
    limit = pca.rank_limit(n_samples, n_features)
    needed = [1]
    if "pca" in cfg.methods or _residual_inputs(cfg):
        needed.append(max(cfg.removed_pcs))
    if "ica" in cfg.methods:
        if cfg.ica.n_components in (None, "all"):
            return None
        needed.append(max(cfg.removed_pcs) + int(cfg.ica.n_components))
    if "lda" in cfg.methods:
        needed.append(cfg.lda.n_components)
    return min(max(needed), limit)


def fit_pair_pca(pair: PairData, cfg: SweepConfig, mesh: Mesh | None) -> PCAFit:
    """The PCA fit of the pair's training images and its seconds: the leading components the
    methods with ``uses_pca_fit`` (``vpr_jax.method_table``) need (``pca_components_needed``),
    by the solver ``pca.solver`` names. The runner fits it once per pair and passes it in
    their context."""
    n = pca_components_needed(cfg, len(pair.train), pair.train[0].size)
    state, seconds = timed(
        lambda x: pca.fit_pca(x, n, solver=cfg.pca.solver, mesh=mesh, seed=cfg.seed), pair.train
    )
    return PCAFit(state, seconds)


_centred = jax.jit(encode_centred)  # the saved encoder's own; compiled once per shape


def describe_raw(pair: PairData, cfg: SweepConfig, ctx: MethodContext) -> Iterator[Descriptors]:
    """Raw pixels, centred with the training mean; cosine does the L2 normalisation."""
    mean, fit_s = timed(lambda x: jax.numpy.mean(pca.device_rows(x), axis=0), pair.train)
    fitted = Fitted(folder="raw", encode=f"{SAVED}:encode_centred", state={"mean": mean})
    yield describe(
        "raw", lambda x: _centred(fitted.state, x, 0), pair, fit_seconds=fit_s, fitted=fitted
    )


def describe_pca(pair: PairData, cfg: SweepConfig, ctx: MethodContext) -> Iterator[Descriptors]:
    """Every removed-PC count from the pair's one PCA fit: the centred image minus its
    projection on the first k components.

    ``pca.suffix_descriptors`` (coefficients and the residual) serve all counts at once
    (``starts=removed_pcs``); ``pca.output=pixels`` encodes each count in pixel space, one
    encoding per count (the seed's form: the same similarities, slower).
    """
    state, ks = ctx.pca_fit.state, ctx.removed_pcs
    shown = as_images(state.components[: cfg.tb.n_basis_images], pair)
    basis = [shown[:k] if k else None for k in ks]
    how = "encode_pixels" if cfg.pca.output == "pixels" else "encode_suffix"
    fitted = Fitted(folder="pca", encode=f"{SAVED}:{how}", state=state, counts=cfg.removed_pcs)
    if cfg.pca.output == "pixels":
        for k, removed in zip(ks, basis, strict=True):
            yield describe(
                "pca",
                lambda x, k=k: pca.encode(state, x, k, "pixels"),
                pair,
                removed_pcs=(k,),
                basis=(removed,),
                fit_seconds=ctx.pca_fit.seconds,
                fitted=fitted,
            )
    else:
        yield describe(
            "pca",
            lambda x: pca.suffix_descriptors(state, x),
            pair,
            removed_pcs=ks,
            starts=ks,
            basis=basis,
            fit_seconds=ctx.pca_fit.seconds,
            fitted=fitted,
        )


def describe_diff_pca(
    pair: PairData, cfg: SweepConfig, ctx: MethodContext
) -> Iterator[Descriptors]:
    """Supervised change removal (Lowry & Milford) for every removed-PC count from one fit
    on the aligned training places' season differences: each count's descriptor is the
    image minus its projection on the first k change directions, all counts scored in one
    matching pass over suffixes of ``diff_pca.suffix_descriptors``."""
    ks = ctx.removed_pcs
    state, fit_s = timed(  # every direction: shapes that do not depend on the counts
        lambda a, b: diff_pca.fit_diff_pca(a, b, solver=cfg.pca.solver, mesh=ctx.mesh),
        *pair.aligned_train,
    )
    shown = as_images(state.components[: cfg.tb.n_basis_images], pair)
    yield describe(
        "diff_pca",
        lambda x: diff_pca.suffix_descriptors(state, x),
        pair,
        removed_pcs=ks,
        starts=ks,
        basis=[shown[:k] if k else None for k in ks],
        fit_seconds=fit_s,
        basis_name="removed_changes",
        fitted=Fitted(
            folder="diff_pca",
            encode=f"{SAVED}:encode_suffix",
            state=state,
            counts=cfg.removed_pcs,
        ),
    )


def describe_lda(pair: PairData, cfg: SweepConfig, ctx: MethodContext) -> Iterator[Descriptors]:
    """Within-place whitening in the leading ``lda.n_components`` components of the pair's
    PCA fit (all of them when it has fewer; ``vpr_jax.encoders.lda``). fit_seconds is that
    PCA fit plus the whitening."""
    m = min(cfg.lda.n_components, pca.rank_limit(len(pair.train), pair.train[0].size))
    state, lda_s = timed(
        lambda a, b: lda.fit_lda(ctx.pca_fit.state, a, b, m, cfg.lda.shrinkage),
        *pair.aligned_train,
    )
    shown = as_images(state.transform[: cfg.tb.n_basis_images], pair)
    yield describe(
        "lda",
        lambda x: lda.encode(state, x),
        pair,
        basis=(shown,),
        fit_seconds=ctx.pca_fit.seconds + lda_s,
        basis_name="invariant_directions",
        fitted=Fitted(folder="lda", encode=f"{SAVED}:encode_lda", state=state),
    )


def describe_ica(pair: PairData, cfg: SweepConfig, ctx: MethodContext) -> Iterator[Descriptors]:
    """Symmetric FastICA per removed-PC count, all whitened from the pair's one PCA fit.

    Yields each count as soon as it is done, so the sweep saves its cells at once.
    fit_seconds is the PCA fit plus that count's FastICA iterations: what ICA costs alone.
    """
    pca_state = ctx.pca_fit.state
    rank = ica.data_rank(pca_state, len(pair.train))
    c = cfg.ica
    for k in ctx.removed_pcs:
        try:
            ica.resolve_n_components(c.n_components, k, rank)
        except ValueError as err:
            raise UserError(str(err)) from None
        state, ica_s = timed(
            lambda x, k=k: ica.fit_ica(
                x,
                jax.random.key(cfg.seed),
                n_components=c.n_components,
                removed_pcs=k,
                fun=c.fun,
                alpha=c.alpha,
                max_iter=c.max_iter,
                tol=c.tol,
                n_init=c.n_init,
                pca_state=pca_state,
            ),
            pair.train,
        )
        converged = bool(state.converged)
        warning = (
            None
            if converged
            else (
                f"ICA ({state.unmixing.shape[0]} components, removed_pcs={k}) did not converge: "
                f"stopped at ica.max_iter={c.max_iter} above ica.tol={c.tol}; raise ica.max_iter "
                "or ica.tol, or lower ica.n_components"
            )
        )
        basis = as_images(np.asarray(ica.mixing(state)).T[: cfg.tb.n_basis_images], pair)
        yield describe(
            "ica",
            lambda x, state=state: ica.encode(state, x),
            pair,
            removed_pcs=(k,),
            basis=(basis,),
            warning=warning,
            fit_seconds=ctx.pca_fit.seconds + ica_s,
            n_iter=int(state.n_iter),
            converged=converged,
            basis_name="independent_components",
            fitted=Fitted(
                folder=f"ica_k{k:03d}", encode=f"{SAVED}:encode_ica", state=state, counts=(k,)
            ),
        )
