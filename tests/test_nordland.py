"""Real-data readers on tiny data written into tmp_path: release PNGs, videos, any folders."""

from __future__ import annotations

import math
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.conftest import LogLines
from tests.inputs import frame_image, second_level, source_frame, write_release, write_video
from vpr_jax.command_line import parse_config
from vpr_jax.data import load_data, nordland
from vpr_jax.data.frames import LIST_DIR, frame_id_from_name, frame_list_path, parse_frame_list
from vpr_jax.data.nordland import load_nordland, read_folders, read_image_release, read_videos
from vpr_jax.data.route import IMAGE_SHAPE
from vpr_jax.errors import UserError

H, W = IMAGE_SHAPE


# --------------------------------------------------------------------------------------------
# helpers


def make_release(root, season: str, frames) -> None:
    write_release(root, {season: [frame_image(season, f) for f in frames]}, frames)


def unit(img: np.ndarray) -> np.ndarray:
    return img / np.float32(255)


# --------------------------------------------------------------------------------------------
# the 64x32 image release


def test_release_reads_frames_as_unit_floats(tmp_path):
    for season in ("spring", "summer"):
        make_release(tmp_path, season, range(1, 7))
    log = LogLines()
    route = read_image_release(tmp_path, ["spring", "summer"], log=log)
    assert route.frame_ids.dtype == np.int64
    np.testing.assert_array_equal(route.frame_ids, np.arange(1, 7))
    assert route.seasons == ("spring", "summer")
    for season in ("spring", "summer"):
        images = route.images[season]
        assert images.shape == (6, H, W) and images.dtype == np.float32
        assert 0.0 <= images.min() and images.max() <= 1.0
        for row, frame in enumerate(route.frame_ids):
            np.testing.assert_array_equal(images[row], frame_image(season, frame) / np.float32(255))
    assert not any("colour" in line or "different" in line for line in log)


def test_release_keeps_frame_zero(tmp_path):
    for season in ("fall", "winter"):
        make_release(tmp_path, season, range(0, 4))
    route = read_image_release(tmp_path, ["fall", "winter"], log=LogLines())
    np.testing.assert_array_equal(route.frame_ids, [0, 1, 2, 3])
    np.testing.assert_array_equal(route.images["fall"][0], frame_image("fall", 0) / np.float32(255))


def test_release_gaps_keep_the_intersection_and_report_losses(tmp_path):
    make_release(tmp_path, "spring", [f for f in range(1, 11) if f != 3])
    make_release(tmp_path, "summer", [f for f in range(1, 11) if f not in (7, 8)])
    (tmp_path / "summer" / "notes.txt").write_text("not an image")
    log = LogLines()
    route = read_image_release(tmp_path, ["spring", "summer"], log=log)
    np.testing.assert_array_equal(route.frame_ids, [1, 2, 4, 5, 6, 9, 10])
    lost = [line for line in log if "different frames" in line]
    assert len(lost) == 1
    assert "spring 2" in lost[0] and "summer 1" in lost[0]  # frames each season had
    row = list(route.frame_ids).index(9)  # alignment: row i is frame 9 in both seasons
    for season in ("spring", "summer"):
        np.testing.assert_array_equal(route.images[season][row], unit(frame_image(season, 9)))


def test_release_no_common_frame(tmp_path):
    make_release(tmp_path, "spring", [1, 2])
    make_release(tmp_path, "summer", [3, 4])
    with pytest.raises(UserError, match="share no frame"):
        read_image_release(tmp_path, ["spring", "summer"], log=LogLines())


def test_frame_list_of_names_numbers_and_ranges(tmp_path):
    for season in ("spring", "summer"):
        make_release(tmp_path, season, range(1, 21))
    listing = tmp_path / "frames.txt"
    listing.write_text(
        "# clean frames\n\nimages-00002.png\n5-7   # a range\n"
        "spring/images-00009.png\n12\n 15 - 16\n"
    )
    route = read_image_release(tmp_path, ["spring", "summer"], frame_list=listing, log=LogLines())
    np.testing.assert_array_equal(route.frame_ids, [2, 5, 6, 7, 9, 12, 15, 16])
    np.testing.assert_array_equal(route.images["summer"][4], unit(frame_image("summer", 9)))

    stepped = read_image_release(
        tmp_path, ["spring", "summer"], frame_list=listing, frame_step=3, log=LogLines()
    )
    np.testing.assert_array_equal(stepped.frame_ids, [2, 7, 15])


def test_frame_list_naming_absent_frames_is_an_error(tmp_path):
    for season in ("spring", "summer"):
        make_release(tmp_path, season, range(1, 6))
    listing = tmp_path / "frames.txt"
    listing.write_text("1-3\n40\n41\n")
    with pytest.raises(UserError, match=r"names 2 frames absent .*first: 40, 41"):
        read_image_release(tmp_path, ["spring", "summer"], frame_list=listing, log=LogLines())
    with pytest.raises(UserError, match="does not exist"):
        read_image_release(tmp_path, ["spring"], frame_list=tmp_path / "nope.txt", log=LogLines())


def test_frame_range_narrows_a_list_to_the_frames_the_data_holds(tmp_path):
    for season in ("spring", "summer"):
        make_release(tmp_path, season, range(1, 21))
    listing = tmp_path / "frames.txt"
    listing.write_text("2-4\n9\n40-45\n")  # 40..45 are not in the data
    route = read_image_release(
        tmp_path, ["spring", "summer"], frame_list=listing, frame_range=(1, 20), log=LogLines()
    )
    np.testing.assert_array_equal(route.frame_ids, [2, 3, 4, 9])
    with pytest.raises(UserError, match=r"keeps none of the frames listed in .*frame_list=null"):
        read_image_release(
            tmp_path, ["spring", "summer"], frame_list=listing, frame_range=(5, 8), log=LogLines()
        )
    # The built-in list on data without its frames: the fix names the list's own ways out.
    with pytest.raises(UserError, match=r"frame list nordland_clean names 27,592 frames absent"):
        read_image_release(tmp_path, ["spring"], frame_list="nordland_clean", log=LogLines())
    with pytest.raises(UserError, match=r"keeps none of the frames listed in nordland_clean"):
        read_image_release(
            tmp_path, ["spring"], frame_list="nordland_clean", frame_range=(1, 20), log=LogLines()
        )


def test_the_shipped_clean_list_is_the_published_one():
    """vpr_jax/data/lists/nordland_clean.txt: Patch-NetVLAD's 27,592 frames, 202..35582, in
    182 runs (its header names the source); a path, not the name, reads a file."""
    assert frame_list_path("nordland_clean") == LIST_DIR / "nordland_clean.txt"
    assert frame_list_path("./nordland_clean") == Path("nordland_clean")
    assert frame_list_path(Path("nordland_clean")) == Path("nordland_clean")
    frames = parse_frame_list("nordland_clean")
    assert frames.dtype == np.int64 and frames.size == 27_592
    assert (frames[0], frames[-1]) == (202, 35_582)
    assert np.all(np.diff(frames) > 0)
    assert np.count_nonzero(np.diff(frames) > 1) == 181  # tunnels and stops: 182 ranges
    text = (LIST_DIR / "nordland_clean.txt").read_text()
    assert "QVPR/Patch-NetVLAD" in text and "b07289d4e6e3ccbb9cabad4297bea37a0a33a843" in text


@pytest.mark.timeout(60)
def test_nordland_star_preset_reads_the_published_frames_of_a_whole_release(tmp_path):
    """preset=nordland_star on the release's 35,768 frames a season (blank ones, all the
    same PNG) keeps exactly the shipped list: 27,592 references, every 10th a query. Blank
    frames are constant; the preset keeps them (the list is the selection), so the count
    is the list's whatever the pixels show."""
    ok, png = cv2.imencode(".png", np.zeros(IMAGE_SHAPE, np.uint8))
    assert ok
    root = tmp_path / "release"
    for season in ("summer", "winter"):
        folder = root / season
        folder.mkdir(parents=True)
        # Hard links to one file a season (ext4 allows 65,000 a file): fast to write.
        blank = tmp_path / f"{season}.png"
        blank.write_bytes(png.tobytes())
        for frame in range(1, 35_769):
            os.link(blank, folder / f"images-{frame:05d}.png")
    cfg = parse_config(["preset=nordland_star", f"data.root={root}"])
    assert cfg.data.frame_list == "nordland_clean" and cfg.data.frame_range is None
    assert not cfg.data.drop_constant_frames
    log = LogLines()
    bench = load_data(cfg.data, cfg.seed, log=log)
    listed = parse_frame_list("nordland_clean")
    assert (len(bench.db), len(bench.query)) == (27_592, 2_760)
    np.testing.assert_array_equal(bench.db_ids, listed)
    np.testing.assert_array_equal(bench.query_ids, listed[::10])
    assert (bench.db_name, bench.query_name) == ("winter", "summer")
    assert any("27,592 frames x 2 seasons" in line and "202..35582" in line for line in log)
    assert any("constant frames" in line and "kept" in line for line in log)


def test_frame_list_parsing(tmp_path):
    listing = tmp_path / "l.txt"
    listing.write_text("3\n1-2\n3\n")
    np.testing.assert_array_equal(parse_frame_list(listing), [1, 2, 3])
    listing.write_text("9-4\n")
    with pytest.raises(UserError, match="backwards"):
        parse_frame_list(listing)
    listing.write_text("1\nhello.png\n")
    with pytest.raises(UserError, match="line 2"):
        parse_frame_list(listing)
    listing.write_text("# nothing\n\n")
    with pytest.raises(UserError, match="names no frame"):
        parse_frame_list(listing)
    assert frame_id_from_name("images-00202.png") == 202
    assert frame_id_from_name("cam0_t12_000017.jpg") == 17
    assert frame_id_from_name("frame.png") is None


def test_frame_step_keeps_every_step_th_common_frame(tmp_path):
    for season in ("spring", "summer"):
        make_release(tmp_path, season, range(1, 26))
    route = read_image_release(tmp_path, ["spring", "summer"], frame_step=10, log=LogLines())
    np.testing.assert_array_equal(route.frame_ids, [1, 11, 21])
    np.testing.assert_array_equal(route.images["spring"][2], unit(frame_image("spring", 21)))
    for bad in (0, -1, 1.5):
        with pytest.raises(UserError, match="frame_step"):
            read_image_release(tmp_path, ["spring"], frame_step=bad, log=LogLines())


def test_season_subset_in_the_order_asked(tmp_path):
    for season in ("spring", "summer", "fall", "winter"):
        make_release(tmp_path, season, range(1, 4))
    route = read_image_release(tmp_path, ["winter", "spring"], log=LogLines())
    assert route.seasons == ("winter", "spring")


def test_release_wrong_size_points_to_folders_source(tmp_path):
    make_release(tmp_path, "spring", [1, 2])
    cv2.imwrite(str(tmp_path / "spring" / "images-00003.png"), np.zeros((64, 64), np.uint8))
    with pytest.raises(UserError, match=r"images-00003\.png is 64x64.*data\.source=folders"):
        read_image_release(tmp_path, ["spring"], log=LogLines())


def test_release_corrupt_and_empty_files_are_named(tmp_path):
    make_release(tmp_path, "spring", [1, 2, 3])
    path = tmp_path / "spring" / "images-00002.png"
    path.write_bytes(path.read_bytes()[:40])  # truncated
    with pytest.raises(UserError, match=r"images-00002\.png cannot be read"):
        read_image_release(tmp_path, ["spring"], log=LogLines())
    path.write_bytes(b"")
    with pytest.raises(UserError, match=r"images-00002\.png is empty \(0 bytes\)"):
        read_image_release(tmp_path, ["spring"], log=LogLines())


def test_release_colour_png_becomes_gray_with_one_note(tmp_path):
    make_release(tmp_path, "spring", [1, 2, 3])
    rng = np.random.default_rng(1)
    colour = {f: rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for f in (1, 2)}
    for frame, img in colour.items():
        cv2.imwrite(str(tmp_path / "spring" / f"images-{frame:05d}.png"), img)
    log = LogLines()
    route = read_image_release(tmp_path, ["spring"], log=log)
    for row, frame in enumerate((1, 2)):
        gray = cv2.cvtColor(colour[frame], cv2.COLOR_BGR2GRAY)
        np.testing.assert_array_equal(route.images["spring"][row], gray / np.float32(255))
    notes = [line for line in log if line.startswith("converted colour")]
    assert len(notes) == 1 and "spring 2" in notes[0]


def test_release_path_errors(tmp_path):
    with pytest.raises(UserError, match=r"does not exist: set data\.root="):
        read_image_release(tmp_path / "missing", ["spring"], log=LogLines())
    (tmp_path / "file").write_text("x")
    with pytest.raises(UserError, match="is not a directory"):
        read_image_release(tmp_path / "file", ["spring"], log=LogLines())
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="is empty"):
        read_image_release(tmp_path / "empty", ["spring"], log=LogLines())
    make_release(tmp_path / "data", "summer", [1])
    (tmp_path / "data" / "fall").mkdir()
    with pytest.raises(UserError, match=r"spring is missing \(.* holds fall, summer\)"):
        read_image_release(tmp_path / "data", ["summer", "spring"], log=LogLines())
    with pytest.raises(UserError, match="fall holds no images"):
        read_image_release(tmp_path / "data", ["summer", "fall"], log=LogLines())
    with pytest.raises(UserError, match="no season"):
        read_image_release(tmp_path / "data", [], log=LogLines())


def test_load_nordland_dispatches(tmp_path):
    make_release(tmp_path, "spring", [1, 2])
    route = load_nordland("nordland_images", tmp_path, ["spring"], cache_dir=None, log=LogLines())
    assert len(route) == 2
    route = load_nordland("folders", tmp_path, ["spring"], cache_dir=None, log=LogLines())
    assert len(route) == 2
    with pytest.raises(UserError, match="unknown data source"):
        load_nordland("kitti", tmp_path, ["spring"], cache_dir=None)


# --------------------------------------------------------------------------------------------
# any folders of frames


def test_folders_resize_any_size_and_order_by_number(tmp_path):
    rng = np.random.default_rng(2)
    src = {
        2: rng.integers(0, 256, (64, 128, 3), dtype=np.uint8),  # colour png, 2x
        10: rng.integers(0, 256, (50, 100), dtype=np.uint8),  # gray jpg, odd scale
        1: rng.integers(0, 256, (32, 64, 3), dtype=np.uint8),  # colour jpeg, already 64x32
    }
    names = {2: "frame_2.png", 10: "frame_10.jpg", 1: "frame_1.jpeg"}
    for season in ("summer", "winter"):
        (tmp_path / season).mkdir()
        (tmp_path / season / "readme.txt").write_text("ignored")
        for frame, img in src.items():
            cv2.imwrite(str(tmp_path / season / names[frame]), img)
    log = LogLines()
    route = read_folders(tmp_path, ["summer", "winter"], log=log)
    np.testing.assert_array_equal(route.frame_ids, [1, 2, 10])
    assert route.images["summer"].shape == (3, H, W)
    assert route.images["summer"].dtype == np.float32
    for row, frame in enumerate(route.frame_ids):
        stored = cv2.imread(str(tmp_path / "summer" / names[frame]), cv2.IMREAD_UNCHANGED)
        if stored.ndim == 3:
            stored = cv2.cvtColor(stored, cv2.COLOR_BGR2GRAY)
        want = cv2.resize(stored.astype(np.float32) / 255, (W, H), interpolation=cv2.INTER_AREA)
        np.testing.assert_allclose(route.images["summer"][row], want, atol=1e-6)
    assert any("colour" in line for line in log)


def test_folders_file_without_number_is_an_error(tmp_path):
    (tmp_path / "fall").mkdir()
    cv2.imwrite(str(tmp_path / "fall" / "frame_1.png"), np.zeros((10, 10), np.uint8))
    cv2.imwrite(str(tmp_path / "fall" / "cover.png"), np.zeros((10, 10), np.uint8))
    with pytest.raises(UserError, match=r"cover\.png has no number"):
        read_folders(tmp_path, ["fall"], log=LogLines())


# --------------------------------------------------------------------------------------------
# season videos


def decoded_small(path, k: int) -> np.ndarray:
    """Frame k as OpenCV decodes it, grayscale, area-resized to 64x32 (the expected output)."""
    cap = cv2.VideoCapture(str(path))
    for _ in range(k + 1):
        ok, img = cap.read()
        assert ok
    cap.release()
    gray = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return cv2.resize(gray, (W, H), interpolation=cv2.INTER_AREA)


@pytest.mark.parametrize("fps", [25.0, 7.5])
def test_video_takes_the_first_frame_of_each_second(tmp_path, fps):
    videos = tmp_path / "videos"
    videos.mkdir()
    path = videos / "Nordland_SUMMER.avi"
    write_video(path, fps, round(4 * fps))  # 4 s
    route = read_videos(videos, ["summer"], cache_dir=tmp_path / "cache", log=LogLines())
    np.testing.assert_array_equal(route.frame_ids, [0, 1, 2, 3])
    images = route.images["summer"]
    assert images.shape == (4, H, W) and images.dtype == np.float32
    assert 0.0 <= images.min() and images.max() <= 1.0
    top = images[:, : H // 2]
    for second in range(4):
        # the right second (left half) and its first frame (right half dark)
        assert abs(top[second, :, : W // 2].mean() * 255 - second_level(second)) < 3
        assert top[second, :, W // 2 :].max() * 255 < 20
        k = math.ceil(second * fps - 1e-9)  # first frame at t >= second
        want = decoded_small(path, k).astype(np.float32) / 255
        np.testing.assert_allclose(images[second], want, atol=1.01 / 255)
        gray_src = cv2.cvtColor(source_frame(k, fps), cv2.COLOR_BGR2GRAY)
        area = cv2.resize(gray_src, (W, H), interpolation=cv2.INTER_AREA) / 255.0
        nearest = cv2.resize(gray_src, (W, H), interpolation=cv2.INTER_NEAREST) / 255.0
        assert np.abs(images[second] - area).mean() < 8 / 255  # codec loss only
        assert np.abs(images[second] - nearest).mean() > 3 * np.abs(images[second] - area).mean()


def test_video_timestamps_missing_fall_back_to_frame_number(tmp_path, monkeypatch):
    write_video(tmp_path / "fall.avi", 7.5, 30)
    real = cv2.VideoCapture

    class NoTimestamps:
        def __init__(self, *args):
            self.cap = real(*args)

        def get(self, prop):
            return 0.0 if prop == cv2.CAP_PROP_POS_MSEC else self.cap.get(prop)

        def __getattr__(self, name):
            return getattr(self.cap, name)

    monkeypatch.setattr(cv2, "VideoCapture", NoTimestamps)
    log = LogLines()
    route = read_videos(tmp_path, ["fall"], cache_dir=None, log=log)
    np.testing.assert_array_equal(route.frame_ids, [0, 1, 2, 3])
    for second in range(4):
        assert abs(route.images["fall"][second, :16, :32].mean() * 255 - second_level(second)) < 3
        assert route.images["fall"][second, :16, 32:].max() * 255 < 20
    assert any("no usable timestamps" in line for line in log)


def test_video_cache_is_written_then_reused_without_decoding(tmp_path, monkeypatch):
    write_video(tmp_path / "spring.avi", 25.0, 100)
    write_video(tmp_path / "winter.avi", 25.0, 75)  # 3 s: one frame fewer than spring
    cache = tmp_path / "cache"
    log = LogLines()
    first = read_videos(tmp_path, ["spring", "winter"], cache_dir=cache, log=log)
    np.testing.assert_array_equal(first.frame_ids, [0, 1, 2])
    assert any("different frames" in line and "spring 1" in line for line in log)
    cached = sorted(cache.iterdir())
    assert len(cached) == 2 and all(p.suffix == ".npz" for p in cached)

    def no_decoding(*args, **kwargs):
        raise AssertionError("the second load must not decode the video")

    monkeypatch.setattr(cv2, "VideoCapture", no_decoding)
    again = read_videos(tmp_path, ["spring", "winter"], cache_dir=cache, log=LogLines())
    np.testing.assert_array_equal(again.frame_ids, first.frame_ids)
    for season in ("spring", "winter"):
        np.testing.assert_array_equal(again.images[season], first.images[season])
    stepped = read_videos(tmp_path, ["spring"], cache_dir=cache, frame_step=2, log=LogLines())
    np.testing.assert_array_equal(stepped.frame_ids, [0, 2])

    # a changed video (new mtime) is a new cache key: it is decoded again
    stat = (tmp_path / "spring.avi").stat()
    os.utime(tmp_path / "spring.avi", ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    with pytest.raises(AssertionError, match="must not decode"):
        read_videos(tmp_path, ["spring"], cache_dir=cache, log=LogLines())


def test_bad_cache_tells_to_delete_it(tmp_path):
    write_video(tmp_path / "summer.avi", 25.0, 50)
    cache = tmp_path / "cache"
    read_videos(tmp_path, ["summer"], cache_dir=cache, log=LogLines())
    (path,) = cache.iterdir()
    frames = np.zeros((2, H, W), np.float32)
    frames[1, 3, 4] = np.nan
    np.savez(path, frames=frames, frame_ids=np.arange(2))
    with pytest.raises(UserError, match="NaN or Inf.*delete it"):
        read_videos(tmp_path, ["summer"], cache_dir=cache, log=LogLines())
    np.savez(path, frames=np.zeros((2, 16, 16), np.uint8), frame_ids=np.arange(2))
    with pytest.raises(UserError, match="shape.*delete it"):
        read_videos(tmp_path, ["summer"], cache_dir=cache, log=LogLines())
    path.write_bytes(b"junk")
    with pytest.raises(UserError, match="cannot be read.*delete it"):
        read_videos(tmp_path, ["summer"], cache_dir=cache, log=LogLines())


def test_video_errors(tmp_path):
    (tmp_path / "summer.mp4").write_bytes(os.urandom(4096))
    with pytest.raises(UserError, match=r"summer\.mp4 cannot be opened"):
        read_videos(tmp_path, ["summer"], cache_dir=None, log=LogLines())

    write_video(tmp_path / "fall.avi", 25.0, 10)  # 0.4 s
    with pytest.raises(UserError, match=r"fall\.avi lasts only 0\.40 s"):
        read_videos(tmp_path, ["fall"], cache_dir=None, log=LogLines())

    with pytest.raises(UserError, match="no video for season winter"):
        read_videos(tmp_path, ["winter"], cache_dir=None, log=LogLines())

    write_video(tmp_path / "Fall_2.avi", 25.0, 30)
    with pytest.raises(UserError, match=r"several videos .*Fall_2\.avi, fall\.avi"):
        read_videos(tmp_path, ["fall"], cache_dir=None, log=LogLines())

    with pytest.raises(UserError, match="does not exist"):
        read_videos(tmp_path / "nope", ["fall"], cache_dir=None, log=LogLines())


def test_video_frame_list_selects_seconds(tmp_path):
    write_video(tmp_path / "spring.avi", 25.0, 100)
    listing = tmp_path / "frames.txt"
    listing.write_text("1-2\n")
    route = nordland.load_nordland(
        "nordland_videos", tmp_path, ["spring"], cache_dir=None, frame_list=listing, log=LogLines()
    )
    np.testing.assert_array_equal(route.frame_ids, [1, 2])
    assert abs(route.images["spring"][1, :16, :32].mean() * 255 - second_level(2)) < 3
