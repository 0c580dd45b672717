"""The bad-input catalogue: every case runs the CLI in a subprocess and must end in one line
naming the problem and the fix, exit code 2, no traceback, and the log directory exactly as
it was. (Input the suite accepts with a note, such as colour images or seasons of different
lengths, is tested in test_hostile_data.py.)"""

import hashlib
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from omegaconf import OmegaConf

from tests.conftest import SMALL, TINY_ROUTE, assert_one_line_error, run_cli, run_here
from tests.inputs import write_release, write_video
from vpr_jax.command_line import parse_config
from vpr_jax.config import to_dict
from vpr_jax.outputs.logdir import config_yaml


def _snapshot(folder: Path) -> dict:
    if not folder.exists():
        return {}
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def _release(root: Path, seasons=("spring", "summer", "fall"), ids=range(1, 5), shape=(32, 64)):
    return write_release(
        root, {s: [np.full(shape, 40 + i, np.uint8) for i in ids] for s in seasons}, ids
    )


def _corrupt(root):
    path = _release(root) / "summer" / "images-00002.png"
    path.write_bytes(path.read_bytes()[:20])
    return _images(root)


def _zero_bytes(root):
    path = _release(root) / "fall" / "images-00004.png"
    path.write_bytes(b"")
    return _images(root)


def _wrong_size(root):
    _release(root)
    cv2.imwrite(str(root / "fall" / "images-00003.png"), np.zeros((48, 64), np.uint8))
    return _images(root)


def _no_common(root):
    _release(root, seasons=("spring", "summer"), ids=range(1, 4))
    _release(root, seasons=("fall",), ids=range(10, 14))
    return _images(root)


def _absent_in_list(root):
    listing = root.parent / "frames.txt"
    listing.write_text("# the clean stretch\n1-3\nimages-00007.png\n")
    return [*_images(_release(root)), f"data.frame_list={listing}"]


def _images(root):
    return ["data.source=nordland_images", f"data.root={root}"]


def _videos(root, seasons=("spring", "summer", "fall"), n_frames=50):
    for season in seasons:
        write_video(root / f"{season}.avi", 25.0, n_frames)
    return [
        "data.source=nordland_videos",
        f"data.root={root}",
        f"data.cache_dir={root.parent / 'cache'}",
    ]


def _unopenable_video(root):
    args = _videos(root, seasons=("spring", "fall"))
    (root / "summer.mp4").write_bytes(np.random.default_rng(0).bytes(4096))
    return args


def _short_video(root):
    args = _videos(root, seasons=("spring", "summer"))
    write_video(root / "fall.avi", 25.0, 10)  # 0.4 s
    return args


def _poisoned_cache(value):
    def make(root):
        args = _videos(root)
        # A first run decodes and caches the videos, then stops at the split (2 seconds of
        # video are too few places): the cache is real, written by the reader.
        first = run_here(*args, f"logdir={root.parent / 'first'}")
        assert_one_line_error(first, "split")
        cache = next((root.parent / "cache").glob("summer*.npz"))
        with np.load(cache) as z:
            frames, ids = z["frames"].astype(np.float32) / 255, z["frame_ids"]
        frames[1, 5, 7] = value
        np.savez(cache, frames=frames, frame_ids=ids)
        return args

    return make


DATA_CASES = {
    "missing root": (lambda root: _images(root / "absent"), ["does not exist", "data.root"]),
    "empty root": (_images, ["data.root"]),
    "missing season": (
        lambda root: _images(_release(root, seasons=("spring", "summer"))),
        ["fall"],
    ),
    "corrupt image": (_corrupt, ["images-00002.png", "re-copy"]),
    "zero-byte image": (_zero_bytes, ["images-00004.png", "empty (0 bytes)"]),
    "wrong size": (_wrong_size, ["images-00003.png", "data.source=folders"]),
    "no common frames": (_no_common, ["share no frame"]),
    "frame list naming absent frames": (
        _absent_in_list,
        ["frames.txt", "first: 7", "remove them from the list"],
    ),
    "video that cannot be opened": (
        _unopenable_video,
        ["summer.mp4", "cannot be opened", "re-encode"],
    ),
    "video shorter than one second": (_short_video, ["fall.avi", "lasts only 0.40 s"]),
    "NaN in the video cache": (_poisoned_cache(np.nan), ["NaN or Inf", "delete it"]),
    "Inf in the video cache": (_poisoned_cache(np.inf), ["NaN or Inf", "delete it"]),
}


@pytest.mark.parametrize("case", DATA_CASES)
def test_bad_data(case, tmp_path):
    """In this process: the command line's own refusals are test_logdir_*'s and
    test_foreign_logdir's, run in a fresh interpreter."""
    make, words = DATA_CASES[case]
    root = tmp_path / "data"
    root.mkdir()
    args = make(root)
    logdir = tmp_path / "runs"
    logdir.mkdir()
    (logdir / "keep.txt").write_text("mine")
    proc = run_here(*args, f"logdir={logdir}")
    assert_one_line_error(proc, *words)
    assert _snapshot(logdir) == {"keep.txt": hashlib.sha256(b"mine").hexdigest()}


TINY = TINY_ROUTE  # the smallest route that gets past the data checks to the methods
CONFIG_CASES = {
    "unknown key": (["method=raw"], ["method"]),
    "frame range for the built-in route": (
        ["data.frame_range=[1,50]"],
        ["data.frame_range applies to Nordland sources"],
    ),
    "a frame range that is not [first, last]": (
        ["data.source=nordland_images", "data.root=/nowhere", "data.frame_range=[9,2]"],
        ["data.frame_range=[9, 2] is not [first, last]"],
    ),
    "wrong type": (["tolerance=two"], ["tolerance"]),
    "unknown matching precision": (
        ["matching.precision=tf32"],
        ["matching.precision=tf32", "float32", "default"],
    ),
    "bad pair name": (["season_pairs=summer_fall"], ["summer_fall", "season_pairs"]),
    "pair of one season": (["season_pairs=fall-fall"], ["fall-fall"]),
    "pair outside seasons": (["season_pairs=summer-winter"], ["winter", "data.seasons"]),
    "negative removed count": (["removed_pcs=[-1,5]"], ["removed_pcs"]),
    "one number for seeds": (["seeds=3"], ["seeds=3 names one seed", "seeds=[3]", "seeds=[0,1,2]"]),
    "a list for a one-value setting": (
        ["tolerance=[1,2]"],
        ["tolerance=[1, 2] is a list", "tolerance takes one value"],
    ),
    "removed count leaves nothing": ([*SMALL, "removed_pcs=[0,599]"], ["599", "up to 248"]),
    "more ICs than the data allow": (
        [*SMALL, "ica.n_components=590"],
        ["ica.n_components=590", "up to 20", "ica.n_components <= 229"],
    ),
    "ICs not a count": (["ica.n_components=many"], ["ica.n_components=many", "all"]),
    "more change directions than aligned places": (
        [*SMALL, "removed_pcs=[0,200]"],
        ["diff_pca", "125 aligned training places", "up to 125"],
    ),
    "LDA shrinkage outside [0, 1]": (["lda.shrinkage=1.5"], ["lda.shrinkage=1.5", "[0, 1]"]),
    "a method needing more components than a subspace PCA fit holds": (
        [*SMALL, "methods=[pca,lda]", "pca.solver=subspace", "pca.subspace_components=100"],
        ["method lda needs 200 components", "holds 100", "pca.subspace_components"],
    ),
    "an unknown setting of a method": (["ica.foo=1"], ["ica.foo is unknown", "n_components"]),
    "a bad value among a swept setting's": (
        ["lda.shrinkage=[0.1,2]"],
        ["lda.shrinkage=2", "[0, 1]"],
    ),
    "an empty list for a setting": (
        ["ica.n_components=[]"],
        ["ica.n_components=[] is an empty list", "values to sweep"],
    ),
    "seeds that repeat": (["seeds=[0,0]"], ["seeds=[0, 0]", "name each once"]),
    "unknown ICA contrast": (["ica.fun=tanh"], ["ica.fun=tanh", "logcosh"]),
    "sequence of no image": (["sequence.ds=[0,10]"], ["sequence.ds=[0, 10]", "ds=1"]),
    "velocities backwards": (
        ["sequence.v_min=1.2", "sequence.v_max=0.8"],
        ["v_min=1.2", "v_max=0.8"],
    ),
    "patch that does not tile": (
        ["preprocess=patchnorm", "patchnorm.size=5"],
        ["patchnorm.size=5", "2, 4, 8, 16, 32"],
    ),
    "unknown preprocessing": (["preprocess=clahe"], ["preprocess=clahe", "patchnorm"]),
    "an input that is no part": (
        ["lda.input=[pixels,edges]"],
        ["lda.input=edges", "'edges' is not an input part", "standardised+gradients"],
    ),
    "an input naming a part twice": (
        ["raw.input=gradients+gradients"],
        ["raw.input=gradients+gradients", "named twice"],
    ),
    "the flag an input replaced": (
        ["lda.standardise=true"],
        ["lda.standardise is now lda.input", "lda.input=standardised"],
    ),
    "patch normalisation twice": (
        ["preprocess=patchnorm", "raw.input=patchnorm"],
        ["raw.input=patchnorm", "preprocess=patchnorm", "drop one"],
    ),
    "unknown block normalisation": (["gradients.norm=L3"], ["gradients.norm=L3", "L2-Hys"]),
    "a method that is not module:name": (["methods=[raw,a:b:c]"], ["'a:b:c' is not module:name"]),
    "your method named like a built-in one": (
        ["methods=[raw,my.mod:pca]"],
        ["'pca' has the name of a built-in method", "rename"],
    ),
    "two of your methods of one name": (
        ["methods=[a.b:x,c.d:x]"],
        ["two of your methods are called 'x'"],
    ),
    "settings of a method not in methods": (["plugin.x.alpha=1"], ["plugin.x.*", "methods=[...]"]),
    "your module does not import": (
        [*TINY, "methods=[raw,no_such_module:m]"],
        ["no_such_module does not import", "PYTHONPATH", "python -c 'import no_such_module'"],
    ),
    "your module lacks the object": ([*TINY, "methods=[raw,json:nothing]"], ["json", "no nothing"]),
    "your object lacks fit and encode": (
        [*TINY, "methods=[raw,json:JSONDecoder]"],
        ["json:JSONDecoder has no callable fit or encode", "docs/methods.md"],
    ),
}


@pytest.mark.parametrize("case", CONFIG_CASES)
def test_bad_config(case, tmp_path):
    """In this process (the command line itself: test_logdir_* and test_foreign_logdir)."""
    args, words = CONFIG_CASES[case]
    proc = run_here(*args, f"logdir={tmp_path / 'runs'}")
    assert_one_line_error(proc, *words)
    assert _snapshot(tmp_path / "runs") == {}


def test_a_setting_of_a_method_left_out_of_methods_is_noted(tmp_path):
    """Not refused (a long command may keep settings of a method it drops), but said."""
    proc = run_here(
        *TINY,
        "methods=[raw]",
        "fae.hidden=[64,128]",
        "season_pairs=summer-fall",
        f"logdir={tmp_path / 'runs'}",
    )
    assert proc.returncode == 0, proc.stderr
    assert "note: fae.hidden set, but methods=['raw'] has no fae: unused" in proc.stdout


def test_logdir_that_is_a_file(tmp_path):
    path = tmp_path / "runs"
    path.write_text("not a folder")
    assert_one_line_error(run_cli(f"logdir={path}"), "is a file")
    assert path.read_text() == "not a folder"


def test_logdir_that_cannot_be_written():
    # /proc refuses new folders even to root, unlike a chmod-ed folder.
    assert_one_line_error(run_cli("logdir=/proc/vpr_jax_runs"), "not writable", "logdir")


def _our_config() -> str:
    return config_yaml(parse_config([]))


LOGDIR_CASES = {
    "results.csv without config.yaml": (
        {"results.csv": "season_pair,recall_at_1\nsummer-fall,0.5\n"},
        ["no config.yaml", "new logdir=PATH"],
    ),
    "results.csv of another tool": (
        {"config.yaml": _our_config(), "results.csv": "query,match\n1,1\n"},
        ["results.csv is not a results table", "lacks columns", "move it away"],
    ),
    "config.yaml that is not a config": (
        {"config.yaml": "methods: [raw\n"},
        ["config.yaml is not a sweep config"],
    ),
    "config.yaml of another format": (
        {"config.yaml": OmegaConf.to_yaml(to_dict(parse_config([])))},
        ["written in another format (None", "new logdir=PATH"],
    ),
}


@pytest.mark.parametrize("case", LOGDIR_CASES)
def test_foreign_logdir(case, tmp_path):
    files, words = LOGDIR_CASES[case]
    logdir = tmp_path / "runs"
    logdir.mkdir()
    for name, text in files.items():
        (logdir / name).write_text(text)
    before = _snapshot(logdir)
    assert_one_line_error(run_cli(f"logdir={logdir}"), *words)
    assert _snapshot(logdir) == before


def test_finished_logdir_is_untouched_by_bad_reruns(small_sweep, tmp_path):
    finished, _ = small_sweep
    logdir = tmp_path / "runs"
    shutil.copytree(finished, logdir)
    before = _snapshot(logdir)
    assert_one_line_error(
        run_here(*SMALL, "tolerance=3", f"logdir={logdir}"), "different configuration", "tolerance"
    )
    assert_one_line_error(run_here(*SMALL, "removed_pcs=[0,900]", f"logdir={logdir}"), "900")
    assert _snapshot(logdir) == before
