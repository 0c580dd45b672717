"""Data sources: every one yields a frame-aligned ``Route`` of (N, 32, 64) float32 seasons."""

from __future__ import annotations

from vpr_jax.config import DataConfig
from vpr_jax.data.route import IMAGE_SHAPE, SEASON_ORDER, Route
from vpr_jax.data.screen import screen_route
from vpr_jax.progress import Log

__all__ = ["IMAGE_SHAPE", "SEASON_ORDER", "Route", "load_route"]


def load_route(cfg: DataConfig, seed: int, log: Log = print) -> Route:
    """Read (or render) every configured season, then screen it for constant frames
    (reported; dropped with ``data.drop_constant_frames``). Raises UserError on bad data."""
    if cfg.source == "synthetic":
        from vpr_jax.data.synthetic import synthetic_route

        route = synthetic_route(cfg.n_frames, cfg.seasons, seed=seed, frame_step=cfg.frame_step)
    else:
        from vpr_jax.data.nordland import load_nordland

        route = load_nordland(cfg.source, cfg.root, cfg.seasons, cache_dir=cfg.cache_dir,
                              frame_list=cfg.frame_list, frame_step=cfg.frame_step,
                              max_pixels=cfg.max_pixels, log=log)
    return screen_route(route, max_std=cfg.constant_std, drop=cfg.drop_constant_frames, log=log)
