"""Aligned host arrays: numpy's own gathers as the oracle, and the one fact about JAX that
the whole route's memory rests on (an aligned host array enters JAX without a copy)."""

import jax
import numpy as np
import pytest

from vpr_jax import host_arrays
from vpr_jax.config import SplitConfig
from vpr_jax.data.pair import pair_data
from vpr_jax.data.splits import make_split
from vpr_jax.data.synthetic import synthetic_route
from vpr_jax.encoders import pca
from vpr_jax.methods.descriptors import degenerate_rows, encode_rows


def test_gathers_equal_numpy_and_are_aligned():
    rng = np.random.default_rng(0)
    x = rng.random((50, 4, 6), dtype=np.float32)
    y = rng.random((30, 4, 6), dtype=np.float32)
    rows, mask = np.array([7, 0, 49, 7]), rng.random(30) < 0.5
    taken = host_arrays.take(x, rows)
    np.testing.assert_array_equal(taken, x[rows])
    np.testing.assert_array_equal(host_arrays.take(y, mask), y[mask])
    stacked = host_arrays.stack_rows([(x, rows), (y, mask)])
    np.testing.assert_array_equal(stacked, np.concatenate([x[rows], y[mask]]))
    for a in (taken, stacked, host_arrays.empty((3, 5), np.float64)):
        assert host_arrays.is_aligned(a)
    with pytest.raises(IndexError):
        host_arrays.take(x, [50])
    with pytest.raises(IndexError):
        host_arrays.take(x, [-1])  # numpy would wrap it; a split never means that


def test_aligned_copies_only_when_it_must():
    a = host_arrays.aligned(np.arange(12.0).reshape(3, 4))  # float64: one float32 copy
    assert a.dtype == np.float32 and host_arrays.is_aligned(a)
    assert host_arrays.aligned(a) is a
    np.testing.assert_array_equal(a, np.arange(12.0).reshape(3, 4))


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="a host array is the device's on CPU")
def test_jax_reads_an_aligned_host_array_in_place():
    a = host_arrays.empty((64, 32))
    a[...] = 1.0
    assert np.shares_memory(np.asarray(jax.device_put(a)), a)
    rows = pca.device_rows(a.reshape(64, 4, 8))  # flattened on the host: still in place
    assert rows.shape == (64, 32) and np.shares_memory(np.asarray(rows), a)


def test_a_pair_is_built_in_aligned_arrays():
    route = synthetic_route(n_frames=120, seasons=("summer", "winter"))
    for season in route.seasons:
        assert host_arrays.is_aligned(route.images[season])
    split = make_split(route.frame_ids, SplitConfig(n_train=40, n_test=30, gap=5))
    pair = pair_data(route, split, "summer", "winter", "test", 1)
    for a in (pair.train, pair.db, pair.query, pair.val_db, pair.val_query):
        assert host_arrays.is_aligned(a)
    summer, winter = route.images["summer"], route.images["winter"]
    np.testing.assert_array_equal(
        pair.train, np.concatenate([summer[split.train], winter[split.train]])
    )
    np.testing.assert_array_equal(pair.query, winter[split.test])


def test_blocked_encoding_equals_one_call():
    rng = np.random.default_rng(1)
    images = rng.random((45, 4, 8), dtype=np.float32)
    state = pca.fit_pca(images, 6)
    whole = np.asarray(pca.suffix_descriptors(state, images))
    blocked = encode_rows(lambda x: pca.suffix_descriptors(state, x), images, block_rows=8)
    assert host_arrays.is_aligned(blocked)
    np.testing.assert_allclose(blocked, whole, rtol=1e-6, atol=1e-6)


def test_degenerate_rows_match_the_definition_with_zero_rows():
    rng = np.random.default_rng(2)
    desc = np.repeat(rng.normal(size=(1, 16)).astype(np.float32), 9, axis=0)
    desc[[0, 4]] = 0.0  # zero rows are neither counted as parallel nor as the first row
    n_zero, one_way = degenerate_rows(desc * rng.uniform(0.5, 2.0, size=(9, 1)).astype(np.float32))
    assert int(n_zero) == 2 and bool(one_way)
    desc[5, 0] += 1.0  # one row points elsewhere
    assert not bool(degenerate_rows(desc)[1])
