"""Every product the math needs at float32 states its precision (``vpr_jax/precision.py``).

A CPU computes float32 whatever a product asks for, so no numeric test here can see a product
that a GPU would round to TF32. These tests read the programs instead: JAX writes out the
jaxpr of every program it lowers (``jax_dump_ir_to`` with the mode ``jaxpr``), nested calls
inline, and every ``dot_general`` and convolution in them must carry float32 precision
(``Precision.HIGHEST``, or the dot algorithm ``F32_F32_F32``), also with bfloat16 set as
the default, as a user's program may. Whole sweeps are read, not a list of functions, so a
product added anywhere a sweep reaches (a fit, an encoder, a check, the matcher, a user's
method) fails here. The exceptions are the programs the code names
with its reason (``train_programs.PLATFORM_PRECISION``) and the matcher's ``matching.precision=
default``, which asks for the platform's fastest products.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.conftest import TINY_MODELS, TINY_ROUTE, run_here
from tests.inputs import N_PLACES, read_grey, write_vpr_bench
from tests.programs import jaxpr_of, lowered_programs, n_products, unpinned
from vpr_jax import load_encoder
from vpr_jax.data.synthetic import synthetic_route
from vpr_jax.encoders.train_programs import PLATFORM_PRECISION
from vpr_jax.evaluation import sequence
from vpr_jax.evaluation.matching import _top_k_unpadded
from vpr_jax.precision import f32_matmul, float32_products


def test_the_reader_finds_an_unpinned_product_and_passes_a_pinned_one():
    """The check itself can fail: a plain ``a @ b`` is found; the same product at float32,
    or traced inside ``float32_products``, is not."""

    def traced(x):
        with float32_products():
            return x @ x.T

    a = jnp.ones((4, 3))
    programs = {
        "plain": jaxpr_of(jax.jit(lambda x: x @ x.T), a),
        "stated": jaxpr_of(jax.jit(lambda x: f32_matmul(x, x.T)), a),
        "traced": jaxpr_of(jax.jit(traced), a),
    }
    assert n_products(programs) == 3
    assert set(unpinned(programs)) == {"plain"}


SWEEP = [
    *TINY_ROUTE,
    *TINY_MODELS,
    "season_pairs=summer-fall",
    "removed_pcs=3",
    "ica.n_components=8",
    # every PCA solver and whitened PCA (diff_pca: PCA's pixel-space encoding)
    "pca.solver=[covariance,gram,subspace]",
    "pca.subspace_components=40",
    "pca.whiten=[0,4]",
    # the auto-encoders' linear starts, a residual input, a code-only and a decoding objective
    "fae.init=lda",
    "fae.input=residual",
    "fae.objective=contrastive",
    "cae.init=whitened_pca",
    "cae.linear_units=16",
    "cae.objective=cross_season",
    "train.epochs=1",
    "fae.epochs=1",
    "methods=[raw,pca,diff_pca,ica,lda,fae,cae,precision_plugin:mine]",
]

# A user's method whose products state no precision: the runner traces it at float32.
PLUGIN = """
import jax.numpy as jnp


class mine:
    @staticmethod
    def fit(train, aligned, key):
        x = jnp.reshape(train, (len(train), -1))
        return {"basis": jnp.linalg.eigh(x.T @ x / len(x))[1][:, -8:]}

    @staticmethod
    def encode(state, images):
        return jnp.reshape(images, (len(images), -1)) @ state["basis"]
"""


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    """(the programs a tiny sweep of every built-in method and a user's lowers, the folder
    of its logdir ``runs``, its checkpoints and the user's module)."""
    folder = tmp_path_factory.mktemp("precision")
    (folder / "precision_plugin.py").write_text(PLUGIN)
    with lowered_programs() as programs:
        proc = run_here(*SWEEP, f"logdir={folder / 'runs'}", path=[folder])
    assert proc.returncode == 0, proc.stderr[-3000:]
    return programs, folder


def test_every_product_a_sweep_computes_states_float32(swept):
    """Fits (every PCA solver, ICA, lda, diff_pca, the auto-encoders' linear starts), their
    checks, encoders, a user's method, matching and sequence matching: all float32, but the
    training programs the code names. Those are there, and do keep the platform's default,
    so the exemption is not what lets this pass."""
    programs, _ = swept
    assert n_products(programs) > 50
    for name in ("_fit_gram", "_fit_subspace", "_moments", "fastica", "fit_lda", "encode"):
        assert name in programs, sorted(programs)
    assert not unpinned(programs, PLATFORM_PRECISION)
    assert set(unpinned(programs)) == set(PLATFORM_PRECISION)


def test_load_encoder_hands_out_the_float32_encoders_the_sweep_scored(swept, monkeypatch):
    """Every fitted method ``load_encoder`` gives back (a user's too) encodes at float32,
    also inside a program whose own default is the platform's fastest."""
    _, folder = swept
    monkeypatch.syspath_prepend(str(folder))  # the user's module
    folders = sorted(p.parent for p in (folder / "checkpoints").glob("**/fit.json"))
    names = {"pca_solver=gram_whiten=4", "diff_pca", "ica_k003", "lda", "fae_contrastive", "mine"}
    assert {f.name for f in folders} >= names
    images = np.random.default_rng(0).random((3, 32, 64), np.float32)
    programs = {}
    with jax.default_matmul_precision("bfloat16"):
        for path in folders:
            encode, params = load_encoder(path, plugins=["precision_plugin"])  # its module
            programs[path.name] = jaxpr_of(encode, params, images)
    assert n_products(programs) >= len(folders)
    assert not unpinned(programs)


def sequence_blocks(query, db, ds: int, precision: str):
    """Sequence matching's one program (``sequence._sequence_blocks``) on descriptors."""
    stretch = lambda n: jnp.asarray(sequence.stretch_ids(np.arange(n)))  # noqa: E731
    offsets = sequence.trajectory_offsets(ds, sequence.DEFAULT_VELOCITIES)
    return sequence._sequence_blocks(
        query,
        db,
        stretch(len(query)),
        stretch(len(db)),
        **dict(ds=ds, offsets=offsets, window=4, unique=4, k=5, block=8, precision=precision),
    )


def test_matching_precision_default_leaves_the_products_to_the_platform():
    """The matcher's key acts: float32 states it, ``default`` leaves every product of the
    ranking to the platform, single images and sequences alike."""
    rng = np.random.default_rng(1)
    query, db = rng.random((30, 16), np.float32), rng.random((40, 16), np.float32)
    kinds = {}
    for precision in ("float32", "default"):
        blocks = dict(k=5, block_size=16, query_block_size=30, starts=(0, 4))
        ranked = jaxpr_of(
            functools.partial(_top_k_unpadded, **blocks, precision=precision), query, db
        )
        sequences = jaxpr_of(
            functools.partial(sequence_blocks, ds=3, precision=precision), query, db
        )
        kinds[precision] = {"matcher": ranked, "sequence": sequences}
    assert n_products(kinds["float32"]) >= 3 and not unpinned(kinds["float32"])
    assert set(unpinned(kinds["default"])) == {"matcher", "sequence"}


def test_outside_descriptors_are_looked_up_at_float32(tmp_path):
    """The precomputed method's fingerprints (an image's fixed random projection, matched
    within 1e-6 of the fit's) and a benchmark's path are float32 too."""
    route = synthetic_route(N_PLACES, ("summer", "fall"), seed=5)
    refs, queries, _ = write_vpr_bench(tmp_path / "bench", route)
    for side, names in (("ref", refs), ("query", queries)):
        images = np.stack([read_grey(tmp_path / "bench" / side / n) for n in names])
        np.save(tmp_path / f"{side}.npy", images.reshape(len(images), -1)[:, ::7])
    args = [
        "data.source=vpr_bench",
        f"data.root={tmp_path / 'bench'}",
        "methods=[raw,precomputed]",
        f"precomputed.database={tmp_path / 'ref.npy'}",
        f"precomputed.queries={tmp_path / 'query.npy'}",
    ]
    with lowered_programs() as programs:
        proc = run_here(*args, f"logdir={tmp_path / 'runs'}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "encode" in programs and n_products(programs) > 5
    assert not unpinned(programs)
