"""Reading image files as the suite's frames: (N, 32, 64) float32 grey in [0, 1].

Every reader of image folders (Nordland's release, aligned ``folders``, VPR-Bench and
positions benchmarks) goes through ``read_images``: each file's size is read from its header
first and refused over ``data.max_pixels``; colour is converted to grey and counted; any
size is resized with area interpolation (or refused, for the fixed-size release). An entry
that cannot be opened (a link loop, a dangling link, no permission) is one line.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

import cv2
import numpy as np

from vpr_jax import host_arrays
from vpr_jax.data.image_header import image_size
from vpr_jax.errors import UserError
from vpr_jax.progress import Log, track
from vpr_jax.shapes import IMAGE_SHAPE, MAX_PIXELS

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")
_H, _W = IMAGE_SHAPE
_SIZE_WH = (_W, _H)  # cv2 takes (width, height)


def is_image_file(entry: os.DirEntry) -> bool:
    """Whether a directory entry named like a frame is a file to read; a symbolic link
    that loops or points nowhere is refused (it is a frame the user meant to have)."""
    try:
        if entry.is_file():
            return True
        if entry.is_symlink():
            os.stat(entry.path)
    except OSError as err:
        if entry.is_symlink():
            what = "loops" if err.errno == errno.ELOOP else "points to a missing file"
            raise UserError(
                f"image {entry.path} is a symbolic link that {what} "
                f"({os.readlink(entry.path)}): fix the link or remove it"
            ) from None
        raise UserError(
            f"image {entry.path} cannot be read ({err.strerror}): check that it "
            "exists and that you may read it"
        ) from None
    return False


def check_pixels(what: str, width: int, height: int, max_pixels: int) -> None:
    if width * height > max_pixels:
        raise UserError(
            f"{what} is {width:,} x {height:,} pixels, over data.max_pixels="
            f"{max_pixels:,}: shrink it (the suite reads every frame as 64x32) or "
            "raise data.max_pixels if this is meant"
        )


def read_images(
    paths: list[Path], season: str, *, resize: bool, max_pixels: int = MAX_PIXELS
) -> tuple[np.ndarray, int]:
    """(N, 32, 64) float32 in [0, 1] and how many of the files were colour. Each file's
    size is read from its header first (``image_header``): an image over ``max_pixels``
    is refused before it is decoded."""
    out = host_arrays.empty((len(paths), _H, _W))  # JAX reads it in place
    colour = 0
    for i, path in enumerate(track(paths, f"reading {season}", total=len(paths))):
        try:
            size = image_size(path)
        except OSError as err:
            raise UserError(
                f"image {path} cannot be read ({err.strerror}): check that it "
                "exists and that you may read it"
            ) from None
        if size is not None:
            check_pixels(f"image {path}", *size, max_pixels)
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise UserError(_unreadable(path))
        h, w = img.shape[:2]
        if not resize and (h, w) != IMAGE_SHAPE:
            raise UserError(
                f"image {path} is {w}x{h}, the 64x32 release reader needs exactly 64 wide x 32 "
                f"high: set data.source=folders to resize images of any size"
            )
        gray, was_colour = _gray(img, path)
        colour += was_colour
        gray = to_unit_float(gray)
        if (h, w) != IMAGE_SHAPE:
            gray = cv2.resize(gray, _SIZE_WH, interpolation=cv2.INTER_AREA)
        out[i] = gray
    if resize:
        np.clip(out, 0.0, 1.0, out=out)
    return out, colour


def _unreadable(path: Path) -> str:
    try:
        size = path.stat().st_size
    except OSError:
        size = None
    if size == 0:
        return f"image {path} is empty (0 bytes): re-copy or re-extract it, or delete it"
    return (
        f"image {path} cannot be read (corrupt, truncated, not an image or not readable): "
        f"re-copy or re-extract it, or delete it"
    )


def _gray(img: np.ndarray, path: Path) -> tuple[np.ndarray, bool]:
    """Single-channel image and whether the input was colour (BGR / BGRA)."""
    if img.ndim == 2:
        return img, False
    channels = img.shape[2]
    if channels == 1:
        return img[..., 0], False
    if channels == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), True
    if channels == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY), True
    raise UserError(f"image {path} has {channels} channels: save it as grayscale or RGB")


def to_unit_float(img: np.ndarray) -> np.ndarray:
    """uint8 / uint16 / float image -> float32 in [0, 1]."""
    out = host_arrays.empty(img.shape)  # JAX reads it in place
    if img.dtype == np.uint8:
        return np.divide(img, np.float32(255), out=out, dtype=np.float32)
    if img.dtype == np.uint16:
        return np.divide(img, np.float32(65535), out=out, dtype=np.float32)
    return np.clip(img, 0.0, 1.0, out=out, dtype=np.float32)


def note_colour(colour: dict[str, int], log: Log) -> None:
    if any(colour.values()):
        where = ", ".join(f"{s} {n:,}" for s, n in colour.items() if n)
        log(f"converted colour images to grayscale ({where})")


READ_EXTENSIONS = (*IMAGE_EXTENSIONS, ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp")


def relative_names(paths: list[Path], root: Path) -> np.ndarray:
    """(N,) the files' paths relative to ``root`` (``data.root``), as ``/``-separated text:
    how exported retrieval lists name the images."""
    return np.array([p.relative_to(root).as_posix() for p in paths], dtype=object)


def list_images(folder: Path, what: str) -> list[Path]:
    """The image files in ``folder``, sorted by file name (Python's ``sorted``, as
    VPR-Bench lists them); hidden files and other extensions are left out."""
    with os.scandir(folder) as entries:
        found = sorted(
            (entry.name, Path(entry.path))
            for entry in entries
            if not entry.name.startswith(".")
            and entry.name.lower().endswith(READ_EXTENSIONS)
            and is_image_file(entry)
        )
    if not found:
        raise UserError(
            f"{folder} holds no images: put {what} there as {', '.join(READ_EXTENSIONS)} files"
        )
    return [path for _, path in found]
