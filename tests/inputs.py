"""What the tests write to disk or build as input: Nordland's image release, season videos,
folders of frames, random matching cases. Shared by the test modules that need them."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from pathlib import Path

import cv2
import numpy as np

from vpr_jax.data.route import IMAGE_SHAPE


def write_release(
    root: Path, frames: Mapping[str, Iterable[np.ndarray]], ids: Iterable[int] | None = None
) -> Path:
    """Nordland's 64x32 release layout, ``ROOT/<season>/images-%05d.png``, from each season's
    uint8 images, numbered ``ids`` (default 1, 2, ...). Returns ``root``."""
    for season, images in frames.items():
        folder = Path(root) / season
        folder.mkdir(parents=True, exist_ok=True)
        images = list(images)
        numbers = range(1, len(images) + 1) if ids is None else ids
        for i, img in zip(numbers, images, strict=True):
            assert cv2.imwrite(str(folder / f"images-{i:05d}.png"), img)
    return Path(root)


def frame_image(season: str, frame: int) -> np.ndarray:
    """A deterministic (32, 64) uint8 image for (season, frame)."""
    seed = (sum(map(ord, season)) * 100_003 + frame) % (2**32)
    return np.random.default_rng(seed).integers(0, 256, IMAGE_SHAPE, dtype=np.uint8)


# A sweep of raw pixels over ``write_folders``'s frames: the smallest run that reads files.
FOLDERS = [
    "data.source=folders",
    "split.n_train=30",
    "split.n_test=10",
    "split.gap=2",
    "methods=[raw]",
    "season_pairs=summer-winter",
    "data.seasons=[summer,winter]",
]


def write_folders(root: Path, n: int = 50) -> Path:
    """``ROOT/{summer,winter}/frame_%04d.png``: ``n`` random (32, 64) grey frames a season,
    the layout ``data.source=folders`` reads. Returns ``root``."""
    rng = np.random.default_rng(1)
    for season in ("summer", "winter"):
        (root / season).mkdir(parents=True)
        for i in range(n):
            image = rng.integers(0, 256, (32, 64), np.uint8)
            cv2.imwrite(str(root / season / f"frame_{i:04d}.png"), image)
    return root


# season videos

SRC_H, SRC_W = 96, 160  # 2.5x wider, 3x higher than 64x32: a non-trivial area resize


def second_level(second: int) -> int:
    return 40 + 50 * second


def source_frame(k: int, fps: float) -> np.ndarray:
    """Left half: brightness of the frame's second; right half: 0 for a second's first frame,
    bright for any later one; bottom rows: 1-pixel stripes that only area resizing averages."""
    second = math.floor(k / fps + 1e-9)
    first_of_second = math.ceil(second * fps - 1e-9)
    img = np.zeros((SRC_H, SRC_W, 3), np.uint8)
    img[:, : SRC_W // 2] = second_level(second)
    img[:, SRC_W // 2 :] = 0 if k == first_of_second else 160 + 3 * (k - first_of_second)
    img[2 * SRC_H // 3 :, 0::2] = 255
    img[2 * SRC_H // 3 :, 1::2] = 0
    return img


def write_video(path, fps: float, n_frames: int) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (SRC_W, SRC_H))
    assert writer.isOpened()
    for k in range(n_frames):
        writer.write(source_frame(k, fps))
    writer.release()


def random_case(seed, nq=40, ndb=60, ties=False, all_match=False):
    """Frame ids along a route, unsorted db ids, similarity peaked near the true frame."""
    rng = np.random.default_rng(seed)
    route = 120
    db_ids = rng.choice(route, ndb, replace=False)  # unsorted, with gaps
    if all_match:
        query_ids = rng.choice(db_ids, nq, replace=False)
    else:
        query_ids = rng.choice(route, nq, replace=False)  # some land in gaps
    dist = np.abs(query_ids[:, None] - db_ids[None, :])
    sim = np.exp(-dist / 2.0) + rng.normal(0.0, 0.35, size=(nq, ndb))
    if ties:
        sim = np.round(sim, 1)
    return sim, query_ids, db_ids


N_PLACES = 120  # places of write_vpr_bench's route


def u8(image: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(image * 255), 0, 255).astype(np.uint8)


def write_vpr_bench(root: Path, route, *, drop_rows=(), skew=0) -> tuple[list, list]:
    """``root/ref`` (summer, 64x32 grey PNGs named so that string order is not numeric
    order), ``root/query`` (every 2nd fall frame, colour JPEG-free PNGs at 128x64) and
    ``ground_truth_new.npy``: query n's references are the frames within +-1 of its place
    (``skew`` shifts them: wrong on purpose). Returns the (ref, query) file names in
    VPR-Bench's order and the ground-truth rows written."""
    (root / "ref").mkdir(parents=True)
    (root / "query").mkdir()
    for i in range(N_PLACES):
        cv2.imwrite(str(root / "ref" / f"r{i}.png"), u8(route.images["summer"][i]))
    places = list(range(0, N_PLACES, 2))
    for n, i in enumerate(places):
        big = cv2.resize(u8(route.images["fall"][i]), (128, 64), interpolation=cv2.INTER_NEAREST)
        cv2.imwrite(str(root / "query" / f"q{n:03d}.png"), cv2.cvtColor(big, cv2.COLOR_GRAY2BGR))
    refs = sorted(f"r{i}.png" for i in range(N_PLACES))  # r0, r1, r10, r100, ...
    position = {name: k for k, name in enumerate(refs)}
    rows = []
    for n, i in enumerate(places):
        if n in drop_rows:
            continue
        near = [
            position[f"r{j}.png"]
            for j in (i - 1 + skew, i + skew, i + 1 + skew)
            if 0 <= j < N_PLACES
        ]
        rows.append((n, near))
    table = np.empty(len(rows), dtype=object)
    for r, row in enumerate(rows):
        table[r] = row
    np.save(root / "ground_truth_new.npy", table, allow_pickle=True)
    return refs, [f"q{n:03d}.png" for n in range(len(places))], rows


def read_grey(path: Path) -> np.ndarray:
    """The reference reader: any image as 64x32 grey in [0, 1] (area interpolation)."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    image = image.astype(np.float32) / np.float32(255)
    if image.shape != (32, 64):
        image = cv2.resize(image, (64, 32), interpolation=cv2.INTER_AREA)
    return image.reshape(-1).astype(np.float64)
