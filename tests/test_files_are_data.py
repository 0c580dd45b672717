"""Files from elsewhere are data, never code: an encoder folder, a logdir and a VPR-Bench
ground truth that ask for more (a function to call, a module to import, a pickle payload, an
environment variable, a folder elsewhere, an array larger than memory) are refused in one
line with nothing run: the marker file each payload would write never appears. Folders saved
before files became data only (tests/data/format2_encoders) still load and encode to the
codes they gave then."""

import json
import os
import pickle
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import REPO, assert_one_line_error, run_here
from vpr_jax import load_encoder
from vpr_jax.errors import UserError
from vpr_jax.untrusted import read_object_array

FORMAT2 = REPO / "tests" / "data" / "format2_encoders"
NUMPY1 = REPO / "tests" / "data" / "vpr_bench_numpy1"
EVIL_MODULE = """
from pathlib import Path
Path({marker!r}).write_text("imported")
method = None
"""


def _codes() -> dict[str, np.ndarray]:
    with np.load(FORMAT2 / "codes.npz") as codes:
        return {key: codes[key] for key in codes.files}


@pytest.mark.parametrize("key", sorted(set(_codes()) - {"images"}))
def test_a_folder_saved_before_files_became_data_encodes_to_its_codes(key):
    """Every built-in method and kind of state, saved by the commit before (format 2)."""
    import jax

    codes = _codes()
    folder, _, served = key.partition("@")
    values = dict(part.split("=") for part in served.split(",") if part)
    encode, params = load_encoder(FORMAT2 / folder, **{k: int(v) for k, v in values.items()})
    images = codes["images"]
    np.testing.assert_allclose(encode(params, images), codes[key], rtol=1e-5, atol=1e-6)
    per_image = jax.vmap(lambda image: encode(params, image[None])[0])(images)
    np.testing.assert_allclose(per_image, codes[key], rtol=1e-5, atol=1e-5)


def _refused(work, *words: str) -> str:
    """The one line ``work()`` is refused with (a UserError holding every one of ``words``)."""
    with pytest.raises(UserError) as refused:
        work()
    line = str(refused.value)
    assert "\n" not in line, line
    for word in words:
        assert word in line, line
    return line


def _folder_with_skeleton(tmp_path: Path, skeleton: dict, arrays: bool) -> Path:
    """A copy of a saved raw folder whose state's skeleton is ``skeleton`` (its arrays kept,
    or only the skeleton: a lone skeleton.json was enough for the old loader)."""
    folder = tmp_path / "shared_encoder"
    shutil.copytree(FORMAT2 / "raw", folder)
    if not arrays:
        shutil.rmtree(folder / "state")
        (folder / "state").mkdir()
    (folder / "state" / "skeleton.json").write_text(json.dumps(skeleton))
    return folder


def _leaf() -> dict:
    return {"leaf": 0, "shape": [2048], "dtype": "float32"}


def _payloads(marker: Path) -> dict[str, dict]:
    touch = ["touch", str(marker)]
    return {
        "a function called": {
            "dataclass": "subprocess:run",
            "fields": {},
            "static": {"args": touch},
        },
        "a dotted path through a vpr_jax module": {
            "dataclass": "vpr_jax.compile_cache:os.system",
            "fields": {},
            "static": {"command": f"touch {marker}"},
        },
        "a static value's type": {
            "namedtuple": "vpr_jax.encoders.pca:PCAState",
            "fields": {"mean": _leaf()},
            "static": {"x": {"namedtuple": "subprocess:run", "fields": {"args": touch}}},
        },
        "a function inside a state type": {
            "dataclass": "vpr_jax.encoders.autoencoders:ModelState",
            "fields": {"params": {"dict": {}}},
            "static": {"spec": {"namedtuple": "subprocess:run", "fields": {"args": touch}}},
        },
    }


@pytest.mark.parametrize("arrays", [True, False], ids=["with arrays", "a lone skeleton"])
@pytest.mark.parametrize("payload", list(_payloads(Path("m"))))
def test_a_skeleton_that_names_a_function_is_refused_unrun(tmp_path, payload, arrays):
    marker = tmp_path / "marker"
    skeleton = _payloads(marker)[payload]
    folder = _folder_with_skeleton(tmp_path, skeleton, arrays)
    _refused(lambda: load_encoder(folder), "skeleton.json")
    assert not marker.exists()


def test_a_skeleton_that_claims_more_than_memory_is_refused_before_reading(tmp_path):
    huge = {"dict": {"mean": {"leaf": 0, "shape": [1 << 20, 1 << 20], "dtype": "float32"}}}
    folder = _folder_with_skeleton(tmp_path, huge, arrays=True)
    _refused(lambda: load_encoder(folder), "claims 4,096.0 GiB", "nothing was read")


def test_a_skeleton_of_a_dtype_that_is_no_number_is_refused(tmp_path):
    odd = {"dict": {"mean": {"leaf": 0, "shape": [2048], "dtype": "object"}}}
    folder = _folder_with_skeleton(tmp_path, odd, arrays=True)
    _refused(lambda: load_encoder(folder), "not a fitted state's skeleton", "dtype")


def _evil_module(tmp_path: Path, marker: Path) -> Path:
    folder = tmp_path / "theirs"
    folder.mkdir()
    (folder / "evil_methods.py").write_text(EVIL_MODULE.format(marker=str(marker)))
    return folder


def test_a_method_named_by_a_folder_is_imported_only_when_the_caller_names_it(
    tmp_path, monkeypatch
):
    marker = tmp_path / "marker"
    monkeypatch.syspath_prepend(str(_evil_module(tmp_path, marker)))
    folder = tmp_path / "shared_encoder"
    shutil.copytree(FORMAT2 / "raw", folder)
    for name in ("encoder.json", "fit.json"):
        description = json.loads((folder / name).read_text())
        (folder / name).write_text(json.dumps({**description, "method": "evil_methods:method"}))
    line = _refused(lambda: load_encoder(folder), "evil_methods:method", "nothing imported")
    assert "plugins=['evil_methods:method']" in line and not marker.exists()
    # Named by the caller, the module is imported (and its state types admitted).
    with pytest.raises(UserError):
        load_encoder(folder, plugins=["evil_methods:method"])  # its object is no method
    assert marker.exists()
    sys.modules.pop("evil_methods", None)


# Pickle payloads: what an object array's pickle can name to run a command.
class _System:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


class _Popen(_System):
    def __reduce__(self):
        return subprocess.Popen, (["touch", str(self.marker)],)


class _Eval(_System):
    def __reduce__(self):
        return eval, (f"open({str(self.marker)!r}, 'w')",)


def _npy_of(path: Path, payload) -> Path:
    """``path`` written as numpy writes an object array, with ``payload`` as the array."""
    with open(path, "wb") as f:
        header = {"descr": "|O", "fortran_order": False, "shape": (1,)}
        np.lib.format.write_array_header_1_0(f, header)
        pickle.dump(payload, f, protocol=3)
    return path


def _nested(marker: Path) -> np.ndarray:
    table = np.empty(1, dtype=object)
    table[0] = (0, [1, _System(marker)])
    return table


@pytest.mark.parametrize(
    "payload, asked",
    [
        (_System, "system"),
        (_Popen, "subprocess.Popen"),
        (_Eval, "builtins.eval"),
        (_nested, "system"),
    ],
    ids=["os.system", "subprocess", "builtins.eval", "nested in an object array"],
)
def test_a_pickle_payload_in_an_object_array_is_refused_unrun(tmp_path, payload, asked):
    marker = tmp_path / "marker"
    path = _npy_of(tmp_path / "ground_truth_new.npy", payload(marker))
    _refused(lambda: read_object_array(path, str(path), "the fix"), asked, "nothing run")
    assert not marker.exists()


def test_an_object_array_claiming_more_elements_than_its_file_is_refused(tmp_path):
    """numpy takes an object array's claimed memory before reading its elements."""
    table = np.empty(2, dtype=object)
    table[:] = [(0, [1]), (1, [2])]
    state = table.__reduce__()[2]
    forged = (state[0], (1 << 40,), *state[2:])
    reduced = (table.__reduce__()[0], table.__reduce__()[1], forged)

    class Forged:
        def __reduce__(self):
            return reduced

    path = _npy_of(tmp_path / "ground_truth_new.npy", Forged())
    _refused(lambda: read_object_array(path, str(path), "the fix"), "in a smaller file")


@pytest.mark.parametrize("name", ["ground_truth_lists.npy", "ground_truth_arrays.npy"])
def test_ground_truth_written_by_numpy_1_reads_as_numpy_reads_it(name):
    """Files numpy 1.26 wrote (``numpy.core.multiarray``), rows of lists or of arrays."""
    path = NUMPY1 / name
    mine = read_object_array(path, str(path), "the fix")
    theirs = np.load(path, allow_pickle=True)
    assert mine.shape == theirs.shape and mine.dtype == theirs.dtype
    for a, b in zip(mine.reshape(-1), theirs.reshape(-1), strict=True):
        assert np.array_equal(np.asarray(a, dtype=object), np.asarray(b, dtype=object))


def test_a_vpr_bench_ground_truth_of_numpy_1_scores_as_before(tmp_path):
    """The same benchmark scored with the file numpy 2 writes and with each of numpy 1's."""
    from tests.inputs import write_vpr_bench
    from vpr_jax.data.synthetic import synthetic_route

    root = tmp_path / "bench"
    write_vpr_bench(root, synthetic_route(120, ("summer", "fall"), seed=0), drop_rows={7})
    results = {}
    for name in ("numpy 2", "ground_truth_lists.npy", "ground_truth_arrays.npy"):
        if name != "numpy 2":
            shutil.copy(NUMPY1 / name, root / "ground_truth_new.npy")
        logdir = tmp_path / name.replace(" ", "_") / "runs"
        proc = run_here(
            "data.source=vpr_bench", f"data.root={root}", "methods=[raw]", f"logdir={logdir}"
        )
        assert proc.returncode == 0, proc.stderr[-2000:]
        results[name] = (logdir / "results.csv").read_text().splitlines()[1].split(",")
    columns = (tmp_path / "numpy_2" / "runs" / "results.csv").read_text().splitlines()[0]
    kept = [i for i, c in enumerate(columns.split(",")) if "seconds" not in c and "ms" not in c]
    first = [results["numpy 2"][i] for i in kept]
    for name, row in results.items():
        assert [row[i] for i in kept] == first, name


def test_a_vpr_bench_with_a_payload_is_refused_in_one_line_and_nothing_written(tmp_path):
    from tests.inputs import write_vpr_bench
    from vpr_jax.data.synthetic import synthetic_route

    marker, root = tmp_path / "marker", tmp_path / "bench"
    write_vpr_bench(root, synthetic_route(120, ("summer", "fall"), seed=0))
    _npy_of(root / "ground_truth_new.npy", _nested(marker))
    logdir = tmp_path / "runs"
    proc = run_here("data.source=vpr_bench", f"data.root={root}", f"logdir={logdir}")
    assert_one_line_error(proc, "ground_truth_new.npy asks for", "nothing run")
    assert not marker.exists() and not logdir.exists()


def test_an_npy_header_claiming_more_than_its_file_is_refused(tmp_path):
    from vpr_jax.data.precomputed import open_descriptors

    path = tmp_path / "descriptors.npy"
    with open(path, "wb") as f:
        header = {"descr": "<f4", "fortran_order": False, "shape": (1 << 20, 1 << 20)}
        np.lib.format.write_array_header_1_0(f, header)
        f.write(b"\0" * 64)
    _refused(lambda: open_descriptors(path, "precomputed.x.database"), "claims an array")


def test_a_video_cache_with_a_compressed_member_is_refused(tmp_path):
    """A deflated member could inflate past any size its file suggests."""
    from vpr_jax.data.nordland_video import _load_cache

    path = tmp_path / "cache.npz"
    np.savez_compressed(path, frames=np.zeros((4, 32, 64), np.uint8), frame_ids=np.arange(4))
    assert zipfile.ZipFile(path).infolist()[0].compress_type == zipfile.ZIP_DEFLATED
    _refused(lambda: _load_cache(path), "compressed")
    np.savez(path, frames=np.zeros((4, 32, 64), np.uint8), frame_ids=np.arange(4))
    frames, ids = _load_cache(path)  # as the sweep writes it: stored
    assert frames.shape == (4, 32, 64) and list(ids) == [0, 1, 2, 3]


def test_a_compile_cache_others_may_write_to_is_refused(tmp_path):
    import jax

    from vpr_jax.compile_cache import unsafe, use

    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    assert unsafe(shared) == f"{shared} may be written by others (mode 777)"
    session_cache = jax.config.jax_compilation_cache_dir  # the test session's, set for JAX
    jax.config.update("jax_compilation_cache_dir", None)
    try:
        _refused(lambda: use(str(shared)), "compile_cache=", "not yours alone", "mode 777")
        assert jax.config.jax_compilation_cache_dir is None
    finally:
        jax.config.update("jax_compilation_cache_dir", session_cache)
    shared.chmod(0o1777)  # sticky, as /tmp: others cannot move what is yours
    assert unsafe(shared) is None
    own = tmp_path / "own"
    own.mkdir(mode=0o755)
    assert unsafe(own) is None


def _logdir_copy(small_sweep, tmp_path: Path) -> Path:
    logdir, _ = small_sweep
    copy = tmp_path / logdir.name
    shutil.copytree(logdir, copy, ignore=shutil.ignore_patterns(".lock"))
    return copy


def _edit_config(logdir: Path, edit) -> None:
    import yaml

    config = yaml.safe_load((logdir / "config.yaml").read_text())
    edit(config)
    (logdir / "config.yaml").write_text(yaml.safe_dump(config))


def _export(logdir: Path, out: Path, capsys) -> subprocess.CompletedProcess:
    """``python -m experiments.export LOGDIR out=OUT`` by its ``main``, in this process."""
    from experiments import export

    capsys.readouterr()
    code = export.main([str(logdir), f"out={out}"])
    captured = capsys.readouterr()
    return subprocess.CompletedProcess(["export"], code, captured.out, captured.err)


def test_a_logdir_naming_a_module_imports_nothing_on_resume_or_export(
    small_sweep, tmp_path, monkeypatch, capsys
):
    marker = tmp_path / "marker"
    theirs = _evil_module(tmp_path, marker)
    logdir = _logdir_copy(small_sweep, tmp_path)
    _edit_config(logdir, lambda c: c["methods"].append("evil_methods:method"))
    monkeypatch.syspath_prepend(str(theirs))  # importable, as PYTHONPATH would make it
    proc = _export(logdir, tmp_path / "out", capsys)
    line = assert_one_line_error(proc, "evil_methods:method", "nothing was imported")
    assert "plugins=evil_methods:method" in line
    assert not marker.exists() and not (tmp_path / "out").exists()
    # Resuming: the command names its own methods; the config's others are never imported.
    from tests.conftest import SMALL

    before = (logdir / "results.csv").read_text()
    proc = run_here(*SMALL, "methods=[raw]", f"logdir={logdir}", path=[theirs])
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert not marker.exists() and (logdir / "results.csv").read_text() == before


def test_a_logdir_with_an_environment_interpolation_is_refused_unresolved(
    small_sweep, tmp_path, monkeypatch, capsys
):
    logdir = _logdir_copy(small_sweep, tmp_path)
    _edit_config(logdir, lambda c: c["data"].update(cache_dir="${oc.env:VPR_SECRET}"))
    monkeypatch.setenv("VPR_SECRET", "hunter2")
    proc = _export(logdir, tmp_path / "out", capsys)
    assert_one_line_error(proc, "interpolation at data.cache_dir", "nothing was resolved")
    assert "hunter2" not in proc.stdout + proc.stderr and not (tmp_path / "out").exists()


def test_the_export_reads_no_folder_outside_the_logdirs_checkpoints(small_sweep, tmp_path, capsys):
    logdir = _logdir_copy(small_sweep, tmp_path)
    listing = (logdir / "encoders.csv").read_text().splitlines()
    elsewhere = tmp_path / "elsewhere"
    shutil.copytree(FORMAT2 / "raw", elsewhere)
    first = listing[1].rsplit(",", 1)[0] + f",{elsewhere}"
    (logdir / "encoders.csv").write_text("\n".join([listing[0], first, *listing[2:]]) + "\n")
    proc = _export(logdir, tmp_path / "out", capsys)
    assert_one_line_error(proc, str(elsewhere), "outside this logdir's checkpoint folder")
    assert not (tmp_path / "out").exists()


def test_the_fixture_folders_are_format_2_and_cover_every_built_in_state_type():
    from vpr_jax.method_table import BUILTIN
    from vpr_jax.methods.state_types import state_types

    folders = [f for f in FORMAT2.iterdir() if f.is_dir()]
    methods = {json.loads((f / "encoder.json").read_text())["method"] for f in folders}
    assert methods == {m.method for m in BUILTIN}
    assert {json.loads((f / "fit.json").read_text())["format"] for f in folders} == {2}
    named = {
        n
        for f in folders
        for n in _class_names(json.loads((f / "state/skeleton.json").read_text()))
    }
    # State types made after the fixture have no folder of an earlier version to load;
    # tests/test_inputs.py saves and loads theirs.
    newer = {
        "vpr_jax.encoders.inputs:InputState",
        "vpr_jax.encoders.inputs:Options",
        "vpr_jax.methods.inputs:WithInput",
    }
    assert newer <= set(state_types())
    assert named == set(state_types()) - newer


def _class_names(skeleton) -> set[str]:
    if isinstance(skeleton, dict):
        own = {v for k, v in skeleton.items() if k in ("namedtuple", "dataclass")}
        return own.union(*(_class_names(v) for v in skeleton.values()))
    if isinstance(skeleton, list):
        return set().union(*(_class_names(v) for v in skeleton))
    return set()


PLUGIN_STATE = """
from typing import NamedTuple

class Edges(NamedTuple):
    mean: object
"""


def test_a_named_methods_state_types_are_rebuilt_and_no_others(tmp_path, monkeypatch):
    """A NamedTuple at the top level of a user's module is rebuilt when the caller names
    the module, and refused when nobody did."""
    import importlib

    from vpr_jax.encoders.fitted_state import restore_state, save_state
    from vpr_jax.methods.state_types import state_types

    (tmp_path / "their_states.py").write_text(PLUGIN_STATE)
    monkeypatch.syspath_prepend(str(tmp_path))
    module = importlib.import_module("their_states")
    try:
        save_state(tmp_path / "state", module.Edges(np.arange(3.0)))
        _refused(lambda: restore_state(tmp_path / "state", state_types()), "their_states:Edges")
        state = restore_state(tmp_path / "state", state_types((module,)))
        assert type(state) is module.Edges and list(state.mean) == [0.0, 1.0, 2.0]
    finally:
        sys.modules.pop("their_states", None)
