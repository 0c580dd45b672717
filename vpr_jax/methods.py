"""One season pair through one method: fit on training images, encode, match.

No result files: the sweep runner writes what these return. Every method returns one
``CellOutput`` per removed-PC count it was asked for (methods without that knob return one
cell with ``removed_pcs=0``). The auto-encoders checkpoint their training and report it
through the ``MethodContext`` the runner passes in.
"""

from __future__ import annotations

import dataclasses
import time
import zlib
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import NamedTuple

import jax
import numpy as np
from jax.sharding import Mesh

from vpr_jax import sharding
from vpr_jax.config import TRAIN_BOOKKEEPING, SweepConfig
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import ica, pca
from vpr_jax.encoders.train import TrainingLog, fit_autoencoder, split_validation
from vpr_jax.errors import UserError
from vpr_jax.matching import degenerate_rows, top_k_matches
from vpr_jax.sequence import sequence_top_k_cosine, velocities

TOP_K = 10  # enough for recall@10


class PairData(NamedTuple):
    db_season: str
    query_season: str
    train: np.ndarray  # (2 * n_train, 32, 64): training places of BOTH seasons
    db: np.ndarray  # (n_test, 32, 64) database season, test places
    query: np.ndarray  # (n_test, 32, 64) query season, same test places
    db_ids: np.ndarray  # original frame indices of the test places
    query_ids: np.ndarray
    fits: dict  # fits shared by the methods of this pair (the PCA fit), filled on first use


class Encoded(NamedTuple):
    db: jax.Array  # (n_db, d) descriptors
    query: jax.Array  # (n_queries, d)
    ms_per_image: float  # warm (compiled) encoding time
    warning: str | None  # descriptors that make matching arbitrary, if any


class CellOutput(NamedTuple):
    method: str
    removed_pcs: int
    top_scores: np.ndarray  # (n_queries, K) cosine scores, best first
    top_indices: np.ndarray  # (n_queries, K) indices into the database
    fit_seconds: float
    encode_ms_per_image: float
    basis_images: np.ndarray | None  # (m, 32, 64) what the method removed or learned, if any
    basis_name: str = "removed_components"  # TensorBoard tag under basis/
    n_iter: int = 0  # iterations of an iterative fit (0: closed form)
    converged: bool = True  # False when an iterative fit stopped at its iteration limit
    warning: str | None = None  # one line for the run log (non-convergence, degenerate)
    encoded: Encoded | None = None  # the descriptors matched: sequence matching reuses them
    feature_start: int = 0  # cosine on descriptor features [feature_start:] (PCA removal)


class MethodContext(NamedTuple):
    """What a method may need from the runner besides data and config."""

    checkpoint_dir: Path | None = None  # this pair's model folders go under it
    training_log: Callable[[str], TrainingLog] | None = None  # method name -> its log
    identity: dict | None = None  # what besides its spec determines a trained model
    mesh: Mesh | None = None  # devices to split work over (vpr_jax.sharding); None: one


def _timed(fn: Callable, *args):
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - start


def _encode(encode: Callable, pair: PairData) -> Encoded:
    """Encode database and queries, timed on a warm function, and check the descriptors."""
    encode(pair.db)  # compile for this shape
    db, seconds_db = _timed(encode, pair.db)
    query, seconds_q = _timed(encode, pair.query)
    ms = 1000 * (seconds_db + seconds_q) / (len(pair.db) + len(pair.query))
    return Encoded(db, query, ms, degenerate_warning(db, query))


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
    return (f"{' and '.join(found)}: their matches are arbitrary. Check for constant images "
            "(data.drop_constant_frames=true) or, for an auto-encoder, dead units (another "
            "seed, train.learning_rate, more epochs)")


def _join(*warnings: str | None) -> str | None:
    return "; ".join(w for w in warnings if w) or None


def shared_pca_fit(
    pair: PairData, cfg: SweepConfig, ctx: MethodContext
) -> tuple[pca.PCAState, float]:
    """The pair's PCA fit and its seconds, computed once and reused by PCA and ICA cells."""
    if "pca" not in pair.fits:
        pair.fits["pca"] = _timed(
            lambda x: pca.fit_pca(x, solver=cfg.pca.solver, mesh=ctx.mesh), pair.train
        )
    return pair.fits["pca"]


def _match(query, db, cfg: SweepConfig, ctx: MethodContext, starts=(0,)):
    return top_k_matches(query, db, TOP_K, starts=starts, block_size=cfg.matching.block_size,
                         mesh=ctx.mesh)  # fmt: skip


def _images(vectors: np.ndarray, pair: PairData) -> np.ndarray:
    return np.asarray(vectors).reshape(len(vectors), *pair.train.shape[1:])


@jax.jit
def _centred(images, mean):
    """Raw descriptor: flattened pixels minus the training mean (compiled once per shape)."""
    return pca.flatten(images) - mean


def run_raw(
    pair: PairData, removed_pcs: tuple[int, ...], cfg: SweepConfig, ctx: MethodContext
) -> list[CellOutput]:
    """Raw pixels, centred with the training mean; cosine does the L2 normalisation."""
    del removed_pcs
    mean, fit_s = _timed(lambda x: jax.numpy.mean(pca.flatten(x), axis=0), pair.train)
    enc = _encode(lambda x: _centred(x, mean), pair)
    scores, idx = _match(enc.query, enc.db, cfg, ctx)
    return [CellOutput("raw", 0, scores[0], idx[0], fit_s, enc.ms_per_image, None,
                       warning=enc.warning, encoded=enc)]


def run_pca(
    pair: PairData, removed_pcs: tuple[int, ...], cfg: SweepConfig, ctx: MethodContext
) -> list[CellOutput]:
    """One PCA fit and one matching pass serve every removed-PC count.

    Matching scores coefficient suffixes (``starts=removed_pcs``), which equals zeroing the
    first k coefficients or, with ``pca.output=pixels``, mapping the kept ones back to pixels.
    """
    state, fit_s = shared_pca_fit(pair, cfg, ctx)
    if cfg.pca.output == "pixels":
        outputs = []
        for k in removed_pcs:
            enc = _encode(lambda x, k=k: pca.encode(state, x, k, "pixels"), pair)
            scores, idx = _match(enc.query, enc.db, cfg, ctx)
            outputs.append((k, scores[0], idx[0], enc))
    else:
        enc = _encode(lambda x: pca.project(state, x), pair)
        scores, idx = _match(enc.query, enc.db, cfg, ctx, starts=removed_pcs)
        outputs = [(k, scores[i], idx[i], enc) for i, k in enumerate(removed_pcs)]
    components = _images(state.components[: cfg.tb.n_basis_images], pair)
    return [
        CellOutput("pca", k, s, i, fit_s, enc.ms_per_image, components[:k] if k else None,
                   warning=enc.warning, encoded=enc,
                   feature_start=0 if cfg.pca.output == "pixels" else k)
        for k, s, i, enc in outputs
    ]


def run_ica(
    pair: PairData, removed_pcs: tuple[int, ...], cfg: SweepConfig, ctx: MethodContext
) -> Iterator[CellOutput]:
    """Symmetric FastICA per removed-PC count, all whitened from the pair's one PCA fit.

    Yields each count's cell as soon as it is done, so the sweep saves it at once.
    fit_seconds is the PCA fit plus that count's FastICA iterations: what ICA costs alone.
    """
    pca_state, pca_s = shared_pca_fit(pair, cfg, ctx)
    rank = ica.data_rank(pca_state, len(pair.train))
    c = cfg.ica
    for k in removed_pcs:
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
        enc = _encode(lambda x, state=state: ica.encode(state, x), pair)
        scores, idx = _match(enc.query, enc.db, cfg, ctx)
        n_iter, converged = int(state.n_iter), bool(state.converged)
        warning = None if converged else (
            f"ICA ({state.unmixing.shape[0]} components, removed_pcs={k}) did not converge: "
            f"stopped at ica.max_iter={c.max_iter} above ica.tol={c.tol}; raise ica.max_iter "
            "or ica.tol, or lower ica.n_components"
        )
        basis = _images(np.asarray(ica.mixing(state)).T[: cfg.tb.n_basis_images], pair)
        yield CellOutput(
            "ica", k, scores[0], idx[0], pca_s + ica_s, enc.ms_per_image, basis,
            basis_name="independent_components", n_iter=n_iter, converged=converged,
            warning=_join(warning, enc.warning), encoded=enc,
        )  # fmt: skip


def autoencoder_spec(method: str, cfg: SweepConfig) -> ae.Spec:
    if method == "fae":
        return ae.FAESpec(hidden=cfg.fae.hidden, centre=cfg.fae.input_centre)
    c = cfg.cae
    return ae.CAESpec(tuple(c.channels), tuple(c.kernel_sizes), c.code_channels)


def run_autoencoder(
    method: str, pair: PairData, cfg: SweepConfig, ctx: MethodContext
) -> list[CellOutput]:
    """Train (or resume, or restore) the pair's auto-encoder; its code is the descriptor.

    It trains on both seasons' training images minus the tail of each stretch, which is
    the validation set for early stopping. fit_seconds is the training time (of all
    sessions, when it was resumed); n_iter counts epochs; converged means early stopping
    ended training before train.epochs.
    """
    name = f"{pair.db_season}-{pair.query_season}"
    spec = autoencoder_spec(method, cfg)
    train, val = split_validation(pair.train, 2, cfg.train.val_fraction)
    epochs = getattr(cfg, method).epochs or cfg.train.epochs  # fae.epochs / cae.epochs first
    settings = dataclasses.replace(cfg.train, epochs=epochs)
    trained_by = {
        k: v for k, v in dataclasses.asdict(settings).items() if k not in TRAIN_BOOKKEEPING
    }
    log = ctx.training_log(method) if ctx.training_log else None
    try:
        result = fit_autoencoder(
            spec,
            train,
            val,
            jax.random.fold_in(jax.random.key(cfg.seed), zlib.crc32(method.encode())),
            settings,
            checkpoint_dir=ctx.checkpoint_dir / method if ctx.checkpoint_dir else None,
            identity={**(ctx.identity or {}), "train": trained_by, "season_pair": name,
                      "method": method},  # fmt: skip
            log=log,
            name=f"{name} {method}",
            mesh=ctx.mesh,
        )
    finally:
        if log is not None:
            log.close()
    encode = ae.make_encode(result.graphdef)
    # Encoding runs on one device: a mesh-replicated model would encode on every device.
    params = jax.tree.map(sharding.to_host, result.params)
    enc = _encode(lambda x: encode(params, x), pair)
    scores, idx = _match(enc.query, enc.db, cfg, ctx)
    basis = None
    if method == "fae":  # what each hidden unit looks for: its weights as an image
        weights = np.asarray(params["encoder"]["kernel"]).T[: cfg.tb.n_basis_images]
        basis = _images(weights, pair)
    return [
        CellOutput(
            method, 0, scores[0], idx[0], result.train_seconds, enc.ms_per_image, basis,
            basis_name="hidden_units", n_iter=result.epochs, converged=result.stopped_early,
            warning=enc.warning, encoded=enc,
        )  # fmt: skip
    ]


def run_fae(pair, removed_pcs, cfg, ctx) -> list[CellOutput]:
    del removed_pcs
    return run_autoencoder("fae", pair, cfg, ctx)


def run_cae(pair, removed_pcs, cfg, ctx) -> list[CellOutput]:
    del removed_pcs
    return run_autoencoder("cae", pair, cfg, ctx)


def with_sequence(out: CellOutput, pair: PairData, ds: int, cfg: SweepConfig) -> CellOutput:
    """The same cell matched by sequences of ``ds`` frames (``vpr_jax.sequence``) on its
    descriptors; ds = 1 is the cell as it is."""
    if ds == 1:
        return out
    seq = cfg.sequence
    start = out.feature_start
    scores, idx = sequence_top_k_cosine(
        out.encoded.query[:, start:], out.encoded.db[:, start:], ds,
        query_ids=pair.query_ids, db_ids=pair.db_ids,
        vels=velocities(seq.v_min, seq.v_max, seq.v_step),
        contrast_window=seq.contrast_window, uniqueness_window=seq.uniqueness_window, k=TOP_K,
    )
    return out._replace(top_scores=scores, top_indices=idx)


# A method maps (pair, removed-PC counts, config) to its cells, in any order, as they finish.
Method = Callable[[PairData, tuple[int, ...], SweepConfig, MethodContext], Iterable[CellOutput]]
METHODS: dict[str, Method] = {
    "raw": run_raw,
    "pca": run_pca,
    "ica": run_ica,
    "fae": run_fae,
    "cae": run_cae,
}
