"""Data sources: aligned routes yield a ``Route`` of (N, 32, 64) float32 seasons; benchmarks
(``config.BENCHMARK_SOURCES``) yield a ``Benchmark``: database, queries, ground-truth sets."""

from __future__ import annotations

import dataclasses

from vpr_jax.config import BENCHMARK_SOURCES, DataConfig
from vpr_jax.data.benchmark import Benchmark
from vpr_jax.data.route import IMAGE_SHAPE, SEASON_ORDER, Route
from vpr_jax.data.screen import screen_route
from vpr_jax.errors import UserError
from vpr_jax.progress import Log

__all__ = [
    "IMAGE_SHAPE",
    "SEASON_ORDER",
    "Benchmark",
    "Route",
    "load_data",
    "load_route",
    "load_train_route",
]


def load_route(cfg: DataConfig, seed: int, log: Log = print) -> Route:
    """Read (or render) every configured season of an aligned route, then screen it for
    constant frames (reported; dropped with ``data.drop_constant_frames``). Raises
    UserError on bad data."""
    if cfg.source == "synthetic":
        from vpr_jax.data.synthetic.api import kept_route

        route = kept_route(cfg.n_frames, cfg.seasons, seed=seed, frame_step=cfg.frame_step)
    else:
        from vpr_jax.data.nordland import load_nordland

        route = load_nordland(
            cfg.source,
            cfg.root,
            cfg.seasons,
            cache_dir=cfg.cache_dir,
            frame_list=cfg.frame_list,
            frame_step=cfg.frame_step,
            frame_range=cfg.frame_range,
            max_pixels=cfg.max_pixels,
            log=log,
        )
    return screen_route(route, max_std=cfg.constant_std, drop=cfg.drop_constant_frames, log=log)


def load_benchmark(cfg: DataConfig, seed: int, log: Log = print) -> Benchmark:
    """A benchmark source: VPR-Bench's folders, a positions benchmark, or Nordland* (read
    from the 64x32 release as an aligned route of ``data.seasons``, then partitioned)."""
    if cfg.source == "vpr_bench":
        from vpr_jax.data.vpr_bench import read_vpr_bench

        return read_vpr_bench(cfg.root, max_pixels=cfg.max_pixels, log=log)
    if cfg.source == "positions":
        from vpr_jax.data.positions import read_positions

        return read_positions(cfg.root, cfg.radius_m, max_pixels=cfg.max_pixels, log=log)
    from vpr_jax.data.benchmark import star_partition

    db, query = _star_seasons(cfg.seasons)  # before anything is read
    route = load_route(
        dataclasses.replace(cfg, source="nordland_images", train_source=None, train_root=None),
        seed,
        log,
    )
    return star_partition(route, db, query)


def _star_seasons(seasons) -> tuple[str, str]:
    """Nordland*: the references are winter, the queries summer (VPR-Bench)."""
    if set(seasons) != {"summer", "winter"}:
        raise UserError(
            f"data.source=nordland_star matches summer queries to winter "
            f"references, data.seasons={list(seasons)}: set "
            "data.seasons=[summer,winter]"
        )
    return "winter", "summer"


def load_train_route(cfg: DataConfig, seed: int, log: Log = print) -> Route | None:
    """The aligned route a benchmark's encoders learn from (``data.train_source``), or None
    when they fit on the benchmark's database images."""
    if cfg.train_source is None:
        return None
    log(f"training route: data.train_source={cfg.train_source}, seasons {list(cfg.seasons)}")
    # The benchmark's frame selection is not the route's: the route's split picks its places.
    route_cfg = dataclasses.replace(
        cfg,
        source=cfg.train_source,
        root=cfg.train_root,
        train_source=None,
        train_root=None,
        frame_list=None,
        frame_range=None,
    )
    return load_route(route_cfg, seed, log)


def load_data(cfg: DataConfig, seed: int, log: Log = print) -> Route | Benchmark:
    """What ``data.source`` names: an aligned route or a benchmark."""
    if cfg.source in BENCHMARK_SOURCES:
        return load_benchmark(cfg, seed, log)
    return load_route(cfg, seed, log)
