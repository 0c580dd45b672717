"""Nordland season videos: decoding one at one frame per second of video time into (32, 64)
uint8 grey frames, and the on-disk ``.npz`` cache that spares a second run the decoding.

``find_video`` picks a season's file in the data root; ``video_frames`` gives its frames and
frame ids (id = second), from the cache or the video. ``vpr_jax.data.nordland.read_videos``
aligns the seasons and applies the frame list and step.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from vpr_jax.data.images import check_pixels, to_unit_float
from vpr_jax.data.route import IMAGE_SHAPE
from vpr_jax.errors import UserError
from vpr_jax.files import atomic_open
from vpr_jax.progress import Log, interactive, track
from vpr_jax.shapes import MAX_PIXELS
from vpr_jax.untrusted import check_npy_fits

VIDEO_EXTENSIONS = tuple(".mp4 .avi .mkv .mov .webm .m4v .mpg .mpeg .wmv .flv .ts".split())

_H, _W = IMAGE_SHAPE
_SIZE_WH = (_W, _H)  # cv2 takes (width, height)
# Video timestamps are milliseconds from a rational time base; a frame meant to sit exactly on
# a second may come back a hair early (1999.9999999 ms).
_TIME_EPS_S = 1e-6
CACHE_VERSION = 1
LOG_EVERY_VIDEO_S = 3600  # a plain progress line per hour of video when not on a terminal


def find_video(root: Path, season: str) -> Path:
    """The one video in ``root`` whose name contains ``season`` (any case)."""
    files = [p for p in root.iterdir() if p.is_file() and not p.name.startswith(".")]
    videos = [p for p in files if p.suffix.lower() in VIDEO_EXTENSIONS]
    hits = sorted(p for p in videos if season.lower() in p.name.lower())
    if len(hits) == 1:
        return hits[0]
    if not hits:
        present = ", ".join(sorted(p.name for p in videos)) or "no video files"
        raise UserError(
            f"no video for season {season} in {root} ({present}): name its video so the name "
            f"contains {season!r} (e.g. {season}.mp4) or set data.root to its folder"
        )
    names = ", ".join(p.name for p in hits)
    raise UserError(
        f"several videos in {root} name season {season} ({names}): keep exactly one of them there"
    )


def video_frames(
    video: Path, season: str, cache_dir: Path | None, log: Log, max_pixels: int = MAX_PIXELS
) -> tuple[np.ndarray, np.ndarray]:
    """(frames (N, 32, 64) uint8 or float, frame ids (N,) int64) from the cache or the video."""
    cache = _cache_path(video, cache_dir) if cache_dir is not None else None
    if cache is not None and cache.exists():
        return _load_cache(cache)
    start = time.perf_counter()
    frames, ids = _decode_video(video, season, log, max_pixels)
    took = time.perf_counter() - start
    note = ""
    if cache is not None:
        try:
            _write_cache(cache, frames, ids)
            note = f", cached in {cache}"
        except OSError as err:
            note = f"; could not write the cache {cache} ({err}), the next run decodes again"
    log(f"{season}: {ids.size:,} frames (1 per second) from {video} in {took:.1f} s{note}")
    return frames, ids


def _cache_path(video: Path, cache_dir: Path) -> Path:
    absolute = video.resolve()
    stat = absolute.stat()
    key = json.dumps(
        [str(absolute), stat.st_size, stat.st_mtime_ns, list(IMAGE_SHAPE), CACHE_VERSION]
    )
    digest = hashlib.sha256(key.encode()).hexdigest()[:16]
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", video.stem)[:60]
    return cache_dir / f"{stem}-{_W}x{_H}-{digest}.npz"


def _write_cache(path: Path, frames: np.ndarray, ids: np.ndarray) -> None:
    with atomic_open(path, "wb") as f:
        np.savez(f, frames=frames, frame_ids=ids)


def _load_cache(path: Path) -> tuple[np.ndarray, np.ndarray]:
    fix = "delete it and run again to rebuild it from the video"
    try:
        check_npy_fits(path, f"video cache {path}", fix)  # nothing claimed past its bytes
        with np.load(path, allow_pickle=False) as data:
            if set(data.files) != {"frames", "frame_ids"}:
                raise UserError(
                    f"video cache {path} holds {sorted(data.files)}, not frames and frame_ids: "
                    f"{fix}"
                )
            frames, ids = data["frames"], data["frame_ids"]
    except UserError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as err:
        raise UserError(f"video cache {path} cannot be read ({err}): {fix}") from None
    if frames.ndim != 3 or frames.shape[1:] != IMAGE_SHAPE or frames.shape[0] == 0:
        raise UserError(
            f"video cache {path} holds frames of shape {frames.shape}, not (N, {_H}, {_W}): {fix}"
        )
    if ids.shape != frames.shape[:1] or not np.issubdtype(ids.dtype, np.integer):
        raise UserError(
            f"video cache {path} holds frame ids of shape {ids.shape} ({ids.dtype}) for "
            f"{frames.shape[0]} frames: {fix}"
        )
    if np.any(np.diff(ids) <= 0):
        raise UserError(f"video cache {path} holds frame ids that do not increase: {fix}")
    if frames.dtype != np.uint8:
        if not np.issubdtype(frames.dtype, np.floating):
            raise UserError(f"video cache {path} holds {frames.dtype} frames, not uint8: {fix}")
        if not np.all(np.isfinite(frames)):
            raise UserError(f"video cache {path} holds NaN or Inf pixels: {fix}")
        if frames.min() < 0 or frames.max() > 1:
            raise UserError(f"video cache {path} holds pixels outside [0, 1]: {fix}")
    return frames, ids.astype(np.int64)


def _grabbed(cap: cv2.VideoCapture) -> Iterator[int]:
    k = 0
    while cap.grab():
        yield k
        k += 1


def _open_video(video: Path, max_pixels: int) -> tuple[cv2.VideoCapture, float, int | None]:
    """The opened video, its frame rate (0: unknown) and its frame count (None: unknown)."""
    cap = cv2.VideoCapture(str(video))
    try:
        if not cap.isOpened():
            raise UserError(
                f"video {video} cannot be opened by OpenCV (corrupt, truncated or an unknown "
                f"codec): re-download it or re-encode it, e.g. ffmpeg -i IN -c:v libx264 OUT.mp4"
            )
        width, height = cap.get(cv2.CAP_PROP_FRAME_WIDTH), cap.get(cv2.CAP_PROP_FRAME_HEIGHT)
        if math.isfinite(width) and math.isfinite(height):
            check_pixels(f"a frame of video {video}", int(width), int(height), max_pixels)
    except BaseException:
        cap.release()
        raise
    fps = cap.get(cv2.CAP_PROP_FPS)
    count = cap.get(cv2.CAP_PROP_FRAME_COUNT)
    fps = fps if math.isfinite(fps) and fps > 0 else 0.0
    return cap, fps, int(count) if math.isfinite(count) and count > 0 else None


def _timestamps(
    cap: cv2.VideoCapture, video: Path, season: str, fps: float, log: Log
) -> Iterator[tuple[int, float]]:
    """(frame number, seconds of video time) of every frame grabbed: the stream's own
    timestamps while they increase, frame number / fps from the first one that does not."""
    by_stream, prev_ms = True, -math.inf
    for k in _grabbed(cap):
        if by_stream:
            ms = cap.get(cv2.CAP_PROP_POS_MSEC)
            if math.isfinite(ms) and ms >= 0 and (ms > prev_ms or (k == 0 and ms == 0)):
                prev_ms = ms
                yield k, ms / 1000.0
                continue
            by_stream = False
            if fps == 0:
                raise UserError(
                    f"video {video} has neither usable timestamps nor a frame rate: "
                    f"re-encode it, e.g. ffmpeg -i IN -c:v libx264 -r 25 OUT.mp4"
                )
            log(
                f"{season}: {video.name} has no usable timestamps from frame {k} on: "
                f"timing frames as frame number / {fps:g} fps"
            )
        yield k, k / fps


def _decode_video(
    video: Path, season: str, log: Log, max_pixels: int = MAX_PIXELS
) -> tuple[np.ndarray, np.ndarray]:
    """Sample one frame per second of video time: (frames (N, 32, 64) uint8, ids 0..N-1)."""
    cap, fps, total = _open_video(video, max_pixels)
    frames: list[np.ndarray] = []
    next_second = 0  # the frame id (= second of video time) still to fill
    n_decoded, seconds = 0, 0.0
    next_log, quiet = LOG_EVERY_VIDEO_S, interactive()
    try:
        timed = _timestamps(cap, video, season, fps, log)
        for k, seconds in track(timed, f"decoding {season} video", total=total):
            n_decoded = k + 1
            if seconds + _TIME_EPS_S < next_second:
                continue
            ok, img = cap.retrieve()
            if not ok or img is None:
                raise UserError(
                    f"video {video}: frame {k} ({seconds:.2f} s) cannot be decoded: "
                    f"re-download or re-encode the video"
                )
            small = _small_gray(img)
            # A gap in the stream longer than a second repeats the frame after it.
            while seconds + _TIME_EPS_S >= next_second:
                frames.append(small)
                next_second += 1
            if not quiet and seconds >= next_log:
                log(f"{season}: {int(seconds):,} s of video decoded")
                next_log += LOG_EVERY_VIDEO_S
    finally:
        cap.release()
    if n_decoded == 0:
        raise UserError(
            f"video {video} holds no frame OpenCV can decode: re-download or re-encode it"
        )
    duration = seconds + (1.0 / fps if fps else 0.0)
    if duration + _TIME_EPS_S < 1.0:
        raise UserError(
            f"video {video} lasts only {duration:.2f} s, less than the one second a frame is "
            f"sampled from: use the full season video"
        )
    return np.stack(frames), np.arange(len(frames), dtype=np.int64)


def _small_gray(img: np.ndarray) -> np.ndarray:
    """A decoded frame -> (32, 64) uint8 grayscale, area-resized."""
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
    elif img.ndim == 3:
        img = img[..., 0]
    if img.dtype != np.uint8:
        img = np.clip(np.rint(to_unit_float(img) * 255), 0, 255).astype(np.uint8)
    return cv2.resize(img, _SIZE_WH, interpolation=cv2.INTER_AREA)
