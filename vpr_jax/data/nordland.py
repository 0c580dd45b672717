"""Real Nordland data: the 64x32 image release, raw season videos, any folders of frames.

Every reader returns a :class:`~vpr_jax.data.route.Route`: the frame ids all requested seasons
share (after an optional frame list and a frame step) and, per season, ``(N, 32, 64)`` float32
grayscale images in [0, 1] where row i of every season shows the same place.

Sources (``load_nordland(source, ...)``):

- ``nordland_images``: ``ROOT/<season>/images-%05d.png``, exactly 64x32, ids from the names.
- ``nordland_videos``: ``ROOT/<file naming the season>.mp4`` (any container OpenCV reads),
  sampled at one frame per second of video time (frame id = second), cached as ``.npz``
  (the decoding and its cache: ``vpr_jax.data.nordland_video``).
- ``folders``: ``ROOT/<season>/*.png|jpg|jpeg`` of any size, id = last integer of the name,
  converted to grayscale and resized with area interpolation.

Every reader takes the keywords ``frame_list`` (a file of frame names or ranges to keep),
``frame_step`` (keep every step-th frame after that), ``max_pixels`` (images or video frames
larger than this are refused, from their headers, before decoding) and ``log`` (where notes
go). Mistakes a user can fix raise :class:`~vpr_jax.errors.UserError` with one line naming
the problem and the fix.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Sequence
from functools import partial, reduce
from pathlib import Path
from typing import NamedTuple

import numpy as np

from vpr_jax.config import NORDLAND_SOURCES
from vpr_jax.data.frames import frame_id_from_name, is_built_in, parse_frame_list
from vpr_jax.data.images import (
    IMAGE_EXTENSIONS,
    is_image_file,
    note_colour,
    read_images,
    relative_names,
    to_unit_float,
)
from vpr_jax.data.nordland_video import find_video, video_frames
from vpr_jax.data.route import Route
from vpr_jax.errors import UserError
from vpr_jax.progress import Log
from vpr_jax.shapes import MAX_PIXELS

PathLike = str | os.PathLike

SOURCES = NORDLAND_SOURCES
RELEASE_NAME = re.compile(r"^images-(\d+)\.png$", re.IGNORECASE)


# --------------------------------------------------------------------------------------------
# public readers


def load_nordland(
    source: str, root: PathLike, seasons: Sequence[str], *, cache_dir: PathLike | None, **options
) -> Route:
    """Read ``seasons`` of the route under ``root`` from ``source`` (one of :data:`SOURCES`);
    ``options`` (``frame_list``, ``frame_step``, ``log``) as for every reader, ``cache_dir``
    for videos only."""
    if source not in SOURCES:
        raise UserError(
            f"unknown data source {source!r}: set data.source to one of {', '.join(SOURCES)}"
        )
    if source == "nordland_videos":
        return read_videos(root, seasons, cache_dir=cache_dir, **options)
    reader = read_image_release if source == "nordland_images" else read_folders
    return reader(root, seasons, **options)


def read_image_release(root: PathLike, seasons: Sequence[str], **options) -> Route:
    """Nordland's 64x32 grayscale release: ``ROOT/<season>/images-%05d.png``; ``options``
    as for every reader (``frame_list``, ``frame_step``, ``log``: see the module docstring).

    Frame ids come from the file names (0-based ``images-00000.png`` is kept as id 0). Images
    must be exactly 64 wide and 32 high; colour PNGs are converted to grayscale.
    """
    return _read_image_folders(
        "nordland_images",
        root,
        seasons,
        match=_release_id,
        resize=False,
        empty_hint="the 64x32 release names them images-00001.png ...; for other names or "
        "sizes set data.source=folders",
        options=ReadOptions(**options),
    )


def read_folders(root: PathLike, seasons: Sequence[str], **options) -> Route:
    """Any ``ROOT/<season>/*.png|jpg|jpeg`` folders of aligned frames, of any size;
    ``options`` as for every reader.

    Frame id = the last integer in each file name (``frame_2.png`` -> 2, ordered numerically).
    Images are converted to grayscale and resized to 64x32 with area interpolation.
    """
    return _read_image_folders(
        "folders",
        root,
        seasons,
        match=_folder_id,
        resize=True,
        empty_hint="put the frames there as .png, .jpg or .jpeg files numbered in their names",
        options=ReadOptions(**options),
    )


class ReadOptions(NamedTuple):
    """What every reader takes besides its root and seasons (the module docstring)."""

    frame_list: PathLike | None = None
    frame_step: int = 1
    frame_range: Sequence[int] | None = None
    max_pixels: int = MAX_PIXELS
    log: Log = print


def _read_image_folders(
    source: str,
    root: PathLike,
    seasons: Sequence[str],
    *,
    match: Callable[[Path, str], int | None],
    empty_hint: str,
    resize: bool,
    options: ReadOptions,
) -> Route:
    """Index every season folder ({frame id: path}, names ``match`` maps to ids), align the
    seasons, then read only the frames kept."""
    seasons = _check_seasons(seasons)
    frame_list, frame_step, frame_range, max_pixels, log = options
    _check_step(frame_step)
    root = _check_root(root, "the folder holding " + _folders_hint(seasons))
    files = {}
    for season in seasons:
        folder = _season_dir(root, season, seasons)
        files[season] = _index_files(
            folder, season, match=partial(match, folder), empty_hint=empty_hint
        )
    ids = _align(
        {s: np.fromiter(f, np.int64, len(f)) for s, f in files.items()},
        frame_list,
        frame_step,
        log,
        frame_range,
    )
    images, colour, names = {}, {}, {}
    for season, by_id in files.items():
        paths = [by_id[int(i)] for i in ids]
        images[season], colour[season] = read_images(
            paths, season, resize=resize, max_pixels=max_pixels
        )
        names[season] = relative_names(paths, root)
    note_colour(colour, log)
    log(_summary(source, ids, seasons, root))
    return Route(ids, images, names)


def read_videos(
    root: PathLike, seasons: Sequence[str], *, cache_dir: PathLike | None, **options
) -> Route:
    """Season videos in ``root``: the one file whose name contains the season (any case).

    One frame per second of video time: frame id t takes the first decoded frame whose
    timestamp is >= t seconds (stream timestamps; frame number / fps where those are missing
    or do not increase). Frames are grayscale, resized to 64x32 with area interpolation and
    cached under ``cache_dir`` (None: no cache), keyed by the video's absolute path, size,
    modification time and the target size, so a second run decodes nothing.
    """
    seasons = _check_seasons(seasons)
    frame_list, frame_step, frame_range, max_pixels, log = ReadOptions(**options)
    _check_step(frame_step)
    root = _check_root(root, "the folder holding the season videos (e.g. summer.mp4, fall.mp4)")
    videos = {season: find_video(root, season) for season in seasons}
    cache = None
    if cache_dir is not None:
        cache = Path(cache_dir).expanduser()
        try:
            cache.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise UserError(
                f"cannot create the video cache folder {cache} ({err.strerror}): "
                f"set data.cache_dir=PATH to a writable folder"
            ) from None
    raw = {
        season: video_frames(videos[season], season, cache, log, max_pixels) for season in seasons
    }
    ids = _align({s: r[1] for s, r in raw.items()}, frame_list, frame_step, log, frame_range)
    images = {}
    for season in seasons:
        frames, frame_ids = raw[season]
        rows = np.searchsorted(frame_ids, ids)
        images[season] = to_unit_float(frames[rows])
    log(_summary("nordland_videos", ids, seasons, root))
    return Route(ids, images)


# --------------------------------------------------------------------------------------------
# checks and listing


def _check_seasons(seasons: Sequence[str]) -> tuple[str, ...]:
    if isinstance(seasons, str):
        seasons = [seasons]
    seasons = tuple(dict.fromkeys(seasons))
    if not seasons:
        raise UserError("no season to read: set data.seasons=[summer,fall] or similar")
    for season in seasons:
        if not isinstance(season, str) or season in ("", ".", "..") or Path(season).name != season:
            raise UserError(
                f"season {season!r} is not a plain folder name: set data.seasons to names "
                f"like spring, summer, fall, winter"
            )
    return seasons


def _check_step(frame_step: int) -> None:
    if isinstance(frame_step, bool) or not isinstance(frame_step, (int, np.integer)):
        raise UserError(f"data.frame_step={frame_step!r} is not an integer: set it to 1 or more")
    if frame_step < 1:
        raise UserError(f"data.frame_step={frame_step} keeps no frame: set it to 1 or more")


def _folders_hint(seasons: Sequence[str]) -> str:
    return " ".join(f"{s}/" for s in seasons)


def _check_root(root: PathLike, holding: str) -> Path:
    path = Path(root).expanduser()
    fix = f"set data.root=PATH to {holding}"
    if not path.exists():
        raise UserError(f"data root {path} does not exist: {fix}")
    if not path.is_dir():
        raise UserError(f"data root {path} is not a directory: {fix}")
    if not any(path.iterdir()):
        raise UserError(f"data root {path} is empty: {fix}")
    return path


def _season_dir(root: Path, season: str, seasons: Sequence[str]) -> Path:
    folder = root / season
    if folder.is_dir():
        return folder
    present = sorted(p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
    found = ", ".join(present) if present else "no folders"
    raise UserError(
        f"season folder {folder} is missing ({root} holds {found}): set data.root to the folder "
        f"holding {_folders_hint(seasons)} or data.seasons to the seasons it holds"
    )


def _release_id(folder: Path, name: str) -> int | None:
    m = RELEASE_NAME.match(name)
    return int(m.group(1)) if m else None


def _folder_id(folder: Path, name: str) -> int | None:
    if not name.lower().endswith(IMAGE_EXTENSIONS):
        return None
    frame = frame_id_from_name(name)
    if frame is None:
        raise UserError(
            f"image {folder / name} has no number in its name, so its place on the route is "
            f"unknown: rename it (e.g. frame_00017.png) or move it out of {folder}"
        )
    return frame


def _index_files(
    folder: Path, season: str, *, match: Callable[[str], int | None], empty_hint: str
) -> dict[int, Path]:
    """frame id -> file, in increasing frame id order; names ``match`` returns None for skip."""
    found: dict[int, Path] = {}
    with os.scandir(folder) as entries:
        for entry in entries:
            # ._name files are macOS metadata next to the real images, not images.
            if entry.name.startswith("."):
                continue
            frame = match(entry.name)
            if frame is None or not is_image_file(entry):
                continue
            if frame in found:
                first, second = sorted([found[frame].name, entry.name])
                raise UserError(
                    f"season {season}: {folder / first} and {folder / second} both claim frame "
                    f"{frame}: keep one of them"
                )
            found[frame] = Path(entry.path)
    if not found:
        raise UserError(f"season folder {folder} holds no images: {empty_hint}")
    return dict(sorted(found.items()))


# --------------------------------------------------------------------------------------------
# alignment of seasons, frame list, frame step


def _align(
    available: dict[str, np.ndarray],
    frame_list: PathLike | None,
    frame_step: int,
    log: Log,
    frame_range: Sequence[int] | None = None,
) -> np.ndarray:
    """The sorted frame ids to read: listed (if a list), common to all seasons, within
    ``frame_range`` (first and last id kept, if given), every step-th. Only the listed
    frames inside ``frame_range`` need to be in the data."""
    available = {s: np.unique(np.asarray(ids, dtype=np.int64)) for s, ids in available.items()}
    if frame_list is not None:
        wanted = parse_frame_list(frame_list)
        if frame_range is not None:
            wanted = _within(
                wanted,
                frame_range,
                f"the frames listed in {frame_list}",
                "choose a range inside them, or set data.frame_list=null to read every frame",
            )
        missing = {s: np.setdiff1d(wanted, ids, assume_unique=True) for s, ids in available.items()}
        if any(m.size for m in missing.values()):
            absent = reduce(np.union1d, missing.values())
            first = ", ".join(str(int(i)) for i in absent[:5])
            per_season = ", ".join(f"{s} {m.size:,}" for s, m in missing.items() if m.size)
            fix = (
                "point data.root at the whole 64x32 release, set data.frame_range to the "
                "frames it holds, or set data.frame_list=null to read every frame"
                if is_built_in(frame_list)
                else "remove them from the list or point data.root at data that holds them"
            )
            raise UserError(
                f"frame list {frame_list} names {absent.size:,} frames absent from the data "
                f"({per_season}; first: {first}): {fix}"
            )
        available = {s: wanted for s in available}
    common = reduce(np.intersect1d, available.values())
    if common.size == 0:
        spans = ", ".join(f"{s} {ids[0]}..{ids[-1]} ({ids.size:,})" for s, ids in available.items())
        raise UserError(
            f"seasons share no frame id ({spans}): every season must hold the same places "
            f"under the same frame numbers; check data.root and data.seasons"
        )
    lost = {s: ids.size - common.size for s, ids in available.items()}
    if any(lost.values()):
        dropped = ", ".join(f"{s} {n:,}" for s, n in lost.items())
        log(
            f"seasons hold different frames: keeping the {common.size:,} common to all; "
            f"frames dropped per season: {dropped}"
        )
    if frame_range is not None:
        common = _within(common, frame_range, "the frames")
    return common[::frame_step]


def _within(
    ids: np.ndarray, frame_range: Sequence[int], what: str, fix: str = "choose a range inside them"
) -> np.ndarray:
    """The sorted ``ids`` inside ``frame_range`` (inclusive); none is a UserError."""
    first, last = (int(v) for v in frame_range)
    kept = ids[(ids >= first) & (ids <= last)]
    if kept.size == 0:
        raise UserError(
            f"data.frame_range=[{first},{last}] keeps none of {what} {ids[0]}..{ids[-1]}: {fix}"
        )
    return kept


def _summary(source: str, ids: np.ndarray, seasons: Sequence[str], root: Path) -> str:
    return (
        f"{source}: {ids.size:,} frames x {len(seasons)} seasons ({', '.join(seasons)}), "
        f"frames {ids[0]}..{ids[-1]}, from {root}"
    )
