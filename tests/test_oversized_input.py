"""Images and video frames too large to decode are refused from their headers, in one line,
before any memory is spent on them."""

import struct
import zlib

import cv2
import numpy as np
import pytest

from tests.conftest import assert_one_line_error, run_here
from tests.inputs import FOLDERS, SRC_H, SRC_W, write_folders, write_video
from vpr_jax.data.image_header import image_size


@pytest.mark.parametrize("ext", [".png", ".jpg", ".bmp"])
@pytest.mark.parametrize("shape", [(32, 64), (77, 131), (480, 640)])
def test_header_size_equals_the_decoded_size(tmp_path, ext, shape):
    path = tmp_path / f"image{ext}"
    cv2.imwrite(str(path), np.random.default_rng(0).integers(0, 256, (*shape, 3), np.uint8))
    h, w = cv2.imread(str(path)).shape[:2]
    assert image_size(path) == (w, h)


def _huge_png(path, width: int, height: int) -> None:
    """A PNG whose header (with a valid CRC) claims width x height grey pixels; its data
    are one row of zeros: decoding it would allocate the full image."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\x00" * (width + 1)))
        + chunk(b"IEND", b"")
    )


def test_a_30000_square_png_is_refused_from_its_header(tmp_path):
    root = write_folders(tmp_path / "data")
    bomb = root / "winter" / "frame_0007.png"
    _huge_png(bomb, 30_000, 30_000)
    assert bomb.stat().st_size < 100_000 and image_size(bomb) == (30_000, 30_000)
    proc = run_here(*FOLDERS, f"data.root={root}", f"logdir={tmp_path / 'runs'}")
    assert_one_line_error(proc, str(bomb), "30,000 x 30,000", "data.max_pixels")
    assert not (tmp_path / "runs").exists()


def test_max_pixels_applies_to_jpeg_and_to_video_frames(tmp_path):
    root = write_folders(tmp_path / "data")
    large = root / "summer" / "frame_0003.jpg"
    (root / "summer" / "frame_0003.png").unlink()
    cv2.imwrite(str(large), np.zeros((200, 300, 3), np.uint8))
    proc = run_here(
        *FOLDERS, f"data.root={root}", "data.max_pixels=50000", f"logdir={tmp_path / 'runs'}"
    )
    assert_one_line_error(proc, str(large), "300 x 200", "data.max_pixels=50,000")
    videos = tmp_path / "videos"
    videos.mkdir()
    for season in ("summer", "winter"):
        write_video(videos / f"{season}.avi", 5.0, 10)
    proc = run_here(
        "data.source=nordland_videos",
        f"data.root={videos}",
        "data.seasons=[summer,winter]",
        f"data.max_pixels={SRC_W * SRC_H - 1}",
        f"data.cache_dir={tmp_path / 'cache'}",
        f"logdir={tmp_path / 'runs'}",
    )
    assert_one_line_error(proc, "video", f"{SRC_W} x {SRC_H}", "data.max_pixels")
