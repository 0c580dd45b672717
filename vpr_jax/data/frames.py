"""Frame numbers: parse them from file names and read frame-list files.

A frame list is a text file with one entry a line, in any mix of

- an integer frame id: ``202``
- an inclusive range: ``202-35582``
- an image file name (a path is fine, the last integer of its name is the id):
  ``images-00202.png``

Blank lines and ``#`` comments (whole line or trailing) are ignored.

A list shipped with the package is named instead of a path (:data:`BUILT_IN_LISTS`):
``nordland_clean`` is the published clean Nordland list (``lists/nordland_clean.txt``, its
source in its header).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from vpr_jax.errors import UserError

_INT = re.compile(r"\d+")
_NUMBER_LINE = re.compile(r"^\d+$")
_RANGE_LINE = re.compile(r"^(\d+)\s*-\s*(\d+)$")

# Frame lists shipped in lists/ (data.frame_list=NAME reads lists/NAME.txt).
BUILT_IN_LISTS = ("nordland_clean",)
LIST_DIR = Path(__file__).resolve().parent / "lists"

# A list this long is a typo (e.g. "0-999999999"), not a route: Nordland has ~35,768 frames.
MAX_LISTED_FRAMES = 10_000_000


def frame_id_from_name(name: str | os.PathLike) -> int | None:
    """The last integer in a file name without its extension, or None when there is none.

    ``images-00202.png`` -> 202, ``frame_2.jpg`` -> 2, ``cam0_000017.png`` -> 17.
    """
    stem = Path(name).stem
    numbers = _INT.findall(stem)
    return int(numbers[-1]) if numbers else None


def is_built_in(frame_list: str | os.PathLike) -> bool:
    """Whether ``frame_list`` names a list shipped with the package, not a file (a Path
    object is always a file)."""
    return isinstance(frame_list, str) and frame_list in BUILT_IN_LISTS


def frame_list_path(frame_list: str | os.PathLike) -> Path:
    """The file a ``data.frame_list`` value names: a built-in list's name is its copy in
    :data:`LIST_DIR` (``./nordland_clean`` is a file of that name), anything else a path."""
    if is_built_in(frame_list):
        return LIST_DIR / f"{frame_list}.txt"
    return Path(frame_list)


def parse_frame_list(path: str | os.PathLike) -> np.ndarray:
    """Read a frame-list file, or a built-in list by name, into sorted unique frame ids,
    shape (K,) int64."""
    path = frame_list_path(path)
    fix = (
        "set data.frame_list=PATH to a text file of frame ids, ranges like 202-35582 or "
        f"names, or to a built-in list ({', '.join(BUILT_IN_LISTS)})"
    )
    if not path.exists():
        raise UserError(f"frame list {path} does not exist: {fix}")
    if not path.is_file():
        raise UserError(f"frame list {path} is not a file: {fix}")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as err:
        raise UserError(f"frame list {path} cannot be read ({err}): {fix}") from None

    singles: list[int] = []
    ranges: list[tuple[int, int]] = []
    total = 0
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        if _NUMBER_LINE.match(line):
            singles.append(int(line))
            total += 1
        elif m := _RANGE_LINE.match(line):
            lo, hi = int(m.group(1)), int(m.group(2))
            if lo > hi:
                raise UserError(
                    f"frame list {path} line {lineno}: range {line!r} runs backwards: "
                    f"write it as {hi}-{lo}"
                )
            ranges.append((lo, hi))
            total += hi - lo + 1
        else:
            frame = frame_id_from_name(line.replace("\\", "/").rsplit("/", 1)[-1])
            if frame is None:
                raise UserError(
                    f"frame list {path} line {lineno}: {line!r} is not a frame number, a range "
                    f"like 202-35582 or an image file name like images-00202.png: fix that line"
                )
            singles.append(frame)
            total += 1
        if total > MAX_LISTED_FRAMES:
            raise UserError(
                f"frame list {path} names more than {MAX_LISTED_FRAMES:,} frames "
                f"(line {lineno}: {line!r}): check the ranges in it"
            )

    parts = [np.asarray(singles, dtype=np.int64)]
    parts += [np.arange(lo, hi + 1, dtype=np.int64) for lo, hi in ranges]
    frames = np.unique(np.concatenate(parts))
    if frames.size == 0:
        raise UserError(f"frame list {path} names no frame: {fix}")
    return frames
