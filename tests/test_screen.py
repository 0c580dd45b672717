"""Constant and repeated frames (tunnels, over-exposure, a train waiting at a station), and
descriptors that make cosine matching arbitrary."""

import numpy as np
import pytest

from tests.conftest import LogLines
from vpr_jax.data.route import Route
from vpr_jax.data.screen import constant_frames, repeated_frames, screen_route
from vpr_jax.errors import UserError
from vpr_jax.methods.descriptors import degenerate_rows, degenerate_warning


def _route(n=40, seed=0):
    rng = np.random.default_rng(seed)
    images = {s: rng.uniform(0.2, 0.8, (n, 32, 64)).astype(np.float32) for s in ("summer", "fall")}
    return Route(np.arange(100, 100 + 2 * n, 2), images)


def test_constant_and_repeated_frames_match_numpy():
    route = _route()
    images = route.images["summer"].copy()
    images[3] = 0.0  # tunnel
    images[7] = 1.0  # over-exposed
    images[9] = 0.5 + np.random.default_rng(1).normal(0, 0.004, (32, 64))  # near-constant
    images[20:25] = images[19]  # standing at a station
    images[30] = images[29] + 0.3 / 255  # jpeg noise only
    std = images.reshape(len(images), -1).std(axis=1)
    step = np.abs(np.diff(images, axis=0)).mean(axis=(1, 2))
    np.testing.assert_array_equal(constant_frames(images, 0.01), std <= 0.01)
    assert np.flatnonzero(constant_frames(images, 0.01)).tolist() == [3, 7, 9]
    np.testing.assert_array_equal(repeated_frames(images)[1:], step < 0.5 / 255)
    assert np.flatnonzero(repeated_frames(images)).tolist() == [20, 21, 22, 23, 24, 30]
    assert not repeated_frames(images[:1]).any() and not constant_frames(images[:0], 0.01).any()


def test_constant_frames_are_reported_and_kept_by_default():
    route = _route()
    route.images["summer"][[4, 5]] = 0.0  # a tunnel seen in summer
    route.images["fall"][[5, 6, 30]] = 1.0  # and in fall, plus a washed-out frame
    log = LogLines()
    kept = screen_route(route, max_std=0.01, drop=False, log=log)
    assert kept is route
    assert len(log) == 1
    assert "summer 2, fall 3, at 4 places" in log[0] and "kept" in log[0]
    assert "data.drop_constant_frames=true" in log[0]


def test_dropping_constant_frames_keeps_seasons_aligned():
    route = _route()
    route.images["summer"][[4, 5]] = 0.0
    route.images["fall"][[5, 6, 30]] = 1.0
    log = LogLines()
    out = screen_route(route, max_std=0.01, drop=True, log=log)
    dropped = [4, 5, 6, 30]
    keep = np.setdiff1d(np.arange(len(route)), dropped)
    np.testing.assert_array_equal(out.frame_ids, route.frame_ids[keep])
    for season in route.seasons:
        np.testing.assert_array_equal(out.images[season], route.images[season][keep])
    assert "dropped from every season" in log[0] and "36 places left" in log[0]


def test_repeated_frames_are_reported_not_dropped():
    route = _route()
    route.images["fall"][11:15] = route.images["fall"][10]
    log = LogLines()
    assert screen_route(route, max_std=0.01, drop=True, log=log) is route
    assert len(log) == 1 and "summer 0, fall 4" in log[0] and "kept" in log[0]


def test_a_route_of_only_constant_frames_is_refused():
    route = _route(5)
    for images in route.images.values():
        images[:] = 0.0
    with pytest.raises(UserError, match="every frame is constant"):
        screen_route(route, max_std=0.01, drop=True, log=LogLines())


def test_degenerate_rows_match_numpy():
    rng = np.random.default_rng(0)
    desc = rng.normal(size=(30, 16)).astype(np.float32)
    desc[[2, 9]] = 0.0
    desc[4] = 1e-9  # nonzero, but nothing next to the others
    n_zero, one_way = degenerate_rows(desc)
    norms = np.linalg.norm(desc, axis=1)
    assert int(n_zero) == int(np.sum(norms <= 1e-6 * norms.max())) == 3
    assert not bool(one_way)

    direction = rng.normal(size=16)
    parallel = np.outer(rng.uniform(0.5, 2.0, 30), direction).astype(np.float32)
    parallel[0] = 0.0
    unit = parallel[1:] / np.linalg.norm(parallel[1:], axis=1, keepdims=True)
    assert np.allclose(unit @ unit.T, 1.0, atol=1e-6)  # numpy agrees: all one way
    n_zero, one_way = degenerate_rows(parallel)
    assert int(n_zero) == 1 and bool(one_way)
    assert int(degenerate_rows(np.zeros((4, 8), np.float32))[0]) == 4


def test_degenerate_warning_names_what_is_wrong():
    rng = np.random.default_rng(0)
    fine = rng.normal(size=(20, 8)).astype(np.float32)
    assert degenerate_warning(fine, fine[::-1]) is None
    dead = np.zeros_like(fine)
    line = degenerate_warning(dead, fine)
    assert "zero descriptors (database 20 of 20)" in line and "dead units" in line
