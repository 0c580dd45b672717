"""Validating a sweep before JAX loads: its pairs, its logdir, its data and its split.

``make_plan`` answers bad input (a pair outside the seasons, a foreign logdir, unreadable
data, a removed-PC count that leaves nothing) with one ``UserError`` line within about a
second, and returns what the run needs. Nothing is written here.
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import NamedTuple

from vpr_jax.config import SWEEPS_REMOVED_PCS, SequenceConfig, SweepConfig
from vpr_jax.data import SEASON_ORDER, Route, load_route
from vpr_jax.data.splits import Split, make_split
from vpr_jax.errors import UserError
from vpr_jax.logdir import prepare_logdir
from vpr_jax.preprocess import preprocess_route
from vpr_jax.progress import Log


class Plan(NamedTuple):
    """A validated sweep: what ``experiments.run.run_cells`` runs."""

    cfg: SweepConfig
    logdir: Path  # absolute
    pairs: list[tuple[str, str]]  # (database season, query season)
    route: Route  # loaded, screened and preprocessed
    split: Split


def resolve_pairs(spec: str, seasons: tuple[str, ...]) -> list[tuple[str, str]]:
    """``all`` -> every unordered pair, database season first (SEASON_ORDER); else db-query."""
    if spec.strip() == "all":
        rank = {s: i for i, s in enumerate(SEASON_ORDER)}
        ordered = sorted(seasons, key=lambda s: rank.get(s, len(rank)))
        return list(itertools.combinations(ordered, 2))
    pairs = []
    for name in (p.strip() for p in spec.split(",") if p.strip()):
        db, sep, query = name.partition("-")
        if not sep or not db or not query or "-" in query:
            raise UserError(f"season pair {name!r} is not db-query: write e.g. "
                            "season_pairs=summer-fall,spring-fall or season_pairs=all")
        if db == query:
            raise UserError(f"season pair {name!r} names {db} twice: a pair needs two "
                            "different seasons, e.g. summer-fall")
        unknown = [s for s in (db, query) if s not in seasons]
        if unknown:
            raise UserError(f"season pair {name!r} uses {', '.join(unknown)}, not in "
                            f"data.seasons={list(seasons)}: add it there or fix the pair")
        if (db, query) not in pairs:
            pairs.append((db, query))
    if not pairs:
        raise UserError("season_pairs is empty: write season_pairs=all or e.g. summer-fall")
    return pairs


def check_components(cfg: SweepConfig, n_train_images: int, n_pixels: int, log: Log) -> None:
    """The removed-PC counts and component counts the training set can serve: PCA of the
    pair's ``n_train_images`` (both seasons), the season differences of its aligned places."""
    limit = min(n_train_images - 1, n_pixels)
    if "lda" in cfg.methods and cfg.lda.n_components > limit:
        log(f"note: lda.n_components={cfg.lda.n_components} exceeds the {limit} principal "
            f"components of {n_train_images} training images: lda whitens in all {limit}")
    if not SWEEPS_REMOVED_PCS & set(cfg.methods):
        return
    if max(cfg.removed_pcs) >= limit:
        raise UserError(f"removed_pcs={list(cfg.removed_pcs)} leaves no component: PCA of "
                        f"{n_train_images} training images has {limit} components, so use "
                        f"counts below {limit}")
    n_ica = cfg.ica.n_components
    if "ica" in cfg.methods and n_ica != "all" and max(cfg.removed_pcs) + n_ica > limit:
        raise UserError(
            f"ica.n_components={n_ica} with removed_pcs up to {max(cfg.removed_pcs)} needs "
            f"{max(cfg.removed_pcs) + n_ica} components but PCA of {n_train_images} training "
            f"images has {limit}: use ica.n_components <= {limit - max(cfg.removed_pcs)}, "
            "ica.n_components=all, or smaller removed_pcs"
        )
    most = min(n_train_images // 2, n_pixels)
    if "diff_pca" in cfg.methods and max(cfg.removed_pcs) > most:
        raise UserError(f"removed_pcs up to {max(cfg.removed_pcs)} for diff_pca, but the "
                        f"season differences of {n_train_images // 2} aligned training places "
                        f"span at most {most} directions: use counts up to {most}, or leave "
                        "diff_pca out of methods")


def make_plan(cfg: SweepConfig, log: Log) -> Plan:
    """Check pairs and logdir, load (and screen, and preprocess) the route, split it, and
    check the removed-PC counts against the training set."""
    logdir = Path(cfg.logdir).expanduser().resolve()
    pairs = resolve_pairs(cfg.season_pairs, cfg.data.seasons)
    prepare_logdir(logdir, cfg)
    if not cfg.sequence.enabled and cfg.sequence.ds != SequenceConfig().ds:
        log(f"note: sequence.ds={list(cfg.sequence.ds)} is ignored while sequence.enabled="
            "false: single images only (add sequence.enabled=true for the ds axis)")
    route = load_route(cfg.data, cfg.seed, log)
    route = preprocess_route(route, cfg.preprocess, cfg.patchnorm.size, cfg.patchnorm.rounded,
                             log)  # fmt: skip
    split = make_split(route.frame_ids, cfg.split)
    check_components(cfg, 2 * len(split.train), int(route.images[pairs[0][0]][0].size), log)
    return Plan(cfg, logdir, pairs, route, split)
