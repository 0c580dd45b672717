"""Contact sheet of the built-in synthetic route: one row per season, one column per place.

    python -m experiments.contact_sheet [--out contact_sheet.png] [--n-places 8] [--seed 0]
        [--seasons spring,summer,fall,winter] [--scale 3] [--n-frames 3600]

The same places (spread evenly along the route) appear in every row, so the sheet shows what
changes between seasons and what stays. Images are upscaled with nearest neighbour; season
names are written on the left, frame ids on top. Prints the path written.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from vpr_jax.data.route import IMAGE_SHAPE
from vpr_jax.data.synthetic import DEFAULT_N_FRAMES, SEASONS, render_season
from vpr_jax.errors import UserError, exit_code

LABEL_WIDTH = 72  # pixels left of the images, for the season names
HEADER_HEIGHT = 16  # pixels above the images, for the frame ids
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def sheet_shape(n_seasons: int, n_places: int, scale: int) -> tuple[int, int]:
    """(height, width) of the sheet in pixels."""
    h, w = IMAGE_SHAPE
    return HEADER_HEIGHT + n_seasons * h * scale, LABEL_WIDTH + n_places * w * scale


def spread_places(n_places: int, n_frames: int) -> np.ndarray:
    """``n_places`` frame ids evenly spread along a route of ``n_frames`` (centres of equal
    stretches)."""
    return ((np.arange(n_places) + 0.5) * n_frames / n_places).astype(np.int64)


def make_sheet(images: dict[str, np.ndarray], frame_ids: np.ndarray, scale: int) -> np.ndarray:
    """uint8 grayscale grid: ``images[season]`` is (n_places, 32, 64) in [0, 1]."""
    h, w = IMAGE_SHAPE
    sheet = np.full(sheet_shape(len(images), len(frame_ids), scale), 255, np.uint8)
    for row, (season, imgs) in enumerate(images.items()):
        y0 = HEADER_HEIGHT + row * h * scale
        strip = np.concatenate(list(imgs), axis=1)  # (32, n_places * 64)
        strip = np.round(np.clip(strip, 0.0, 1.0) * 255.0).astype(np.uint8)
        strip = cv2.resize(
            strip, (strip.shape[1] * scale, h * scale), interpolation=cv2.INTER_NEAREST
        )
        sheet[y0 : y0 + h * scale, LABEL_WIDTH:] = strip
        font_scale = 0.45
        (tw, th), _ = cv2.getTextSize(season, _FONT, font_scale, 1)
        cv2.putText(
            sheet,
            season,
            (max(2, (LABEL_WIDTH - tw) // 2), y0 + (h * scale + th) // 2),
            _FONT,
            font_scale,
            0,
            1,
            cv2.LINE_AA,
        )
    for col, fid in enumerate(frame_ids):
        text = str(int(fid))
        (tw, th), _ = cv2.getTextSize(text, _FONT, 0.35, 1)
        x0 = LABEL_WIDTH + col * w * scale + (w * scale - tw) // 2
        cv2.putText(sheet, text, (x0, (HEADER_HEIGHT + th) // 2), _FONT, 0.35, 0, 1, cv2.LINE_AA)
    return sheet


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line on stderr, exit 2 (argparse prints usage too)
        raise UserError(f"{message}: see python -m experiments.contact_sheet --help")


def _parse(argv: Sequence[str] | None) -> argparse.Namespace:
    p = _Parser(prog="python -m experiments.contact_sheet", description=__doc__.splitlines()[0])
    p.add_argument("--out", default="contact_sheet.png", help="PNG to write")
    p.add_argument("--n-places", type=int, default=8, help="columns: places along the route")
    p.add_argument("--seed", type=int, default=0, help="world seed")
    p.add_argument("--seasons", default=",".join(SEASONS), help="comma-separated, one row each")
    p.add_argument("--scale", type=int, default=3, help="nearest-neighbour upscaling factor")
    p.add_argument("--n-frames", type=int, default=DEFAULT_N_FRAMES, help="route length")
    args = p.parse_args(argv)
    args.seasons = [s.strip() for s in args.seasons.split(",") if s.strip()]
    unknown = [s for s in args.seasons if s not in SEASONS]
    if not args.seasons or unknown:
        raise UserError(
            f"--seasons {','.join(unknown) or '(empty)'} not understood: "
            f"use a comma-separated list of {', '.join(SEASONS)}"
        )
    for name, lo, hi in (("n_places", 1, 200), ("scale", 1, 32), ("n_frames", 1, None)):
        value = getattr(args, name)
        if value < lo or (hi is not None and value > hi):
            rng = f"{lo}..{hi}" if hi is not None else f">= {lo}"
            raise UserError(f"--{name.replace('_', '-')} {value} out of range: use {rng}")
    if args.n_places > args.n_frames:
        raise UserError(
            f"--n-places {args.n_places} exceeds --n-frames {args.n_frames}: "
            "ask for fewer places or a longer route"
        )
    if args.seed < 0:
        raise UserError(f"--seed {args.seed} is negative: use a seed >= 0")
    if Path(args.out).suffix.lower() != ".png":
        raise UserError(f"--out {args.out} is not a .png path: name a file ending in .png")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    return exit_code(lambda: _write_sheet(_parse(argv)))


def _write_sheet(args: argparse.Namespace) -> None:
    places = spread_places(args.n_places, args.n_frames)
    images = {s: render_season(places, s, seed=args.seed) for s in args.seasons}
    sheet = make_sheet(images, places, args.scale)
    out = Path(args.out)
    if out.is_dir():
        raise UserError(f"--out {out} is a folder: name a .png file")
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), sheet):
        raise UserError(f"could not write {out}: check the folder is writable")
    print(out)


if __name__ == "__main__":
    sys.exit(main())
