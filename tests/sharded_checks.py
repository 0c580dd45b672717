"""Compare every sharded stage with its single-device run; print the differences as JSON.

    XLA_FLAGS=--xla_force_host_platform_device_count=8 python tests/sharded_checks.py [FOLDER]

A helper of tests/test_sharding.py: the virtual devices must exist before JAX starts, so
the checks run in their own process. With FOLDER, the sweep's ``main`` also runs in this
process, twice: ``REFUSED`` into ``logdir=FOLDER/runs`` (a batch that does not split over
the eight devices), reported as ``refusal``, and one pair of the small sweep
into ``FOLDER/eight``, reported as ``eight`` (each: exit code, stdout, stderr).
"""

import contextlib
import io
import json
import re
import sys

import jax
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from tests.conftest import SMALL, TINY_ROUTE
from tests.programs import jaxpr_of, n_products, unpinned
from vpr_jax import sharding
from vpr_jax.config import TrainConfig
from vpr_jax.data.augment import AugmentConfig
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import pca
from vpr_jax.encoders.train import TrainingData, TrainOptions, fit_autoencoder
from vpr_jax.encoders.train_programs import make_optimizer, make_train_step
from vpr_jax.evaluation import matching
from vpr_jax.evaluation.matching import top_k_matches


def max_diff(a, b) -> float:
    diffs = jax.tree.map(lambda u, v: np.abs(np.asarray(u) - np.asarray(v)).max(), a, b)
    return float(max(jax.tree.leaves(diffs)))


def main() -> None:
    mesh = sharding.make_mesh(0)
    rng = np.random.default_rng(0)
    out = {"devices": sharding.mesh_size(mesh)}

    # PCA: 1,003 samples (padded to 1,008 over 8 devices), blocks of 64 rows per device.
    x = rng.random((1003, 300), np.float32)
    one = pca.fit_pca(x, 20, "covariance", block_rows=64)
    split = pca.fit_pca(x, 20, "covariance", block_rows=64, mesh=mesh)
    out["pca_components"] = max_diff(one.components, split.components)
    ratio = np.asarray(one.explained_variance) / np.asarray(split.explained_variance)
    out["pca_variance_rel"] = float(np.max(np.abs(ratio - 1)))
    out["pca_mean"] = max_diff(one.mean, split.mean)

    # Matching: 997 database rows (not a multiple of 8 x block), repeated rows (ties), suffixes.
    q = rng.standard_normal((301, 40)).astype(np.float32)
    db = rng.standard_normal((997, 40)).astype(np.float32)
    db[500], db[900], q[7] = db[3], db[3], db[3]
    s1, i1 = top_k_matches(q, db, 10, starts=(0, 5, 20), block_size=64)
    s2, i2 = top_k_matches(q, db, 10, starts=(0, 5, 20), block_size=64, mesh=mesh)
    out["match_same_indices"] = bool((i1 == i2).all())
    out["match_scores"] = float(np.abs(s1 - s2).max())
    out["match_tie_order"] = i2[0, 7, :3].tolist()  # query 7 equals db rows 3, 500 and 900

    # The sharded programs state float32 as the one-device ones do (test_precision.py).
    sharded = {
        "moments": jaxpr_of(pca._sharded_moments(mesh, 64), x[:1000], np.float32(1000)),
        "top_k": jaxpr_of(
            matching._sharded_top_k(mesh, 10, 64, 301, (0, 5, 20), "float32"),
            q,
            np.zeros((1024, 40), np.float32),
            np.int32(997),
        ),
    }
    out["sharded_products"] = n_products(sharded)
    out["sharded_unpinned"] = sorted(unpinned(sharded))

    # Auto-encoder training, data parallel: batches of 16 (2 per device); the CAE's
    # 32-to-32 convolution takes the custom-gradient path of vpr_jax.encoders.conv.
    # Gradients must agree to rounding. Whole fits are compared with SGD: Adam divides by
    # the root of tiny second moments, so rounding-level gradient differences in nearly
    # dead units become visible steps; SGD keeps them at rounding level.
    images = rng.random((96, 32, 64), np.float32)  # 80 to train on (5 batches), 16 to validate
    settings = TrainConfig(epochs=2, batch_size=16, optimizer="sgd", learning_rate=0.5)
    batch_sharding = NamedSharding(mesh, P(sharding.AXIS))
    for spec in (
        ae.FAESpec(hidden=32),
        ae.CAESpec(channels=(32, 32), kernel_sizes=(3, 3), code_channels=4),
    ):
        name = type(spec).__name__
        graphdef, params = ae.build(spec, jax.random.key(0), (32, 64))

        def grad(params, batch, constrain, graphdef=graphdef):
            if constrain:
                batch = jax.lax.with_sharding_constraint(batch, batch_sharding)
            return jax.grad(lambda p: ae.reconstruction_loss(graphdef, p, batch))(params)

        one = jax.jit(grad, static_argnums=2)(params, images[:16], False)
        split = jax.jit(grad, static_argnums=2)(
            sharding.replicate(params, mesh), sharding.replicate(images[:16], mesh), True
        )
        rel = jax.tree.map(
            lambda u, v: float(
                np.abs(np.asarray(u) - np.asarray(v)).max() / (np.abs(np.asarray(u)).max() + 1e-30)
            ),
            one,
            split,
        )
        out[f"{name}_grad_rel"] = max(jax.tree.leaves(rel))
        a = fit_autoencoder(
            spec,
            TrainingData(images[:80], images[80:]),
            TrainOptions(key=jax.random.key(0), settings=settings),
        )
        b = fit_autoencoder(
            spec,
            TrainingData(images[:80], images[80:]),
            TrainOptions(key=jax.random.key(0), settings=settings, mesh=mesh),
        )
        out[f"{name}_params"] = max_diff(a.params, b.params)
        out[f"{name}_val_loss"] = [a.best_val_loss, b.best_val_loss]
        out[f"{name}_param_devices"] = len(jax.tree.leaves(b.params)[0].sharding.device_set)

    # The compiled step really splits the batch: each device sees 2 of 16 images.
    graphdef, params = ae.build(ae.FAESpec(hidden=32), jax.random.key(0), (32, 64))
    tx = make_optimizer(TrainConfig())
    step = make_train_step(graphdef, tx, AugmentConfig(), mesh)
    params, opt_state = sharding.replicate((params, tx.init(params)), mesh)
    batch = sharding.replicate(images[:16], mesh)
    hlo = step.lower(params, opt_state, batch, jax.random.key(1)).compile().as_text()
    out["step_batch_shapes"] = sorted({int(b) for b in re.findall(r"f32\[(\d+),32,64\]", hlo)})
    out["step_all_reduces"] = hlo.count("all-reduce(")
    if len(sys.argv) > 1:
        folder = sys.argv[1]
        out["refusal"] = sweep_here(*REFUSED, f"logdir={folder}/runs")
        out["eight"] = sweep_here(
            *EIGHT_DEVICE_SWEEP, f"logdir={folder}/eight", f"train.checkpoint_dir={folder}/ck"
        )
    print(json.dumps(out))


# A batch that does not split over the eight devices: the plan refuses it before any fit.
REFUSED = [*TINY_ROUTE, "season_pairs=summer-fall", "methods=[fae]", "train.batch_size=12"]
# One pair of the suite's small sweep (tests/conftest.py SMALL), its methods that use the
# devices (the shared PCA fit, which ica and lda only read, diff_pca's own, the FAE's data
# parallel training; every method's matcher) and the FAE's objective that takes pairs of a
# place's images (benchmarks/cluster.py's two processes train the other):
# test_sharding.py compares its rows with the single-device small sweep's.
EIGHT_DEVICE_SWEEP = [
    *SMALL,
    "season_pairs=summer-fall",
    "methods=[raw,pca,diff_pca,fae]",
    "fae.objective=cross_season",
]


def sweep_here(*args: str) -> list:
    """``python -m experiments.sweep ARGS`` on this process's devices: [exit code, stdout,
    stderr]."""
    from experiments import sweep

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = sweep.main(list(args))
    return [code, out.getvalue(), err.getvalue()]


if __name__ == "__main__":
    main()
