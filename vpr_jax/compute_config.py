"""Where and how the numbers are computed (never which numbers): the matcher's blocks and
precision, the devices of one cell (``mesh.*``, JAX's SPMD), and the machines a sweep's fits
spread over (``cluster.*``, a Ray cluster). A logdir may change these between runs
(``vpr_jax.outputs.logdir.EXTENDABLE_KEYS``). No JAX here.
"""

from __future__ import annotations

from dataclasses import dataclass

from vpr_jax.errors import UserError

MATCHING_PRECISIONS = ("float32", "default")
CLUSTER_THREADS = ("node", "share")  # experiments.cluster_worker


def check(ok: bool, message: str) -> None:
    if not ok:
        raise UserError(message)


@dataclass(frozen=True)
class MatchingConfig:
    block_size: int = 4096  # database images scored at once; bounds memory on long routes
    # float32: every score as a CPU computes it; default: the platform's fastest products
    # (TF32 on recent NVIDIA GPUs: faster, close scores can swap). Encoders are float32 always.
    precision: str = "float32"

    def __post_init__(self):
        check(self.block_size >= 1, f"matching.block_size={self.block_size} must be >= 1")
        check(
            self.precision in MATCHING_PRECISIONS,
            f"matching.precision={self.precision} is not "
            f"{' or '.join(MATCHING_PRECISIONS)}: use float32 (every score as a CPU computes "
            "it) or default (the platform's fastest products)",
        )


@dataclass(frozen=True)
class MeshConfig:
    """Devices the work is split over (``vpr_jax.sharding``): PCA samples, the matching
    database and each training batch. Results equal one device's up to float rounding."""

    devices: int = 0  # 0: every device JAX sees (one: plain single-device code); N: first N
    # Several processes (one per host): jax.distributed.initialize() before anything else.
    # Leave the three below unset under SLURM, Open MPI and other launchers JAX detects.
    distributed: bool = False
    coordinator: str | None = None  # host:port of process 0, e.g. 10.0.0.1:1234
    num_processes: int | None = None
    process_id: int | None = None  # 0 .. num_processes - 1; process 0 writes the logdir

    def __post_init__(self):
        check(
            self.devices >= 0,
            f"mesh.devices={self.devices} is negative: use 0 (all devices), 1, or a count",
        )
        explicit = (self.coordinator, self.num_processes, self.process_id)
        check(
            self.distributed or all(v is None for v in explicit),
            "mesh.coordinator/num_processes/process_id need mesh.distributed=true",
        )
        check(
            all(v is None for v in explicit) or None not in explicit,
            "set all of mesh.coordinator, mesh.num_processes and mesh.process_id, or none "
            "(a launcher JAX detects, such as SLURM, fills them in)",
        )


@dataclass(frozen=True)
class ClusterConfig:
    """The machines a sweep's fits run on (``experiments.cluster``, docs/scaling.md "Many
    machines"): each fit with its cells is a Ray task; this process plans, validates and
    writes the logdir. The numbers are the one process's."""

    # null: this process alone; local: a Ray cluster started here with ``workers`` workers;
    # auto, HOST:PORT or ray://HOST:PORT: the running cluster there
    address: str | None = None
    workers: int = 2  # local only: worker processes, one CPU each
    gpus_per_fit: float = 0.0  # what a fit that trains asks of a node's GPUs (0: none)
    # node: each worker's JAX and BLAS take every core of its node, as one process there
    # would (the one process's numbers); share: only the worker's own cores, held before
    # JAX starts (faster; the numbers of one process given that many cores)
    threads: str = "node"
    # cores each worker is held to (experiments.cluster_worker); null: none with threads=
    # node, a node's cores over its Ray CPUs with threads=share; 0: not pinned
    cores_per_worker: int | None = None

    def __post_init__(self):
        check(self.workers >= 1, f"cluster.workers={self.workers} must be at least 1")
        check(
            self.gpus_per_fit >= 0,
            f"cluster.gpus_per_fit={self.gpus_per_fit} is negative: use 0 (CPU) or a share",
        )
        check(
            self.threads in CLUSTER_THREADS,
            f"cluster.threads={self.threads} is unknown: use node (the one process's numbers) "
            "or share (each worker's JAX on its own cores)",
        )
        check(
            not (self.threads == "share" and self.cores_per_worker == 0),
            "cluster.threads=share holds each worker to its cores, which "
            "cluster.cores_per_worker=0 turns off: give a count, or leave it unset",
        )
        check(
            self.cores_per_worker is None or self.cores_per_worker >= 0,
            f"cluster.cores_per_worker={self.cores_per_worker} is negative: use null (a "
            "node's cores shared among its workers), 0 (not pinned) or a count",
        )
        check(
            self.address is None or self.address.strip() != "",
            "cluster.address is empty: use null (this process), local, auto, HOST:PORT or "
            "ray://HOST:PORT",
        )
