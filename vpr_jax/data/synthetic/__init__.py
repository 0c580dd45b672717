"""Built-in seasonal route: a deterministic stand-in for Nordland, so the suite runs offline.

A train's forward camera moves along one route, one place per frame, rendered at 32 x 64
(height x width) grayscale float32 in [0, 1]. The scene is a small pseudo-3D world,
rendered in layers, one module each, back to front:

- ``terrain``: sky and clouds, far mountains, forested hills, the ground plane and the track;
- ``vegetation``: the season's fields on the ground, and the forest walls on either side;
- ``objects``: spruces, birches, houses, poles and bushes between the track and the forest;
- ``lighting``: one ride's weather and light (:class:`_Conditions`): slow drift of
  illumination, exposure and camera pose, auto-exposure, vignetting, sensor noise;

on top of ``world`` (what stands where, the route's geometry and the camera's pose on it),
``season`` (how each season looks), ``camera`` (the pinhole camera and the per-block pose)
and ``noise`` (value noise, textures, texture look-ups). ``render`` composes the layers for
a block of frames; ``api`` holds the public functions.

Everything the world contains depends only on ``seed``; the season and the traversal only
change appearance, the way they do on the Nordland line (sky and clouds, exposure and
illumination drift, vegetation, fields, snow, camera offset, synchronisation, noise).

Rendering is vectorised numpy (plus ``cv2.remap`` for texture look-ups) over blocks of
frames; every pixel of a frame depends only on (seed, season, traversal, frame id), so a
subset of frames, in any order, gives exactly the rows of rendering them all. Per-frame
values go through elementwise IEEE arithmetic only (no transcendental functions, whose SIMD
and scalar paths may differ in the last bit) and per-row reductions, so the result does not
depend on how frames are batched.
"""

from vpr_jax.data.synthetic.api import DEFAULT_N_FRAMES, render_season, synthetic_route
from vpr_jax.data.synthetic.season import SEASONS

__all__ = ["DEFAULT_N_FRAMES", "SEASONS", "render_season", "synthetic_route"]
