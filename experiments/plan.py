"""Validating a sweep before anything is written: its pairs, its logdir, its methods and
their settings, its data and its split.

``make_plan`` answers bad input (a pair outside the seasons, a foreign logdir, a setting a
method refuses, unreadable data, a removed-PC count that leaves nothing) with one
``UserError`` line, the methods' settings before any data is read, and returns what the run
needs: every fit of every method (``experiments.resolve``). Nothing is written here.
"""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path
from typing import Any, NamedTuple

from experiments import resolve  # loads each method's module (JAX) only when it resolves
from vpr_jax.config import (
    BENCHMARK_PAIRS,
    BENCHMARK_SOURCES,
    DataConfig,
    SequenceConfig,
    SweepConfig,
)
from vpr_jax.data import SEASON_ORDER, Benchmark, Route, load_data, load_train_route
from vpr_jax.data.precomputed import OutsideSide, read_precomputed
from vpr_jax.data.preprocess import preprocess_benchmark, preprocess_route
from vpr_jax.data.splits import Split, make_split
from vpr_jax.errors import UserError
from vpr_jax.method_table import NAMES as METHOD_NAMES
from vpr_jax.outputs.logdir import check_same_config, identity, prepare_logdir
from vpr_jax.progress import Log


class Plan(NamedTuple):
    """A validated sweep: what ``experiments.run.run_cells`` runs."""

    cfg: SweepConfig
    logdir: Path  # absolute
    pairs: list[tuple[str, str]]  # (database season, query season)
    route: Route | None  # loaded, screened and preprocessed (a benchmark's training route)
    split: Split | None  # of the route
    benchmark: Benchmark | None = None  # data.source is a benchmark: its one pair
    methods: tuple[resolve.Resolved, ...] = ()  # cfg.methods loaded, settings checked
    fits: tuple[resolve.Fit, ...] = ()  # every method's fits in each pair, in order
    outside: dict[str, dict[str, OutsideSide]] = {}  # precomputed set -> side -> descriptors
    pca: resolve.Resolved | None = None  # pca's settings: they shape the pair's shared
    # PCA fit (resolve.pca_settings)
    identity: dict = {}  # the config's part that decides every cell (outputs.logdir)
    mesh: Any = None  # the devices, a jax Mesh (sharding.start_devices); None: one device

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


def read_outside_sets(
    cfg: SweepConfig, bench: Benchmark, log: Log
) -> dict[str, dict[str, OutsideSide]]:
    """Every set of outside descriptors (``precomputed.*``), read once in the benchmark's
    order: a file that cannot serve its images is one line now, before any method runs; a
    warning names the images whose descriptor is zero."""
    from vpr_jax.methods.precomputed import checked_sides, zero_warning  # JAX: only for sets

    names = {"database": bench.db_names, "queries": bench.query_names}
    out = {}
    for name, files in cfg.precomputed.items():
        out[name] = checked_sides(name, files, read_precomputed(files, name, names, cfg.data.root))
        warning = zero_warning(out[name], names)
        if warning:
            log(f"warning: precomputed set {name}: {warning}")
    return out


def make_plan(cfg: SweepConfig, log: Log, given: frozenset[str] = frozenset()) -> Plan:
    """Check pairs, logdir and the methods' settings, load (and screen, and preprocess) the
    route or benchmark, split the route, and fit the methods' settings and the removed-PC
    counts to the training set (``given``: the keys set on the command line)."""
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
    aligned = cfg.data.aligned_training
    _note_unused_settings(cfg, given, log)
    methods = resolve.resolve_methods(cfg, aligned, cfg.data.source, given)
    _check_baseline(cfg, methods, given)
    pca = resolve.pca_settings(cfg)
    from vpr_jax.methods.pca import shared_components  # JAX: loaded with the methods
    from vpr_jax.sharding import mesh_size, start_devices

    data = _load(cfg, benchmark, pairs, log)
    _check_train_places(cfg, data)
    mesh = start_devices(cfg.mesh, log)
    n_images, n_pixels = data.n_train, data.n_pixels
    held = shared_components(pca.combinations[0].settings, n_images, n_pixels)
    sets = {
        r.name: resolve.training_set(r, n_images, n_pixels, aligned, given, held, mesh_size(mesh))
        for r in methods
    }
    methods = resolve.check_training_set(methods, sets, log)
    recorded = _with_effective_settings(cfg, methods)
    named = tuple(cfg.methods)  # a user's method is imported only when this command names it
    check_same_config(logdir, recorded, lambda c: resolve.settings_identities(c, named))
    return Plan(
        cfg=recorded,
        logdir=logdir,
        pairs=pairs,
        route=data.route,
        split=data.split,
        benchmark=data.benchmark,
        methods=methods,
        fits=tuple(f for r in methods for f in resolve.fits(r, cfg)),
        outside=read_outside_sets(cfg, data.benchmark, log) if data.benchmark is not None else {},
        pca=pca,
        identity=identity(recorded),
        mesh=mesh,
    )


def _check_train_places(cfg: SweepConfig, data) -> None:
    """``split.train_places`` within the training places a pair has."""
    places = cfg.split.train_places or ()
    held = data.n_train // 2 if data.route is not None else data.n_train
    if places and max(places) > held:
        raise UserError(
            f"split.train_places={list(places)} goes beyond the {held} training places a "
            f"season has here: use counts up to {held}"
        )


def _check_baseline(cfg: SweepConfig, methods, given: frozenset[str]) -> None:
    """A baseline named on the command line must be in the sweep."""
    names = {r.name for r in methods} | set(cfg.precomputed)
    if "baseline" in given and cfg.baseline not in names:
        raise UserError(
            f"baseline={cfg.baseline} is not in this sweep: choose one of "
            f"{', '.join(sorted(names))} (results.md's paired differences are to it)"
        )


def _note_unused_settings(cfg: SweepConfig, given: frozenset[str], log: Log) -> None:
    """One note per built-in method whose settings the command line sets although
    ``methods`` leaves it out: nothing reads them."""
    for name in METHOD_NAMES:
        keys = sorted(k for k in given if k.startswith(f"{name}."))
        if keys and name not in cfg.methods:
            log(
                f"note: {', '.join(keys)} set, but methods={list(cfg.methods)} has no {name}: "
                f"unused (add {name} to methods to sweep it)"
            )


class _Data(NamedTuple):
    route: Route | None
    split: Split | None
    benchmark: Benchmark | None
    n_train: int  # the training images of a pair, both seasons (or the benchmark's database)
    n_pixels: int


def _load(cfg: SweepConfig, benchmark: bool, pairs, log: Log) -> _Data:
    """The route and its split, or the benchmark (and its training route)."""
    prep = (cfg.preprocess, cfg.patchnorm.size, cfg.patchnorm.rounded, log)
    data = load_data(_seasons_read(cfg.data, benchmark, pairs), cfg.seed, log)
    if not benchmark:
        route = preprocess_route(data, *prep)
        split = make_split(route.frame_ids, cfg.split)
        n_pixels = next(iter(route.images.values()))[0].size
        return _Data(
            route=route,
            split=split,
            benchmark=None,
            n_train=2 * len(split.train),
            n_pixels=n_pixels,
        )
    bench = preprocess_benchmark(data, *prep)
    if len(bench.query) < 2:
        raise UserError(
            f"data.source={cfg.data.source} has {len(bench.query)} query image(s): "
            "validation and test need at least two"
        )
    route = load_train_route(cfg.data, cfg.seed, log)
    if route is None:
        log(
            f"note: data.source={cfg.data.source} has no aligned training places: the "
            f"encoders fit on the database images, the last split.val_fraction="
            f"{cfg.split.val_fraction} of the queries validate; methods and objectives that "
            "learn from the alignment (diff_pca, lda, cross_season) need data.train_source"
        )
        return _Data(
            route=None,
            split=None,
            benchmark=bench,
            n_train=len(bench.db),
            n_pixels=bench.db[0].size,
        )
    route = preprocess_route(route, *prep)
    split = make_split(route.frame_ids, cfg.split)
    return _Data(
        route=route,
        split=split,
        benchmark=bench,
        n_train=2 * len(split.train),
        n_pixels=bench.db[0].size,
    )


def _seasons_read(data: DataConfig, benchmark: bool, pairs) -> DataConfig:
    """``data`` rendering only the seasons ``pairs`` name, where that changes nothing but
    the cost: the built-in route's seasons are rendered on the same frames each (a season of
    the whole route is 0.27 GiB), unless constant frames are dropped (a place is dropped
    where any of ``data.seasons`` shows one). Nordland's seasons are all read: its places
    are the frames every season holds, the same whichever pairs a run names."""
    if benchmark or data.source != "synthetic" or data.drop_constant_frames:
        return data
    named = {season for pair in pairs for season in pair}
    return dataclasses.replace(data, seasons=tuple(s for s in data.seasons if s in named))


def _with_effective_settings(cfg: SweepConfig, methods) -> SweepConfig:
    """``cfg`` with every method's settings as it runs them (defaults filled in, checked,
    fitted to the training set, axes as lists): what config.yaml records."""
    builtin, plugins = {}, dict(cfg.plugin)
    for r in methods:
        if r.info.precomputed:
            continue  # cfg.precomputed holds a set's files as given
        if r.info.plugin:
            plugins[r.name] = r.effective
        else:
            builtin[r.name] = r.effective
    return dataclasses.replace(cfg, plugin=plugins, **builtin)
