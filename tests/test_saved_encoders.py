"""Every fitted method is an encoder you can take away: a finished sweep saves each one,
``vpr_jax.load_encoder`` gives it back as a pure jitted ``(encode_fn, params)`` that scores
the sweep's test places as the sweep did, and damaged or foreign folders are one clear
error."""

import csv
import json
import re
import shutil
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.conftest import SMALL, assert_one_line_error, run_process
from vpr_jax import load_encoder
from vpr_jax.errors import UserError
from vpr_jax.method_table import NAMES


def _listing(logdir) -> list[dict]:
    with open(logdir / "encoders.csv", newline="") as f:
        return list(csv.DictReader(f))


def _folder(logdir, pair: str, method: str, objective: str = ""):
    (entry,) = [
        e
        for e in _listing(logdir)
        if (e["pair"], e["method"], e["objective"]) == (pair, method, objective)
    ]
    return entry["folder"]


def test_a_fresh_process_scores_every_saved_encoder_as_the_sweep_did(small_sweep):
    logdir, _ = small_sweep
    listing = _listing(logdir)
    # Every method of every pair, both objectives of each auto-encoder, ICA once per count.
    per_pair = len(NAMES) + 2 + 1 + 1
    assert {e["method"] for e in listing} == set(NAMES) and len(listing) == 3 * per_pair
    proc = run_process(
        [sys.executable, "tests/saved_encoder_checks.py", str(logdir), "summer-fall", *SMALL]
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    checks = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(checks) == per_pair  # the pair's encoders
    for folder, check in checks.items():
        # Each query's best cosine score is the one the sweep recorded, so its recall@1 too.
        assert check["score_gap"] < 1e-5, (folder, check)
        assert check["recall_at_1"] == check["sweep_recall_at_1"], (folder, check)


def test_the_description_says_what_was_fitted_and_chosen(small_sweep):
    logdir, _ = small_sweep
    with open(f"{_folder(logdir, 'summer-fall', 'pca')}/encoder.json") as f:
        pca = json.load(f)
    k = pca["swept"]["removed_pcs"]
    served = [cell["served"] for cell in pca["cells"]]
    assert served == [{"removed_pcs": c} for c in (0, 5, 20)] and k in (0, 5, 20)
    assert pca["chosen"] == {"removed_pcs": k} and pca["cell"] == f"removed_pcs={k}"
    by_served = pca["val_recall_at_1_by_served"]
    assert set(by_served) == {f"removed_pcs={c}" for c in (0, 5, 20)}
    assert pca["val_recall_at_1"] == max(by_served.values())  # the validation's choice
    assert pca["run"] == f"summer-fall/pca_k{k:03d}"
    assert pca["preprocessing"]["patchnorm"] is None and pca["name"] == "pca"
    assert pca["method"] == "vpr_jax.methods.pca:method" and pca["model"] == "pca"
    with open(f"{_folder(logdir, 'summer-fall', 'fae', 'cross_season')}/encoder.json") as f:
        fae = json.load(f)
    assert (fae["method"], fae["objective"], fae["swept"]) == (
        "vpr_jax.methods.fae:method",
        "cross_season",
        {},
    )
    assert fae["settings"]["objective"] == "cross_season"
    assert [cell["served"] for cell in fae["cells"]] == [{}]


@pytest.fixture(scope="module")
def pca_encoder(small_sweep):
    logdir, _ = small_sweep
    return _folder(logdir, "summer-fall", "pca")


def test_an_encoder_is_pure_and_works_inside_jit_vmap_and_grad(pca_encoder):
    encode, params = load_encoder(pca_encoder, removed_pcs=5)
    images = jnp.asarray(np.random.default_rng(0).random((6, 32, 64), np.float32))
    eager = encode(params, images)
    assert eager.shape[0] == 6 and jnp.isfinite(eager).all()

    @jax.jit
    def similarity(params, a, b):  # someone else's jitted function
        da, db = encode(params, a), encode(params, b)
        return (da / jnp.linalg.norm(da, axis=1, keepdims=True)) @ (
            db / jnp.linalg.norm(db, axis=1, keepdims=True)
        ).T

    assert jnp.allclose(jnp.diag(similarity(params, images, images)), 1.0, atol=1e-5)
    batched = jax.vmap(encode, in_axes=(None, 0))(params, images.reshape(2, 3, 32, 64))
    np.testing.assert_allclose(batched.reshape(6, -1), eager, rtol=1e-5, atol=1e-5)
    grad = jax.grad(lambda x: jnp.sum(encode(params, x) ** 2))(images)
    assert grad.shape == images.shape and jnp.isfinite(grad).all() and jnp.abs(grad).sum() > 0


def test_a_removed_count_is_the_suffix_of_one_fit(pca_encoder):
    full, params = load_encoder(pca_encoder, removed_pcs=0)
    five, _ = load_encoder(pca_encoder, removed_pcs=5)
    images = np.random.default_rng(1).random((4, 32, 64), np.float32)
    np.testing.assert_array_equal(five(params, images), full(params, images)[:, 5:])
    with pytest.raises(UserError, match=r"serves removed_pcs \[0, 5, 20\], not 7"):
        load_encoder(pca_encoder, removed_pcs=7)


def test_folders_that_hold_no_whole_encoder_are_one_clear_error(pca_encoder, tmp_path):
    with pytest.raises(UserError, match="holds no encoder.*encoder.json is missing"):
        load_encoder(tmp_path)
    damaged = shutil.copytree(pca_encoder, tmp_path / "damaged")
    for path in (damaged / "state" / "arrays").rglob("*"):
        if path.is_file() and path.stat().st_size > 1000:
            path.write_bytes(path.read_bytes()[:100])  # cut short, as by a full disk
    with pytest.raises(UserError, match="damaged or incomplete fitted state.*rerun the sweep"):
        load_encoder(damaged)
    with pytest.raises(UserError, match=r"state \(arrays/\S+ has 100 bytes, saved with \d+\)"):
        load_encoder(damaged)  # the file cut short, found before orbax reads (see below)
    newer = shutil.copytree(pca_encoder, tmp_path / "newer")
    description = json.loads((newer / "encoder.json").read_text())
    (newer / "encoder.json").write_text(json.dumps({**description, "format": 99}))
    with pytest.raises(UserError, match="format 99, this suite reads 2: update vpr_jax"):
        load_encoder(newer)


def test_a_cut_short_state_is_refused_before_orbax_reads_it_and_orbax_is_always_closed(
    pca_encoder, tmp_path, monkeypatch
):
    """Orbax reads the leaves concurrently and, when one read fails, closes its event loop
    while the others are in flight: those report to the closed loop from TensorStore's
    threads after the error (``RuntimeError: Event loop is closed``, an unraisable exception
    pytest warns of). So a state whose files were cut short is refused from the sizes saved
    beside them, without asking orbax; and the checkpointer orbax reads with is closed,
    also when it raises."""
    import orbax.checkpoint as ocp

    def never(*args, **kwargs):
        pytest.fail("orbax was asked to read a cut-short state")

    cut = shutil.copytree(pca_encoder, tmp_path / "cut")
    files = [p for p in (cut / "state" / "arrays").rglob("*") if p.is_file()]
    biggest = max(files, key=lambda p: p.stat().st_size)
    biggest.write_bytes(biggest.read_bytes()[:-1])
    monkeypatch.setattr(ocp.Checkpointer, "restore", never)
    with pytest.raises(UserError, match=rf"{biggest.name} has \d+ bytes, saved with \d+\): rerun"):
        load_encoder(cut)

    def fault(*args, **kwargs):
        raise ValueError("DATA_LOSS: simulated read fault")

    closed = []
    close = ocp.Checkpointer.close
    monkeypatch.setattr(ocp.Checkpointer, "restore", fault)
    monkeypatch.setattr(ocp.Checkpointer, "close", lambda self: closed.append(close(self)))
    with pytest.raises(UserError, match=r"\(ValueError: DATA_LOSS: simulated read fault\)"):
        load_encoder(pca_encoder)
    assert len(closed) == 1


def test_a_model_name_no_fit_of_the_pair_has_is_one_line_naming_the_pair_s_folders(
    small_sweep, tmp_path
):
    """``<pair>/fae`` when the sweep ran ``fae.objective=[cross_season]`` alone (the paper's
    objective, whose folder is ``fae``, not among them): one line naming the folders the pair
    has, and the one named loads."""
    logdir, _ = small_sweep
    saved = Path(_folder(logdir, "summer-fall", "fae", "cross_season"))
    pair = tmp_path / "summer-fall"
    shutil.copytree(saved, pair / saved.name, ignore=shutil.ignore_patterns("training"))
    assert saved.name == "fae_cross_season"
    asked = re.escape(str(pair / "fae"))
    with pytest.raises(
        UserError,
        match=rf"^no fitted encoder in {asked}: this pair's folders are fae_cross_season: "
        "pass one of them",
    ):
        load_encoder(pair / "fae")
    encode, params = load_encoder(pair / "fae_cross_season")
    assert encode(params, np.zeros((2, 32, 64), np.float32)).shape[0] == 2


def test_the_listing_command_names_every_encoder_and_refuses_other_folders(small_sweep, tmp_path):
    logdir, _ = small_sweep
    proc = run_process([sys.executable, "-m", "experiments.encoders", str(logdir)])
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert lines[0].split() == ["pair", "method", "setting", "val", "recall@1", "chosen", "folder"]
    assert len(lines) == 1 + len(_listing(logdir)) and "(missing)" not in proc.stdout
    assert any("ica" in line and "removed_pcs=20" in line for line in lines)
    refused = run_process([sys.executable, "-m", "experiments.encoders", str(tmp_path)])
    assert_one_line_error(refused, "has no encoders.csv", "python -m experiments.encoders")
