"""Typed configs from key=value, and train/test splits that never leak."""

import numpy as np
import pytest

from vpr_jax.config import SplitConfig, identity, parse_config
from vpr_jax.data.splits import make_split
from vpr_jax.errors import UserError


def test_defaults_and_overrides():
    cfg = parse_config([])
    assert cfg.preset == "quick" and cfg.logdir == "runs/quick"
    assert cfg.data.seasons == ("spring", "summer", "fall")
    assert cfg.removed_pcs == (0, 5, 10, 20, 50, 100)
    cfg = parse_config(["methods=raw", "removed_pcs=[50,0,50]", "data.seasons=summer,winter",
                        "season_pairs=[summer-winter]", "split.train_fraction=0.5"])
    assert cfg.methods == ("raw",) and cfg.removed_pcs == (0, 50)
    assert cfg.data.seasons == ("summer", "winter") and cfg.season_pairs == "summer-winter"
    assert cfg.split.train_fraction == 0.5


def test_paper_preset_file_is_applied():
    assert parse_config(["preset=paper"]) != parse_config([])


@pytest.mark.parametrize("arg,words", [
    ("foo=1", "foo"), ("tolerance=abc", "tolerance"), ("methods=[raw,sift]", "sift"),
    ("removed_pcs=[-5]", "negative"), ("data.source=web", "data.source"),
    ("preset=huge", "preset"), ("data.seasons=[summer]", "two seasons"),
    ("split.train_fraction=1.5", "train_fraction"), ("data.source=folders", "data.root"),
    ("nonsense", "key=value"),
])
def test_bad_config_is_one_line_user_error(arg, words):
    with pytest.raises(UserError) as err:
        parse_config([arg])
    assert words in str(err.value) and "\n" not in str(err.value)


def test_identity_ignores_keys_that_only_add_cells():
    a = parse_config(["methods=raw", "removed_pcs=[0]", "logdir=/tmp/x"])
    b = parse_config(["methods=[raw,pca]"])
    assert identity(a) == identity(b)
    assert identity(a) != identity(parse_config(["tolerance=3"]))


def test_count_split_has_gap_in_original_frames():
    ids = np.arange(0, 5000, 10)  # frame step 10
    split = make_split(ids, SplitConfig(n_train=100, n_test=50, gap=100))
    assert len(split.train) == 100 and len(split.test) == 50
    assert ids[split.test[0]] - ids[split.train[-1]] > 100
    assert set(split.train).isdisjoint(split.test)


def test_fraction_split_tests_everything_after_the_gap():
    ids = np.arange(1000)
    split = make_split(ids, SplitConfig(train_fraction=0.5, gap=20))
    np.testing.assert_array_equal(split.train, np.arange(500))
    np.testing.assert_array_equal(split.test, np.arange(520, 1000))


def test_split_that_does_not_fit_says_what_to_change():
    with pytest.raises(UserError, match="split.n_train"):
        make_split(np.arange(300), SplitConfig(n_train=250, n_test=100, gap=10))
