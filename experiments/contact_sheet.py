"""A contact sheet of the built-in route: the same places, one row per season.

    python -m experiments.contact_sheet --out contact_sheet.png

prints the path it wrote; open the PNG to see what the sweep's default data looks like.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from vpr_jax.data.synthetic import DEFAULT_N_FRAMES, SEASONS, render_season
from vpr_jax.errors import UserError

LABEL_WIDTH = 70  # pixels, after scaling is applied to the images only


def contact_sheet(seasons, n_places: int, seed: int, scale: int, n_frames: int) -> np.ndarray:
    """uint8 (rows, cols) grayscale: a label column, then one 32x64 image per place."""
    places = np.linspace(0, n_frames - 1, n_places).round().astype(np.int64)
    rows = []
    for season in seasons:
        images = render_season(places, season, seed=seed)
        strip = np.concatenate(list(images), axis=1)
        strip = cv2.resize((strip * 255).round().astype(np.uint8), None, fx=scale, fy=scale,
                           interpolation=cv2.INTER_NEAREST)
        label = np.full((strip.shape[0], LABEL_WIDTH), 255, np.uint8)
        cv2.putText(label, season, (4, strip.shape[0] // 2 + 5), cv2.FONT_HERSHEY_SIMPLEX,
                    0.5, 0, 1, cv2.LINE_AA)
        rows.append(np.concatenate([label, strip], axis=1))
    return np.concatenate(rows, axis=0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="contact_sheet.png", help="PNG to write")
    parser.add_argument("--n-places", type=int, default=8, help="columns: places along the route")
    parser.add_argument("--seed", type=int, default=0, help="which route")
    parser.add_argument("--seasons", default=",".join(SEASONS), help="rows, comma separated")
    parser.add_argument("--scale", type=int, default=3, help="pixel magnification")
    parser.add_argument("--n-frames", type=int, default=DEFAULT_N_FRAMES, help="route length")
    args = parser.parse_args(argv)
    try:
        for name in ("n_places", "scale", "n_frames"):
            if getattr(args, name) < 1:
                raise UserError(f"--{name.replace('_', '-')} must be >= 1")
        seasons = [s.strip() for s in args.seasons.split(",") if s.strip()]
        if not seasons:
            raise UserError("--seasons is empty: e.g. --seasons summer,winter")
        sheet = contact_sheet(seasons, args.n_places, args.seed, args.scale, args.n_frames)
        out = Path(args.out)
        if not out.parent.is_dir():
            raise UserError(f"folder {out.parent} does not exist: create it or change --out")
        if not cv2.imwrite(str(out), sheet):
            raise UserError(f"could not write {out}: use a writable path ending in .png")
    except UserError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
