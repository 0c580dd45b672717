"""One of several processes that compute one sharded similarity together on loopback.

    python tests/loopback_worker.py PORT N_PROCESSES PROCESS_ID OUT.npz

Each process has 2 CPU devices; ``jax.distributed.initialize`` joins them into one mesh
over every process's devices, the database is split across that mesh, and process 0 saves
the top-10 matches it got. A helper of tests/test_sharding.py.
"""

import os
import sys

os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"

import jax  # noqa: E402
import numpy as np  # noqa: E402

from vpr_jax import sharding  # noqa: E402
from vpr_jax.evaluation.matching import top_k_matches  # noqa: E402


def main() -> None:
    port, n_processes, process_id, out = sys.argv[1:]
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(f"127.0.0.1:{port}", int(n_processes), int(process_id))
    mesh = sharding.make_mesh(0)
    # Every process builds the same data (as every sweep process loads the same route).
    rng = np.random.default_rng(0)
    query = rng.standard_normal((50, 64)).astype(np.float32)
    db = rng.standard_normal((301, 64)).astype(np.float32)
    scores, indices = top_k_matches(query, db, 10, block_size=16, mesh=mesh)
    scores, indices = scores[0], indices[0]  # the one suffix start: all features
    if jax.process_index() == 0:
        np.savez(
            out,
            scores=scores,
            indices=indices,
            query=query,
            db=db,
            devices=sharding.mesh_size(mesh),
            processes=jax.process_count(),
        )
    jax.distributed.shutdown()


if __name__ == "__main__":
    main()
