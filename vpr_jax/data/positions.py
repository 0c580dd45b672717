"""GPS-tagged benchmarks (Oxford RobotCar, St Lucia, Pittsburgh, MSLS as their users export
them): ``ROOT/database/`` and ``ROOT/queries/`` images, with ``ROOT/database.csv`` and
``ROOT/queries.csv`` giving each image's position, ``name,x,y`` in metres (e.g. UTM easting
and northing). A query's correct database images are those within ``data.radius_m``
(default 25 m, the Pittsburgh convention), found by a grid search
(``vpr_jax.data.ground_truth.within_radius``), never a dense distance matrix.

Images are taken in file-name order; every image needs a row in its CSV (rows for files that
are not there are ignored and counted).
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import numpy as np

from vpr_jax.data.benchmark import Benchmark
from vpr_jax.data.ground_truth import within_radius
from vpr_jax.data.images import list_images, note_colour, read_images, relative_names
from vpr_jax.errors import UserError
from vpr_jax.progress import Log
from vpr_jax.shapes import MAX_PIXELS

SIDES = ("database", "queries")
LAYOUT = "database/, queries/, database.csv and queries.csv (name,x,y in metres)"


def read_positions(
    root: str | os.PathLike,
    radius_m: float = 25.0,
    *,
    max_pixels: int = MAX_PIXELS,
    log: Log = print,
) -> Benchmark:
    root = Path(root).expanduser()
    if not root.is_dir():
        raise UserError(
            f"data root {root} is not a folder: set data.root=PATH to the folder holding {LAYOUT}"
        )
    if not radius_m > 0:
        raise UserError(f"data.radius_m={radius_m} must be positive: e.g. data.radius_m=25")
    paths, xy = {}, {}
    for side in SIDES:
        if not (root / side).is_dir():
            raise UserError(
                f"{root / side} is missing: data.source=positions reads {LAYOUT}; "
                "point data.root at such a folder"
            )
        paths[side] = list_images(root / side, f"the {side} images")
        xy[side] = _positions(root / f"{side}.csv", paths[side], log)
    truth = within_radius(xy["queries"], xy["database"], radius_m)
    images, colour = {}, {}
    for side in SIDES:
        images[side], colour[side] = read_images(
            paths[side], side, resize=True, max_pixels=max_pixels
        )
    note_colour(colour, log)
    unmatched = int((~truth.has_match()).sum())
    log(
        f"positions: {len(paths['database']):,} database images, {len(paths['queries']):,} "
        f"queries ({unmatched:,} with no database image within {radius_m:g} m) from {root}"
    )
    return Benchmark(
        source="positions",
        db_name="database",
        query_name="queries",
        db=images["database"],
        query=images["queries"],
        truth=truth,
        db_ids=np.arange(len(paths["database"])),
        query_ids=np.arange(len(paths["queries"])),
        db_names=relative_names(paths["database"], root),
        query_names=relative_names(paths["queries"], root),
    )


def _positions(csv_path: Path, images: list[Path], log: Log) -> np.ndarray:
    """(n, 2) positions of ``images`` (in their order) from ``name,x,y`` rows."""
    fix = "give every image a row name,x,y (metres, e.g. UTM easting and northing)"
    if not csv_path.is_file():
        raise UserError(f"{csv_path} is missing: data.source=positions reads {LAYOUT}; {fix}")
    try:
        with open(csv_path, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            fields = [c.strip() for c in reader.fieldnames or ()]
            if not {"name", "x", "y"} <= set(fields):
                raise UserError(f"{csv_path} has columns {fields or 'none'}, not name,x,y: {fix}")
            reader.fieldnames = fields
            table = {}
            for row in reader:
                name = (row["name"] or "").strip()
                try:
                    x, y = float(row["x"]), float(row["y"])
                except (TypeError, ValueError):
                    x = y = math.nan
                if not (math.isfinite(x) and math.isfinite(y)):
                    raise UserError(
                        f"{csv_path} line {reader.line_num}: the position of "
                        f"{name or 'an image'} is not two numbers x,y: {fix}"
                    )
                table[name] = (x, y)
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise UserError(f"{csv_path} cannot be read ({err}): {fix}") from None
    missing = [p.name for p in images if p.name not in table]
    if missing:
        raise UserError(
            f"{csv_path} has no position for {len(missing):,} image(s) in "
            f"{images[0].parent} (first: {missing[0]}): {fix}"
        )
    extra = len(table) - len(images)
    if extra > 0:
        log(
            f"note: {csv_path} lists {extra:,} name(s) with no image in {images[0].parent}: ignored"
        )
    return np.array([table[p.name] for p in images], np.float64)
