"""How each season looks: the grayscale tones and contrasts of every layer, per season.

The world is the same in every season; only its appearance changes, the way it does on
the Nordland line:

- sky: clear summer sky, overcast fall and winter; in winter the overcast sky is darker
  than the snow;
- vegetation: summer dark uniform green; fall patchy orange/yellow/brown (in grayscale
  brighter and mottled); spring fresh light green, sparse foliage, brown fields, snow on
  the mountains; winter snow on ground, roofs and mountains, bare birches, dark spruces;
- fields change with the season in ways that do not stay the same from place to place
  (green crops, harvested stubble, ploughed soil, lingering snow in hollows).
"""

from __future__ import annotations

from typing import NamedTuple

SEASONS = ("spring", "summer", "fall", "winter")


class _Look(NamedTuple):
    """How a season looks (tones are grayscale reflectances in [0, 1])."""

    sky_top: float
    sky_hor: float
    cloud_cover: float  # typical fraction of sky covered
    cloud_tone: float
    cloud_contrast: float
    visibility: float  # haze distance, world units: far things fade into the horizon tone
    mtn_rock: float
    mtn_snow: float
    snowline: float  # pixels above the horizon where mountain snow starts
    hill: float
    ground: float  # mean ground tone
    ground_a: float  # contrast of land-use pattern A (meadows vs fields)
    ground_b: float  # contrast of land-use pattern B (crops: green, harvested, ploughed)
    ground_c: float  # contrast of land-use pattern C (fields harvested / mown this season)
    ground_fine: float  # grass / stubble texture contrast
    ground_mottle: float  # patchy high-contrast texture (fall colours, melting snow)
    ground_snow: float  # 0..1: snow cover of the whole ground
    snow_patches: float  # 0..1: lingering snow in hollows (spring)
    ballast: float
    rail: float
    spruce: float
    birch: float  # foliage tone
    birch_var: float  # per-tree spread of the foliage tone (fall: yellow ... brown)
    birch_alpha: float  # foliage density (bare in winter, sparse in spring)
    bush: float
    house_roof: float
    wall_spruce: float
    wall_birch: float
    wall_tex: float  # forest texture contrast
    wall_patch: float  # patches of changed deciduous foliage (fall colours, spring leaves)
    wall_snow: float  # snow caught in the spruces
    light: float  # overall illumination of the scene below the sky
    exposure: float
    sun: float  # strength of the side-lighting gradient (sunny seasons)
    noise: float  # sensor noise relative to the default (dim winter light is noisier)
    treeline: float  # how jagged the forest's tree-line looks (snow rounds it off)


_LOOKS = {
    "summer": _Look(
        sky_top=0.56,
        sky_hor=0.74,
        cloud_cover=0.30,
        cloud_tone=0.92,
        cloud_contrast=0.5,
        visibility=80.0,
        mtn_rock=0.40,
        mtn_snow=0.80,
        snowline=8.5,
        hill=0.24,
        ground=0.30,
        ground_a=0.07,
        ground_b=-0.06,
        ground_c=0.03,
        ground_fine=0.05,
        ground_mottle=0.0,
        ground_snow=0.0,
        snow_patches=0.0,
        ballast=0.45,
        rail=0.15,
        spruce=0.16,
        birch=0.22,
        birch_var=0.04,
        birch_alpha=1.0,
        bush=0.22,
        house_roof=0.22,
        wall_spruce=0.17,
        wall_birch=0.23,
        wall_tex=0.05,
        wall_patch=0.0,
        wall_snow=0.0,
        light=1.0,
        exposure=1.0,
        sun=0.06,
        noise=1.0,
        treeline=1.0,
    ),
    "spring": _Look(
        sky_top=0.60,
        sky_hor=0.76,
        cloud_cover=0.45,
        cloud_tone=0.88,
        cloud_contrast=0.45,
        visibility=60.0,
        mtn_rock=0.42,
        mtn_snow=0.86,
        snowline=3.5,
        hill=0.32,
        ground=0.34,
        ground_a=0.05,
        ground_b=-0.04,
        ground_c=-0.10,
        ground_fine=0.06,
        ground_mottle=0.05,
        ground_snow=0.0,
        snow_patches=0.7,
        ballast=0.47,
        rail=0.17,
        spruce=0.19,
        birch=0.42,
        birch_var=0.06,
        birch_alpha=0.55,
        bush=0.33,
        house_roof=0.25,
        wall_spruce=0.20,
        wall_birch=0.36,
        wall_tex=0.08,
        wall_patch=0.12,
        wall_snow=0.0,
        light=1.0,
        exposure=1.0,
        sun=0.04,
        noise=1.0,
        treeline=1.0,
    ),
    "fall": _Look(
        sky_top=0.66,
        sky_hor=0.78,
        cloud_cover=0.75,
        cloud_tone=0.80,
        cloud_contrast=0.4,
        visibility=45.0,
        mtn_rock=0.38,
        mtn_snow=0.80,
        snowline=6.0,
        hill=0.36,
        ground=0.34,
        ground_a=0.04,
        ground_b=0.12,
        ground_c=0.06,
        ground_fine=0.05,
        ground_mottle=0.20,
        ground_snow=0.0,
        snow_patches=0.0,
        ballast=0.44,
        rail=0.16,
        spruce=0.18,
        birch=0.50,
        birch_var=0.35,
        birch_alpha=0.95,
        bush=0.42,
        house_roof=0.24,
        wall_spruce=0.19,
        wall_birch=0.42,
        wall_tex=0.15,
        wall_patch=0.40,
        wall_snow=0.0,
        light=0.92,
        exposure=1.0,
        sun=0.02,
        noise=1.0,
        treeline=1.0,
    ),
    "winter": _Look(
        sky_top=0.5,
        sky_hor=0.68,
        cloud_cover=0.90,
        cloud_tone=0.7,
        cloud_contrast=0.25,
        visibility=35.0,
        mtn_rock=0.55,
        mtn_snow=0.90,
        snowline=0.0,
        hill=0.55,
        ground=0.9,
        ground_a=0.04,
        ground_b=0.0,
        ground_c=0.0,
        ground_fine=0.03,
        ground_mottle=0.02,
        ground_snow=1.0,
        snow_patches=0.0,
        ballast=0.80,
        rail=0.45,
        spruce=0.2,
        birch=0.40,
        birch_var=0.05,
        birch_alpha=0.40,
        bush=0.84,
        house_roof=0.90,
        wall_spruce=0.3,
        wall_birch=0.46,
        wall_tex=0.08,
        wall_patch=0.0,
        wall_snow=0.35,
        light=0.95,
        exposure=0.97,
        sun=0.015,
        noise=1.0,
        treeline=0.4,
    ),
}
