"""One season pair through one method: fit on the training images, encode the database and
the queries. What comes out is ``Descriptors``; matching, metrics and files are the runner's
(``experiments/cells.py``), as in VPR_Tutorial's dataset -> features -> matching ->
evaluation.

Methods with the removed-PC axis (``config.SWEEPS_REMOVED_PCS``: pca, diff_pca, ica) serve
several counts: PCA's coefficients and diff_pca's suffix descriptors serve every count at
once (cosine on the suffix ``[k:]`` is the removal of the first k components, one
similarity pass for all), ICA fits once per count and yields each as soon as it is done.
diff_pca and lda learn from the alignment of the training places (``aligned_train``). The
auto-encoders checkpoint their training and report it through the ``MethodContext`` the
runner passes in.
"""

from __future__ import annotations

import dataclasses
import time
import zlib
from collections.abc import Callable, Iterable, Iterator
from functools import partial
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np
from jax.sharding import Mesh

from vpr_jax import sharding
from vpr_jax.config import SweepConfig
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import diff_pca, ica, lda, objectives, pca
from vpr_jax.encoders.train import TrainingLog, fit_autoencoder
from vpr_jax.errors import UserError
from vpr_jax.ground_truth import GroundTruth
from vpr_jax.logdir import lock_folder, training_identity
from vpr_jax.matching import degenerate_rows


class PairData(NamedTuple):
    """One pair's images and ground truth: what every method fits on and is scored with.

    Aligned routes (``experiments.cells.pair_data``): ``train`` holds the training places of
    both seasons back to back, row i of each half one place (``aligned_training``), and the
    validation places are aligned the same way. Unaligned benchmarks
    (``experiments.cells.benchmark_pair``) train on their database images, or on an aligned
    route's training places (``data.train_source``).
    """

    db_season: str
    query_season: str
    train: np.ndarray  # (n_train_images, 32, 64)
    db: np.ndarray  # (n_db, 32, 64) database season, test places (or every frame)
    query: np.ndarray  # (n_test, 32, 64) query season, test places
    db_ids: np.ndarray  # route positions of the database images (frame ids: sequences)
    query_ids: np.ndarray
    truth: GroundTruth  # correct database positions of each query
    val_db: np.ndarray  # (n_val_db, 32, 64): the validation database
    val_query: np.ndarray  # (n_val_query, 32, 64): the validation queries
    val_db_ids: np.ndarray
    val_query_ids: np.ndarray
    val_truth: GroundTruth
    aligned_training: bool = True  # train (and val) are two seasons' aligned places

    @property
    def val(self) -> np.ndarray:
        """The images the auto-encoders' early stopping scores: the validation places of
        both seasons, database first (aligned pairs), or, trained on a benchmark's database,
        the held-out validation queries (the database is the training set)."""
        if not self.aligned_training:
            return self.val_query
        return np.concatenate([self.val_db, self.val_query])

    @property
    def name(self) -> str:
        return f"{self.db_season}-{self.query_season}"

    @property
    def aligned_train(self) -> tuple[np.ndarray, np.ndarray]:
        """(database season, query season) training images: row i of both shows the same
        place (the same frame id: seasons are aligned by frame id when loaded)."""
        if not self.aligned_training:
            raise ValueError(f"pair {self.name} has no aligned training places")
        n = len(self.train) // 2
        return self.train[:n], self.train[n:]


class PCAFit(NamedTuple):
    """The pair's PCA fit, shared by its PCA and ICA cells (ICA whitens with it)."""

    state: pca.PCAState
    seconds: float


class Descriptors(NamedTuple):
    """What one method made of a pair: the descriptors of the database and the queries, for
    one or more removed-PC counts, and what the fit cost and found."""

    method: str
    removed_pcs: tuple[int, ...]  # the cells these descriptors serve (0 without the axis)
    starts: tuple[int, ...]  # per count: cosine on descriptor features [start:]
    db: jax.Array  # (n_db, d)
    query: jax.Array  # (n_queries, d)
    val_db: jax.Array  # (n_val, d): the validation places, database season
    val_query: jax.Array  # (n_val, d): the validation places, query season
    fit_seconds: float
    encode_ms_per_image: float  # warm (compiled) encoding time
    n_iter: int = 0  # iterations of an iterative fit (0: closed form; epochs when trained)
    converged: bool = True  # False when an iterative fit stopped at its iteration limit
    basis: tuple[np.ndarray | None, ...] = ()  # per count: (m, 32, 64) images of what the
    basis_name: str = "removed_components"  # method removed or learned; TensorBoard tag
    warning: str | None = None  # one line for the run log (non-convergence, degenerate)
    objective: str = ""  # the auto-encoders' training objective; "" for the other methods


class MethodContext(NamedTuple):
    """What a method may need from the runner besides the pair's images and the config."""

    removed_pcs: tuple[int, ...] = (0,)  # counts still to do (pca, diff_pca, ica)
    objectives: tuple[str, ...] = ("reconstruct",)  # objectives still to do (fae, cae)
    pca_fit: PCAFit | None = None  # the pair's PCA fit (pca, ica): see fit_pair_pca
    checkpoint_dir: Path | None = None  # this pair's model folders go under it
    training_log: Callable[[str], TrainingLog] | None = None  # method name -> its log
    identity: dict | None = None  # what besides its spec determines a trained model
    mesh: Mesh | None = None  # devices to split work over (vpr_jax.sharding); None: one


def _timed(fn: Callable, *args):
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - start


def pca_components_needed(cfg: SweepConfig, n_samples: int, n_features: int) -> int | None:
    """How many leading components the pair's PCA fit must hold for the methods that use it:
    the largest removed count (pca), that plus ``ica.n_components`` (ica; None for "all",
    which needs every component), ``lda.n_components`` (lda); at least 1, at most the rank
    limit. From the configured counts, not the ones still to do, so a resumed sweep fits
    the same components."""
    limit = pca.rank_limit(n_samples, n_features)
    needed = [1]
    if "pca" in cfg.methods:
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
    methods in ``USES_PCA_FIT`` need (``pca_components_needed``), by the solver
    ``pca.solver`` names. The runner fits it once per pair and passes it in their
    context."""
    n = pca_components_needed(cfg, len(pair.train), pair.train[0].size)
    state, seconds = _timed(
        lambda x: pca.fit_pca(x, n, solver=cfg.pca.solver, mesh=mesh, seed=cfg.seed), pair.train
    )
    return PCAFit(state, seconds)


def _encode(encode: Callable, pair: PairData) -> tuple[jax.Array, jax.Array, float]:
    """Database and query descriptors, and the warm encoding time in ms per image."""
    encode(pair.db)  # compile for this shape
    db, seconds_db = _timed(encode, pair.db)
    query, seconds_q = _timed(encode, pair.query)
    return db, query, 1000 * (seconds_db + seconds_q) / (len(pair.db) + len(pair.query))


def _encode_val(encode: Callable, pair: PairData) -> tuple[jax.Array, jax.Array]:
    if pair.aligned_training:  # one call: the shapes the training already compiled for
        both = encode(pair.val)
        return both[: len(pair.val_db)], both[len(pair.val_db) :]
    return encode(pair.val_db), encode(pair.val_query)


def degenerate_warning(db, query) -> str | None:
    """One run-log line when descriptors cannot tell places apart (zero descriptors, or all
    pointing one way): cosine matching of them is arbitrary, so the cell's metrics mean
    nothing. None when the descriptors are fine."""
    zero, parallel = [], []
    for name, desc in (("database", db), ("query", query)):
        n_zero, one_way = degenerate_rows(jax.numpy.reshape(desc, (len(desc), -1)))
        if int(n_zero):
            zero.append(f"{name} {int(n_zero):,} of {len(desc):,}")
        if bool(one_way):
            parallel.append(name)
    found = [f"zero descriptors ({', '.join(zero)})"] if zero else []
    if parallel:
        found.append(f"the nonzero {' and '.join(parallel)} descriptors all point one way")
    if not found:
        return None
    return (
        f"{' and '.join(found)}: their matches are arbitrary. Check for constant images "
        "(data.drop_constant_frames=true) or, for an auto-encoder, dead units (another "
        "seed, train.learning_rate, more epochs)"
    )


def _descriptors(
    method: str,
    encode: Callable,
    pair: PairData,
    *,
    removed_pcs=(0,),
    starts=(0,),
    basis=(None,),
    warning: str | None = None,
    **fit,
) -> Descriptors:
    """Encode the pair with ``encode`` and add the degenerate-descriptor check's warning."""
    db, query, ms = _encode(encode, pair)
    found = "; ".join(w for w in (warning, degenerate_warning(db, query)) if w) or None
    return Descriptors(
        method,
        tuple(removed_pcs),
        tuple(starts),
        db,
        query,
        *_encode_val(encode, pair),
        encode_ms_per_image=ms,
        basis=tuple(basis),
        warning=found,
        **fit,
    )


def _images(vectors: np.ndarray, pair: PairData) -> np.ndarray:
    return np.asarray(vectors).reshape(len(vectors), *pair.train.shape[1:])


@jax.jit
def _centred(images, mean):
    """Raw descriptor: flattened pixels minus the training mean (compiled once per shape)."""
    return pca.flatten(images) - mean


def describe_raw(pair: PairData, cfg: SweepConfig, ctx: MethodContext) -> Iterator[Descriptors]:
    """Raw pixels, centred with the training mean; cosine does the L2 normalisation."""
    mean, fit_s = _timed(lambda x: jax.numpy.mean(pca.flatten(x), axis=0), pair.train)
    yield _descriptors("raw", lambda x: _centred(x, mean), pair, fit_seconds=fit_s)


def describe_pca(pair: PairData, cfg: SweepConfig, ctx: MethodContext) -> Iterator[Descriptors]:
    """Every removed-PC count from the pair's one PCA fit: the centred image minus its
    projection on the first k components.

    ``pca.suffix_descriptors`` (coefficients and the residual) serve all counts at once
    (``starts=removed_pcs``); ``pca.output=pixels`` encodes each count in pixel space, one
    encoding per count (the seed's form: the same similarities, slower).
    """
    state, ks = ctx.pca_fit.state, ctx.removed_pcs
    shown = _images(state.components[: cfg.tb.n_basis_images], pair)
    basis = [shown[:k] if k else None for k in ks]
    if cfg.pca.output == "pixels":
        for k, removed in zip(ks, basis, strict=True):
            yield _descriptors(
                "pca",
                lambda x, k=k: pca.encode(state, x, k, "pixels"),
                pair,
                removed_pcs=(k,),
                basis=(removed,),
                fit_seconds=ctx.pca_fit.seconds,
            )
    else:
        yield _descriptors(
            "pca",
            lambda x: pca.suffix_descriptors(state, x),
            pair,
            removed_pcs=ks,
            starts=ks,
            basis=basis,
            fit_seconds=ctx.pca_fit.seconds,
        )


def describe_diff_pca(
    pair: PairData, cfg: SweepConfig, ctx: MethodContext
) -> Iterator[Descriptors]:
    """Supervised change removal (Lowry & Milford) for every removed-PC count from one fit
    on the aligned training places' season differences: each count's descriptor is the
    image minus its projection on the first k change directions, all counts scored in one
    matching pass over suffixes of ``diff_pca.suffix_descriptors``."""
    ks = ctx.removed_pcs
    state, fit_s = _timed(  # every direction: shapes that do not depend on the counts
        lambda a, b: diff_pca.fit_diff_pca(a, b, solver=cfg.pca.solver, mesh=ctx.mesh),
        *pair.aligned_train,
    )
    shown = _images(state.components[: cfg.tb.n_basis_images], pair)
    yield _descriptors(
        "diff_pca",
        lambda x: diff_pca.suffix_descriptors(state, x),
        pair,
        removed_pcs=ks,
        starts=ks,
        basis=[shown[:k] if k else None for k in ks],
        fit_seconds=fit_s,
        basis_name="removed_changes",
    )


def describe_lda(pair: PairData, cfg: SweepConfig, ctx: MethodContext) -> Iterator[Descriptors]:
    """Within-place whitening in the leading ``lda.n_components`` components of the pair's
    PCA fit (all of them when it has fewer; ``vpr_jax.encoders.lda``). fit_seconds is that
    PCA fit plus the whitening."""
    m = min(cfg.lda.n_components, pca.rank_limit(len(pair.train), pair.train[0].size))
    state, lda_s = _timed(
        lambda a, b: lda.fit_lda(ctx.pca_fit.state, a, b, m, cfg.lda.shrinkage),
        *pair.aligned_train,
    )
    shown = _images(state.transform[: cfg.tb.n_basis_images], pair)
    yield _descriptors(
        "lda",
        lambda x: lda.encode(state, x),
        pair,
        basis=(shown,),
        fit_seconds=ctx.pca_fit.seconds + lda_s,
        basis_name="invariant_directions",
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
        state, ica_s = _timed(
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
        basis = _images(np.asarray(ica.mixing(state)).T[: cfg.tb.n_basis_images], pair)
        yield _descriptors(
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
        )


def autoencoder_spec(method: str, cfg: SweepConfig) -> ae.Spec:
    if method == "fae":
        return ae.FAESpec(
            hidden=cfg.fae.hidden, centre=cfg.fae.input_centre, standardise=cfg.fae.standardise
        )
    c = cfg.cae
    return ae.CAESpec(
        tuple(c.channels), tuple(c.kernel_sizes), c.code_channels, c.space_to_depth, c.standardise
    )


def model_name(method: str, objective: str = "") -> str:
    """``fae`` for the seed's objective (and methods without one), ``fae_cross_season``
    otherwise: names the cell's run, the model's checkpoint folder and its training run."""
    return method if objective in ("", "reconstruct") else f"{method}_{objective}"


def describe_autoencoder(
    method: str, pair: PairData, cfg: SweepConfig, ctx: MethodContext
) -> Iterator[Descriptors]:
    """Train (or resume, or restore) the pair's auto-encoder for each objective still to do
    (``ctx.objectives``); its code is the descriptor.

    It trains on both seasons' training images and stops early on the validation places
    (``vpr_jax.data.splits``): the images themselves for ``reconstruct``, the aligned
    places' pairs for ``cross_season`` (``vpr_jax.encoders.objectives``). Every
    objective starts from the same initial weights. fit_seconds is the training time (of
    all sessions, when it was resumed); n_iter counts epochs; converged means early
    stopping ended training before train.epochs.
    """
    spec = autoencoder_spec(method, cfg)
    epochs = getattr(cfg, method).epochs or cfg.train.epochs  # fae.epochs / cae.epochs first
    settings = dataclasses.replace(cfg.train, epochs=epochs)
    for objective in ctx.objectives:
        name = model_name(method, objective)
        if ctx.checkpoint_dir is not None and jax.process_index() == 0:
            # Logdirs of one name under different parents share this folder: one writer.
            lock_folder(
                ctx.checkpoint_dir / name,
                "checkpoint folder",
                "wait for it to finish, or give this logdir another name (or set "
                "train.checkpoint_dir)",
            )
        log = ctx.training_log(name) if ctx.training_log else None
        try:
            result = fit_autoencoder(
                spec,
                objectives.training_data(objective, pair.train),
                objectives.training_data(objective, pair.val),
                jax.random.fold_in(jax.random.key(cfg.seed), zlib.crc32(method.encode())),
                settings,
                checkpoint_dir=ctx.checkpoint_dir / name if ctx.checkpoint_dir else None,
                identity={
                    **(ctx.identity or {}),
                    "train": training_identity(settings),
                    "season_pair": pair.name,
                    "method": method,
                },
                log=log,
                name=f"{pair.name} {name}",
                mesh=ctx.mesh,
                objective=objective,
            )
        finally:
            if log is not None:
                log.close()
        yield _autoencoder_descriptors(method, objective, result, pair, cfg)


def _autoencoder_descriptors(
    method: str, objective: str, result, pair: PairData, cfg: SweepConfig
) -> Descriptors:
    encode = ae.make_encode(result.graphdef)
    # Encoding runs on one device: a mesh-replicated model would encode on every device.
    params = jax.tree.map(sharding.to_host, result.params)
    basis = None
    if method == "fae":  # what each hidden unit looks for: its weights as an image
        weights = np.asarray(params["encoder"]["kernel"]).T[: cfg.tb.n_basis_images]
        basis = _images(weights, pair)
    return _descriptors(
        method,
        lambda x: encode(params, x),
        pair,
        basis=(basis,),
        objective=objective,
        fit_seconds=result.train_seconds,
        n_iter=result.epochs,
        converged=result.stopped_early,
        basis_name="hidden_units",
    )


# A method maps (pair, config, context) to its descriptors, in any order, as they finish.
Method = Callable[[PairData, SweepConfig, MethodContext], Iterable[Descriptors]]
METHODS: dict[str, Method] = {
    "raw": describe_raw,
    "pca": describe_pca,
    "diff_pca": describe_diff_pca,
    "ica": describe_ica,
    "lda": describe_lda,
    "fae": partial(describe_autoencoder, "fae"),
    "cae": partial(describe_autoencoder, "cae"),
}
USES_PCA_FIT = frozenset({"pca", "ica", "lda"})  # their context carries the pair's PCA fit
AUTOENCODERS = frozenset({"fae", "cae"})  # trained, one model per objective
