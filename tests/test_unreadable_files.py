"""Frames that cannot be opened: a link that loops, a link to a frame that was deleted, a
file the user may not read, a frame deleted after the folder was listed. Each is one line
naming the file and the fix, exit 2, before anything is written."""

import os

import numpy as np
import pytest

from tests.conftest import assert_one_line_error, run_here
from tests.inputs import FOLDERS, write_folders
from vpr_jax.data import images
from vpr_jax.errors import UserError


def _sweep(root, tmp_path):
    return run_here(*FOLDERS, f"data.root={root}", f"logdir={tmp_path / 'runs'}")


def test_a_symbolic_link_loop_among_the_frames_is_one_line(tmp_path):
    root = write_folders(tmp_path / "data")
    loop = root / "summer" / "frame_0004.png"
    loop.unlink()
    os.symlink("frame_0004.png", loop)  # points at itself
    assert_one_line_error(_sweep(root, tmp_path), str(loop), "loops", "fix the link or remove it")
    assert not (tmp_path / "runs").exists()


def test_a_link_to_a_deleted_frame_is_one_line(tmp_path):
    root = write_folders(tmp_path / "data")
    frame = root / "winter" / "frame_0009.png"
    frame.rename(tmp_path / "elsewhere.png")
    os.symlink(tmp_path / "elsewhere.png", frame)
    (tmp_path / "elsewhere.png").unlink()
    assert_one_line_error(_sweep(root, tmp_path), str(frame), "missing file")
    assert not (tmp_path / "runs").exists()


def test_a_frame_the_user_may_not_read_is_one_line(tmp_path):
    root = write_folders(tmp_path / "data")
    secret = root / "summer" / "frame_0011.png"
    secret.chmod(0)
    if os.access(secret, os.R_OK):  # root (or CAP_DAC_OVERRIDE) reads it anyway
        pytest.skip("this user may read files without read permission")
    assert_one_line_error(
        _sweep(root, tmp_path), str(secret), "Permission denied", "you may read it"
    )
    assert not (tmp_path / "runs").exists()


def test_a_frame_deleted_after_listing_is_one_line(tmp_path):
    root = write_folders(tmp_path / "data", n=3)
    paths = sorted((root / "summer").iterdir())  # the listing
    paths[1].unlink()  # gone before it is read
    with pytest.raises(UserError) as err:
        images.read_images(paths, "summer", resize=True)
    message = str(err.value)
    assert str(paths[1]) in message and "No such file" in message, message
    assert "\n" not in message
    frames, _ = images.read_images([paths[0], paths[2]], "summer", resize=True)
    assert frames.shape == (2, 32, 64) and np.isfinite(frames).all()
