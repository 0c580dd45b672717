"""Typed configs from key=value, and train/test splits that never leak."""

import sys

import numpy as np
import pytest

from tests.conftest import method_settings, run_process
from vpr_jax.command_line import parse_config
from vpr_jax.config import SplitConfig
from vpr_jax.data.splits import make_split
from vpr_jax.errors import UserError
from vpr_jax.outputs.logdir import identity


def test_defaults_and_overrides():
    cfg = parse_config([])
    assert cfg.preset == "quick" and cfg.logdir == "runs/quick"
    assert cfg.data.seasons == ("spring", "summer", "fall")
    assert cfg.removed_pcs == (0, 5, 10, 20, 50, 100)
    cfg = parse_config(
        [
            "methods=raw",
            "removed_pcs=[50,0,50]",
            "data.seasons=summer,winter",
            "season_pairs=[summer-winter]",
            "split.train_fraction=0.5",
        ]
    )
    assert cfg.methods == ("raw",) and cfg.removed_pcs == (0, 50)
    assert cfg.data.seasons == ("summer", "winter") and cfg.season_pairs == "summer-winter"
    assert cfg.split.train_fraction == 0.5


def test_paper_preset_is_the_seeds_protocol_and_the_command_line_overrides_it():
    cfg, default = parse_config(["preset=paper"]), parse_config([])
    # The whole built-in route, every 10th frame: 3,577 images a season.
    assert (cfg.data.n_frames, cfg.data.frame_step) == (35768, 10)
    # The paper's 2,500 training and 450 test images per season, a 100-frame gap.
    assert (cfg.split.n_train, cfg.split.n_test, cfg.split.gap) == (2500, 450, 100)
    assert cfg.tolerance == 10  # original frames: the neighbouring sampled frame
    assert method_settings(cfg, "ica").n_components == 256
    objectives = (method_settings(cfg, m).objective for m in ("fae", "cae"))
    assert set(objectives) == {("reconstruct",)}
    # What the preset leaves alone stays the default.
    assert (cfg.seed, cfg.methods, cfg.removed_pcs) == (
        default.seed,
        default.methods,
        default.removed_pcs,
    )
    assert cfg.data.source == "synthetic" and cfg.season_pairs == default.season_pairs
    # A key on the command line wins over the preset's.
    assert parse_config(["preset=paper", "split.n_test=100"]).split.n_test == 100


@pytest.mark.parametrize(
    "arg,words",
    [
        ("foo=1", "foo"),
        ("tolerance=abc", "tolerance"),
        ("methods=[raw,sift]", "sift"),
        ("removed_pcs=[-5]", "negative"),
        ("data.source=web", "data.source"),
        ("preset=huge", "preset"),
        ("data.seasons=[summer]", "two seasons"),
        ("split.train_fraction=1.5", "train_fraction"),
        ("data.source=folders", "data.root"),
        ("nonsense", "key=value"),
    ],
)
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
    # the stretch of 100: the last 10 validate; 10 frames (= 100 original) before them go
    np.testing.assert_array_equal(split.val, np.arange(90, 100))
    np.testing.assert_array_equal(split.train, np.arange(80))
    assert len(split.test) == 50
    assert ids[split.test[0]] - ids[split.val[-1]] > 100
    assert ids[split.val[0]] - ids[split.train[-1]] > 100
    assert set(split.train).isdisjoint(split.test)


def test_validation_stretch_follows_val_fraction_and_must_leave_training():
    split = make_split(
        np.arange(1000), SplitConfig(n_train=500, n_test=100, gap=5, val_fraction=0.2)
    )
    np.testing.assert_array_equal(split.val, np.arange(400, 500))
    np.testing.assert_array_equal(split.train, np.arange(395))
    with pytest.raises(UserError, match="split.val_fraction"):
        make_split(np.arange(1000), SplitConfig(n_train=12, n_test=100, gap=10))


def test_fraction_split_tests_everything_after_the_gap():
    ids = np.arange(1000)
    split = make_split(ids, SplitConfig(train_fraction=0.5, gap=20))
    np.testing.assert_array_equal(split.train, np.arange(430))  # 50 validate, 20 gap
    np.testing.assert_array_equal(split.val, np.arange(450, 500))
    np.testing.assert_array_equal(split.test, np.arange(520, 1000))


def test_split_that_does_not_fit_says_what_to_change():
    with pytest.raises(UserError, match="split.n_train"):
        make_split(np.arange(300), SplitConfig(n_train=250, n_test=100, gap=10))


def _brute_force_sections(frame_ids, n_sections, length, gap):
    n = len(frame_ids)
    test = []
    for i in range(n_sections):
        start = round((i + 0.5) * n / n_sections - length / 2)
        test += list(range(start, start + length))
    train = [p for p in range(n) if all(abs(frame_ids[p] - frame_ids[t]) > gap for t in test)]
    return np.array(train), np.array(test)


@pytest.mark.parametrize("step", [1, 3])
def test_olid_sections_match_a_brute_force_partition(step):
    frame_ids = np.arange(1, 3001 * step, step)[:3000]
    split = make_split(frame_ids, SplitConfig(test_sections=3, n_test=115, gap=20 * step))
    train, test = _brute_force_sections(frame_ids, 3, 115, 20 * step)
    np.testing.assert_array_equal(split.test, test)
    n_val = round(0.1 * len(train))  # the end of the training frames validates
    np.testing.assert_array_equal(split.val, train[-n_val:])
    rest = train[:-n_val]
    fit = rest[frame_ids[rest] < frame_ids[train[-n_val]] - 20 * step]
    np.testing.assert_array_equal(split.train, fit)
    assert len(test) == 345 and len(set(split.train) & set(split.test)) == 0
    # every training frame is more than the gap from every test frame, and nothing else drops
    assert len(train) == 3000 - 345 - 3 * 2 * 20


def test_sections_that_do_not_fit_are_one_line_errors():
    with pytest.raises(UserError, match="do not fit"):
        make_split(np.arange(1000), SplitConfig(test_sections=3, n_test=300, gap=50))
    with pytest.raises(UserError, match="leave 0 training frames"):
        make_split(np.arange(100), SplitConfig(test_sections=1, n_test=98, gap=10))


def test_full_preset_is_the_whole_route_with_olid_sections():
    cfg = parse_config(["preset=full"])
    assert cfg.data.n_frames == 35768 and cfg.data.frame_step == 1
    assert (cfg.split.test_sections, cfg.split.n_test, cfg.split.gap) == (3, 1150, 200)
    assert cfg.split.database == "all"


def test_a_saved_config_carries_its_format_and_reads_back_as_its_identity(tmp_path):
    """config.yaml says its logdir's format; read back, it is the identity it was written
    from, and one without the format (or of another) is refused."""
    import yaml

    from vpr_jax.errors import UserError
    from vpr_jax.outputs.logdir import FORMAT, config_yaml, saved_config

    def saved_identity(path):
        return identity(saved_config(path))

    cfg = parse_config(["tolerance=4", "methods=[raw,pca]"])
    path = tmp_path / "config.yaml"
    path.write_text(config_yaml(cfg))
    assert yaml.safe_load(path.read_text())["format"] == FORMAT
    assert saved_identity(path) == identity(cfg) != identity(parse_config([]))
    written = yaml.safe_load(path.read_text())
    without_format = {k: v for k, v in written.items() if k != "format"}
    for saved in (without_format, {**written, "format": FORMAT + 1}):
        path.write_text(yaml.safe_dump(saved))
        with pytest.raises(UserError, match="another format.*new logdir=PATH"):
            saved_identity(path)


def test_every_method_of_the_table_loads_with_its_settings():
    """Each line of the method table names an object of the one contract, whose settings
    dataclass takes every default (the table itself and config.py load without JAX)."""
    from experiments.resolve import load
    from vpr_jax import method_table

    for info in method_table.BUILTIN:
        method = load(info)
        assert callable(method.fit) and callable(method.encode), info.method
        assert method.settings is None or method.settings() is not None


def test_the_config_and_the_logdir_checks_load_without_jax():
    code = (
        "import sys; import vpr_jax.config, vpr_jax.outputs.logdir, experiments.plan; "
        "assert not [m for m in sys.modules if m == 'jax' or m.startswith('jax.')], "
        "'jax was imported'"
    )
    proc = run_process([sys.executable, "-c", code], timeout=60)
    assert proc.returncode == 0, proc.stderr


def _route_of(tmp_path, *args: str):
    from experiments.plan import make_plan
    from tests.conftest import TINY_ROUTE, LogLines

    argv = [*TINY_ROUTE, "methods=[raw]", f"logdir={tmp_path / 'runs'}", *args]
    return make_plan(parse_config(argv), LogLines()).route


@pytest.mark.timeout(120)
def test_the_built_in_route_renders_the_seasons_its_pairs_name(tmp_path):
    """A season no pair names is not rendered (0.27 GiB a season on the whole route); the
    ones rendered are the same pixels as when every season is; dropping constant frames
    looks at every season of data.seasons, so all of them are rendered then."""
    every = _route_of(tmp_path / "all")
    named = _route_of(tmp_path / "one", "season_pairs=summer-fall")
    assert every.seasons == ("spring", "summer", "fall")
    assert named.seasons == ("summer", "fall")
    for season in named.seasons:
        np.testing.assert_array_equal(named.images[season], every.images[season])
    dropping = _route_of(
        tmp_path / "drop", "season_pairs=summer-fall", "data.drop_constant_frames=true"
    )
    assert dropping.seasons == every.seasons
