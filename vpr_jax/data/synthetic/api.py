"""The built-in route's public entry points: render places of one ride, or build the
frame-aligned :class:`Route` of several seasons; both check their inputs. ``kept_route``
is the sweep's: a small route rendered once per process."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterable

import numpy as np

from vpr_jax import host_arrays
from vpr_jax.data.route import Route
from vpr_jax.data.synthetic.camera import _H, _W
from vpr_jax.data.synthetic.lighting import _Conditions
from vpr_jax.data.synthetic.render import _render_block
from vpr_jax.data.synthetic.season import SEASONS
from vpr_jax.data.synthetic.world import _world
from vpr_jax.errors import UserError

DEFAULT_N_FRAMES = 3600
_CHUNK = 256  # frames rendered at once: bounds the working memory


def _check_season(season: str) -> None:
    if season not in SEASONS:
        raise UserError(
            f"unknown season {season!r} for the synthetic route: use one of {', '.join(SEASONS)}"
        )


def _check_int(value, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise UserError(
            f"{name} must be an integer >= {minimum}, got {value!r}: "
            f"set {name} to a whole number of at least {minimum}"
        )
    return int(value)


def render_season(
    frame_ids: np.ndarray, season: str, seed: int = 0, traversal: int = 0
) -> np.ndarray:
    """Render the places ``frame_ids`` of the route in ``season``: (N, 32, 64) float32 in [0,1].

    ``frame_ids`` are place indices along the route (any subset, any order, repeats allowed);
    rendering a subset gives exactly the same pixels as those rows of rendering everything.
    The world (what stands where) depends only on ``seed``; ``season`` and ``traversal``
    (another ride in the same season: other clouds, exposure drift, camera offset, noise)
    change only the appearance.
    """
    _check_season(season)
    seed = _check_int(seed, "seed", 0)
    traversal = _check_int(traversal, "traversal", 0)
    ids = np.asarray(frame_ids)
    if ids.ndim != 1 or (ids.size and not np.issubdtype(ids.dtype, np.integer)):
        raise UserError(
            f"frame_ids must be a 1-D array of integers, got shape {ids.shape} "
            f"dtype {ids.dtype}: pass e.g. np.arange(n_frames)"
        )
    ids = ids.astype(np.int64)
    if ids.size and ids.min() < 0:
        raise UserError("frame_ids must be >= 0: pass place indices along the route")
    out = host_arrays.empty((len(ids), _H, _W))  # JAX reads it in place
    if not len(ids):
        return out
    world = _world(seed)
    cond = _Conditions(seed, season, traversal)
    order = np.argsort(ids, kind="stable")  # nearby frames share objects: render in order
    for s in range(0, len(ids), _CHUNK):
        sel = order[s : s + _CHUNK]
        out[sel] = _render_block(world, cond, ids[sel])
    return out


def synthetic_route(
    n_frames: int = DEFAULT_N_FRAMES,
    seasons: Iterable[str] = ("spring", "summer", "fall"),
    seed: int = 0,
    frame_step: int = 1,
) -> Route:
    """The built-in route: ``frame_ids = arange(0, n_frames, frame_step)``, traversal 0 of
    every season, as a frame-aligned :class:`Route`."""
    n_frames, seasons, frame_step = _checked_route(n_frames, seasons, frame_step)
    frame_ids = np.arange(0, n_frames, frame_step, dtype=np.int64)
    images = {season: render_season(frame_ids, season, seed=seed) for season in seasons}
    return Route(frame_ids, images)


def _checked_route(n_frames, seasons, frame_step) -> tuple[int, tuple[str, ...], int]:
    n_frames = _check_int(n_frames, "n_frames", 1)
    frame_step = _check_int(frame_step, "frame_step", 1)
    seasons = (seasons,) if isinstance(seasons, str) else tuple(seasons)
    if not seasons:
        raise UserError(f"no seasons asked for: name at least one of {', '.join(SEASONS)}")
    for season in seasons:
        _check_season(season)
    if len(set(seasons)) != len(seasons):
        raise UserError(f"season listed twice in {', '.join(seasons)}: name each season once")
    return n_frames, seasons, frame_step


# Small routes a process keeps once rendered (``kept_route``): the bytes of all their seasons.
KEPT_BYTES = 64 << 20
_kept: OrderedDict[tuple, Route] = OrderedDict()


def kept_route(n_frames: int, seasons: Iterable[str], seed: int, frame_step: int) -> Route:
    """``synthetic_route``, kept by this process for the next sweep that asks for the same
    route (a notebook's, a benchmark's, the tests' many small sweeps), which then renders
    nothing. A route of ``KEPT_BYTES`` or less (all its seasons) is kept, up
    to ``KEPT_BYTES`` of routes, the least recently asked for going first; a larger one is
    rendered every time and never kept. Its arrays are read-only (each caller gets its own
    ``Route`` and dict): a step that changed them in place would change the next sweep's
    route, so it fails instead."""
    key = (*_checked_route(n_frames, seasons, frame_step), _check_int(seed, "seed", 0))
    route = _kept.get(key)
    if route is None:
        route = synthetic_route(n_frames, seasons, seed=seed, frame_step=frame_step)
        if _nbytes(route) > KEPT_BYTES:
            return route
        for array in (route.frame_ids, *route.images.values()):
            array.flags.writeable = False
        _kept[key] = route
        while sum(map(_nbytes, _kept.values())) > KEPT_BYTES:
            _kept.popitem(last=False)
    _kept.move_to_end(key)
    return Route(route.frame_ids, dict(route.images), route.files)


def _nbytes(route: Route) -> int:
    return sum(a.nbytes for a in route.images.values())
