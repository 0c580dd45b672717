"""Validating a sweep before JAX loads: its pairs, its logdir, its data and its split.

``make_plan`` answers bad input (a pair outside the seasons, a foreign logdir, unreadable
data, a removed-PC count that leaves nothing) with one ``UserError`` line within about a
second, and returns what the run needs. Nothing is written here.
"""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path
from typing import NamedTuple

from vpr_jax.config import BENCHMARK_SOURCES, SequenceConfig, SweepConfig
from vpr_jax.data import SEASON_ORDER, Benchmark, Route, load_data, load_train_route
from vpr_jax.data.benchmark import BENCHMARK_PAIRS
from vpr_jax.data.precomputed import OutsideSide, read_precomputed
from vpr_jax.data.preprocess import preprocess_benchmark, preprocess_route
from vpr_jax.data.splits import Split, make_split
from vpr_jax.errors import UserError
from vpr_jax.method_table import SWEEPS_REMOVED_PCS, MethodInfo, resolve_methods
from vpr_jax.outputs.logdir import check_same_config, prepare_logdir
from vpr_jax.progress import Log


class Plan(NamedTuple):
    """A validated sweep: what ``experiments.run.run_cells`` runs."""

    cfg: SweepConfig
    logdir: Path  # absolute
    pairs: list[tuple[str, str]]  # (database season, query season)
    route: Route | None  # loaded, screened and preprocessed (a benchmark's training route)
    split: Split | None  # of the route
    benchmark: Benchmark | None = None  # data.source is a benchmark: its one pair
    methods: tuple[MethodInfo, ...] = ()  # cfg.methods as rows of the method table
    outside: dict[str, dict[str, OutsideSide]] = {}  # precomputed set -> side -> descriptors

    def describe(self) -> str:
        """What the sweep runs on, for the run log's first line."""
        if self.benchmark is None:
            return (
                f"{len(self.route)} frames per season, {len(self.split.train)} training, "
                f"{len(self.split.val)} validation and {len(self.split.test)} test places "
                "per season"
            )
        b = self.benchmark
        train = (
            f"training on {len(self.split.train)} places of each of {', '.join(self.route.seasons)}"
            if self.route is not None
            else f"training on the {len(b.db):,} database images"
        )
        return (
            f"{b.source}: {len(b.db):,} database images, {len(b.query):,} queries, {train}, "
            f"ground truth {b.truth.describe()}"
        )


def resolve_benchmark_pair(spec: str, source: str) -> list[tuple[str, str]]:
    """A benchmark has one pair, its database and queries: ``all`` or that pair's name."""
    db, query = BENCHMARK_PAIRS[source]
    if spec.strip() not in ("all", f"{db}-{query}"):
        raise UserError(
            f"season_pairs={spec} does not apply to data.source={source}: its one "
            f"pair is {db}-{query} (database {db}, queries {query}); use "
            "season_pairs=all"
        )
    return [(db, query)]


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
            raise UserError(
                f"season pair {name!r} is not db-query: write e.g. "
                "season_pairs=summer-fall,spring-fall or season_pairs=all"
            )
        if db == query:
            raise UserError(
                f"season pair {name!r} names {db} twice: a pair needs two "
                "different seasons, e.g. summer-fall"
            )
        unknown = [s for s in (db, query) if s not in seasons]
        if unknown:
            raise UserError(
                f"season pair {name!r} uses {', '.join(unknown)}, not in "
                f"data.seasons={list(seasons)}: add it there or fix the pair"
            )
        if (db, query) not in pairs:
            pairs.append((db, query))
    if not pairs:
        raise UserError("season_pairs is empty: write season_pairs=all or e.g. summer-fall")
    return pairs


def fit_counts(
    cfg: SweepConfig, n_train_images: int, n_pixels: int, given: frozenset[str], log: Log
) -> SweepConfig:
    """The removed-PC counts and component counts the training set can serve: PCA of the
    pair's ``n_train_images`` (both seasons), the season differences of its aligned places.

    Counts the user set on the command line (``given``) are refused when the training set
    cannot serve them; defaults and a preset's values are trimmed to what it can, with one
    note each: removed counts dropped, ``ica.n_components`` capped."""
    limit = min(n_train_images - 1, n_pixels)
    if "lda" in cfg.methods and cfg.lda.n_components > limit:
        log(
            f"note: lda.n_components={cfg.lda.n_components} exceeds the {limit} principal "
            f"components of {n_train_images} training images: lda whitens in all {limit}"
        )
    if not SWEEPS_REMOVED_PCS & set(cfg.methods):
        return cfg
    cfg = _trimmed(cfg, n_train_images, n_pixels, given, log)
    check_components(cfg, n_train_images, n_pixels)
    return cfg


def _trimmed(
    cfg: SweepConfig, n_train_images: int, n_pixels: int, given: frozenset[str], log: Log
) -> SweepConfig:
    """``cfg`` with the counts it did not get from the command line cut to what
    ``n_train_images`` serve (``fit_counts``)."""
    limit = min(n_train_images - 1, n_pixels)
    why = f"PCA of {n_train_images} training images has {limit} components"
    most = {"removed_pcs": limit - 1}
    if "diff_pca" in cfg.methods:
        most["removed_pcs"] = min(limit - 1, n_train_images // 2, n_pixels)
        why += f" and {n_train_images // 2} aligned places span at most that many changes"
    n_ica = cfg.ica.n_components
    if "ica" in cfg.methods and n_ica != "all":
        if "ica.n_components" in given and "removed_pcs" not in given:
            most["removed_pcs"] = min(most["removed_pcs"], limit - n_ica)
            why += f", {n_ica} of them for ICA (ica.n_components)"
        elif "ica.n_components" not in given:
            kept = [k for k in cfg.removed_pcs if k <= most["removed_pcs"]] or [0]
            cap = limit - max(kept)
            if n_ica > cap >= 1:
                log(
                    f"note: ica.n_components={n_ica} capped to {cap}: {why} and removed_pcs "
                    f"goes up to {max(kept)} (set ica.n_components to choose)"
                )
                cfg = dataclasses.replace(cfg, ica=dataclasses.replace(cfg.ica, n_components=cap))
    if "removed_pcs" not in given:
        dropped = [k for k in cfg.removed_pcs if k > most["removed_pcs"]]
        kept = tuple(k for k in cfg.removed_pcs if k <= most["removed_pcs"])
        if dropped and kept:
            log(f"note: removed_pcs {dropped} dropped: {why} (set removed_pcs to choose)")
            cfg = dataclasses.replace(cfg, removed_pcs=kept)
    return cfg


def check_components(cfg: SweepConfig, n_train_images: int, n_pixels: int) -> None:
    """Refuse removed-PC and component counts the training set cannot serve."""
    limit = min(n_train_images - 1, n_pixels)
    if max(cfg.removed_pcs) >= limit:
        raise UserError(
            f"removed_pcs={list(cfg.removed_pcs)} leaves no component: PCA of "
            f"{n_train_images} training images has {limit} components, so use "
            f"counts below {limit}"
        )
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
        raise UserError(
            f"removed_pcs up to {max(cfg.removed_pcs)} for diff_pca, but the "
            f"season differences of {n_train_images // 2} aligned training places "
            f"span at most {most} directions: use counts up to {most}, or leave "
            "diff_pca out of methods"
        )


def read_outside_sets(cfg: SweepConfig, bench: Benchmark) -> dict[str, dict[str, OutsideSide]]:
    """Every set of outside descriptors (``precomputed.*``), read once in the benchmark's
    order: a file that cannot serve its images is one line now, before any method runs."""
    sides = {"database": bench.db_names, "queries": bench.query_names}
    return {
        name: read_precomputed(files, name, sides, cfg.data.root)
        for name, files in cfg.precomputed.items()
    }


def make_plan(cfg: SweepConfig, log: Log, given: frozenset[str] = frozenset()) -> Plan:
    """Check pairs and logdir, load (and screen, and preprocess) the route or benchmark, split
    the route, and fit the removed-PC counts to the training set (``fit_counts``; ``given``:
    the keys set on the command line)."""
    logdir = Path(cfg.logdir).expanduser().resolve()
    benchmark = cfg.data.source in BENCHMARK_SOURCES
    if benchmark:
        pairs = resolve_benchmark_pair(cfg.season_pairs, cfg.data.source)
    else:
        pairs = resolve_pairs(cfg.season_pairs, cfg.data.seasons)
    prepare_logdir(logdir)
    if not cfg.sequence.enabled and cfg.sequence.ds != SequenceConfig().ds:
        log(
            f"note: sequence.ds={list(cfg.sequence.ds)} is ignored while sequence.enabled="
            "false: single images only (add sequence.enabled=true for the ds axis)"
        )
    prep = (cfg.preprocess, cfg.patchnorm.size, cfg.patchnorm.rounded, log)
    data = load_data(cfg.data, cfg.seed, log)
    if not benchmark:
        route = preprocess_route(data, *prep)
        split = make_split(route.frame_ids, cfg.split)
        cfg = fit_counts(cfg, 2 * len(split.train), route.images[pairs[0][0]][0].size, given, log)
        methods = resolve_methods(cfg.methods, True, cfg.data.source)
        check_same_config(logdir, cfg)
        return Plan(cfg=cfg, logdir=logdir, pairs=pairs, route=route, split=split, methods=methods)
    bench = preprocess_benchmark(data, *prep)
    if len(bench.query) < 2:
        raise UserError(
            f"data.source={cfg.data.source} has {len(bench.query)} query image(s): "
            "validation and test need at least two"
        )
    route = load_train_route(cfg.data, cfg.seed, log)
    split = None
    if route is None:
        log(
            f"note: data.source={cfg.data.source} has no aligned training places: the "
            f"encoders fit on the database images, the last split.val_fraction="
            f"{cfg.split.val_fraction} of the queries validate; methods and objectives that "
            "learn from the alignment (diff_pca, lda, cross_season) need data.train_source"
        )
        n_train = len(bench.db)
    else:
        route = preprocess_route(route, *prep)
        split = make_split(route.frame_ids, cfg.split)
        n_train = 2 * len(split.train)
    cfg = fit_counts(cfg, n_train, bench.db[0].size, given, log)
    methods = resolve_methods(
        cfg.methods, route is not None, cfg.data.source, tuple(cfg.precomputed)
    )
    check_same_config(logdir, cfg)
    return Plan(
        cfg=cfg,
        logdir=logdir,
        pairs=pairs,
        route=route,
        split=split,
        benchmark=bench,
        methods=methods,
        outside=read_outside_sets(cfg, bench),
    )
