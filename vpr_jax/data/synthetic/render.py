"""One block of frames, composed layer by layer, back to front.

Every pixel of a frame depends only on (seed, season, traversal, frame id): each layer is
vectorised over the block with elementwise arithmetic and per-row reductions, so the
result does not depend on how frames are batched.
"""

from __future__ import annotations

import numpy as np

from vpr_jax.data.synthetic.lighting import _add_sensor_noise, _Conditions, _expose, _illumination
from vpr_jax.data.synthetic.objects import _draw_objects, _object_window
from vpr_jax.data.synthetic.terrain import (
    _ground_points,
    _hills,
    _landscape,
    _mountains,
    _sky,
    _track,
)
from vpr_jax.data.synthetic.vegetation import _fields, _forest_walls, _wall_hits
from vpr_jax.data.synthetic.world import _camera_view, _World


def _render_block(world: _World, cond: _Conditions, frame_ids: np.ndarray) -> np.ndarray:
    """Render ``frame_ids`` (int64) of one ride: (B, H, W) float32 in [0, 1]."""
    look = cond.look
    view = _camera_view(world, cond, frame_ids)
    light = _illumination(cond, view)
    # Sky, mountains and hills: rows above the horizon only (the horizon stays in row 12).
    top = _sky(cond, view, light)
    top = _mountains(world, look, view, light, top)
    top = _hills(world, look, view, light, top)
    # Ground plane: the season's fields and the track, from the row holding the horizon down.
    ground = _ground_points(view)
    g = _track(look, ground, _fields(world, look, ground))
    img = _landscape(look, light, top, ground, g)
    # Forest walls, then the standalone objects in front of them, painted far to near.
    walls = _wall_hits(world, view)
    img = _forest_walls(world, look, view, light.light, img, walls)
    objs = world.objects(*_object_window(view.z))
    img = _draw_objects(objs, look, img, view, light.light, walls.d_hit, walls.any_hit)
    # Exposure, side light, gradients, vignetting, noise.
    img = _expose(cond, img, view, light)
    return _add_sensor_noise(cond, img, view.ids)
