"""Sequence matching against a loop-over-queries numpy search, and on planted routes."""

import numpy as np
import pytest

from tests.conftest import numpy_cosine
from tests.sequence_reference import sequence_top_k_numpy
from vpr_jax.evaluation.matching import top_k_matches
from vpr_jax.evaluation.sequence import (
    sequence_top_k,
    sequence_top_k_cosine,
    stretch_ids,
    trajectory_offsets,
    velocities,
)


def planted_route(nq=160, n_db=240, signal=0.5, speed=1.0, shift=12, band=0.0, seed=0):
    """Noise similarities plus ``signal`` where query q's true database frame lies, at
    shift + speed q: a train recorded at another speed in the query season. With ``band``,
    frames up to that far from the true position share the signal, falling off linearly
    (neighbouring frames look alike). Returns (similarity, true frame per query)."""
    rng = np.random.default_rng(seed)
    sim = rng.uniform(-0.3, 0.5, (nq, n_db)).astype(np.float32)
    position = shift + speed * np.arange(nq)
    truth = np.floor(position + 0.5).astype(int)
    if band:
        distance = np.abs(np.arange(n_db)[None, :] - position[:, None])
        sim += (signal * np.clip(1 - distance / band, 0, None)).astype(np.float32)
    else:
        sim[np.arange(nq), truth] += signal
    return sim, truth


def hit_rate(idx, truth):
    return np.mean(np.abs(idx[:, 0] - truth) <= 1)


def test_sequences_recover_a_planted_diagonal_that_single_images_miss():
    sim, truth = planted_route()
    assert hit_rate(sequence_top_k(sim, 1)[1], truth) < 0.7  # one image is ambiguous here
    assert hit_rate(sequence_top_k(sim, 10)[1], truth) >= 0.97


def test_the_velocity_search_follows_a_train_recorded_at_another_speed():
    """The query season's train covers 1.2 database frames per query frame: only
    trajectories of that slope find it."""
    sim, truth = planted_route(speed=1.2, band=1.5)
    searched = hit_rate(sequence_top_k(sim, 20, vels=velocities(0.8, 1.2, 0.1))[1], truth)
    straight = hit_rate(sequence_top_k(sim, 20, vels=(1.0,))[1], truth)
    assert searched >= 0.95
    assert straight < searched - 0.2


def test_the_uniqueness_score_ranks_true_matches_first():
    """The best match's score is its margin over the best match elsewhere: on a route whose
    second half carries no signal, the confident matches are the true ones."""
    sim, truth = planted_route(signal=0.0)
    sim[:80] = planted_route()[0][:80]
    scores, idx = sequence_top_k(sim, 10)
    correct = np.abs(idx[:, 0] - truth) <= 1
    order = np.argsort(-scores[:, 0], kind="stable")
    assert correct[order[:60]].all()  # the 60 most confident are all right
    assert scores[:80, 0].mean() > 3 * scores[80:, 0].mean()
    assert np.all(np.diff(scores, axis=1) <= 0)  # best first, as the metrics require


@pytest.mark.parametrize(
    "ds,window,unique,vels,block",
    [
        (2, 10, 10, (0.8, 0.9, 1.0, 1.1, 1.2), None),
        (5, 0, 4, (1.0,), 7),
        (10, 10, 10, (0.8, 0.9, 1.0, 1.1, 1.2), 16),
        (11, 6, 0, (0.5, 1.5), 40),
        (20, 10, 10, (0.8, 1.0, 1.2), 3),
    ],
)
def test_equals_the_numpy_search(ds, window, unique, vels, block):
    rng = np.random.default_rng(ds)
    sim = rng.normal(size=(57, 83)).astype(np.float32)
    kwargs = dict(vels=vels, contrast_window=window, uniqueness_window=unique, k=10)
    scores, idx = sequence_top_k(sim, ds, query_block_size=block, **kwargs)
    ref_scores, ref_idx = sequence_top_k_numpy(sim, ds, **kwargs)
    np.testing.assert_array_equal(idx, ref_idx)
    np.testing.assert_allclose(scores, ref_scores, atol=2e-5)


def test_trajectories_stop_at_breaks_in_frame_numbers():
    """Two test sections in each season: the search must equal the numpy search that skips
    steps across the breaks, and differ from one that ignores them."""
    rng = np.random.default_rng(7)
    sim = rng.normal(size=(60, 70)).astype(np.float32)
    query_ids = np.r_[np.arange(0, 300, 10), np.arange(2000, 2300, 10)]
    db_ids = np.r_[np.arange(0, 400, 10), np.arange(2000, 2300, 10)]
    got = sequence_top_k(sim, 10, query_ids=query_ids, db_ids=db_ids)
    ref = sequence_top_k_numpy(sim, 10, query_ids=query_ids, db_ids=db_ids)
    np.testing.assert_array_equal(got[1], ref[1])
    np.testing.assert_allclose(got[0], ref[0], atol=2e-5)
    unbroken = sequence_top_k(sim, 10)
    assert not np.array_equal(got[1], unbroken[1])


def test_ds_1_is_single_image_matching():
    rng = np.random.default_rng(1)
    q = rng.normal(size=(40, 16)).astype(np.float32)
    d = rng.normal(size=(50, 16)).astype(np.float32)
    sim = numpy_cosine(q, d)
    order = np.argsort(-sim, axis=1, kind="stable")[:, :10]
    scores, idx = sequence_top_k(sim, 1)
    np.testing.assert_array_equal(idx, order)
    np.testing.assert_allclose(scores, np.take_along_axis(sim, order, 1), atol=1e-6)
    single = top_k_matches(q, d, 10)
    from_desc = sequence_top_k_cosine(q, d, 1)
    np.testing.assert_array_equal(from_desc[1], single[1][0])
    np.testing.assert_array_equal(from_desc[0], single[0][0])


def test_descriptors_blockwise_equal_the_full_similarity():
    rng = np.random.default_rng(2)
    q = rng.normal(size=(45, 24)).astype(np.float32)
    d = rng.normal(size=(90, 24)).astype(np.float32)
    full = sequence_top_k(numpy_cosine(q, d), 10)
    for block in (None, 8):
        blocks = sequence_top_k_cosine(q, d, 10, query_block_size=block)
        np.testing.assert_array_equal(blocks[1], full[1])
        np.testing.assert_allclose(blocks[0], full[0], atol=2e-5)


def test_velocity_grid_offsets_and_stretches():
    assert velocities(0.8, 1.2, 0.1) == (0.8, 0.9, 1.0, 1.1, 1.2)
    assert velocities(1.0, 1.0, 0.1) == (1.0,)
    offsets = trajectory_offsets(10, (1.0, 0.8))
    assert offsets[0] == tuple(range(-5, 5))  # centred: 5 frames before, 4 after
    assert offsets[1] == (-4, -3, -2, -2, -1, 0, 1, 2, 2, 3)
    # One frame left out (40 -> 60) keeps the stretch; a longer gap or a step back breaks it.
    ids = np.r_[np.arange(0, 50, 10), 60, 70, np.arange(500, 530, 10), 0, 10]
    np.testing.assert_array_equal(stretch_ids(ids), [0] * 7 + [1] * 3 + [2] * 2)
    with pytest.raises(ValueError, match="v_min"):
        velocities(1.2, 0.8, 0.1)
