"""A Ray worker's threads and cores (``cluster.threads``, ``cluster.cores_per_worker``).

XLA's CPU client sizes its thread pool from the process's CPU affinity when it starts, and
its reductions (sums, the eigensolver's BLAS) round differently with another count of
threads: measured, the default sweep on one core differs from the 2-core run in 62
validation margins, 16 FastICA iteration counts and one CAE recall@1. Ray starts a worker
with one BLAS thread (OMP_NUM_THREADS=1), which changes eigh's last bits as well. Two modes:

- ``threads=node`` (the default): at its first task (``start``), a worker starts JAX's CPU
  client and numpy's and scipy's BLAS over every core the node gives it, as one process on
  that node would, so the rows are the one process's. Only then, if ``cores_per_worker``
  asks, it holds every one of its threads to its share of the cores: as many threads, fewer
  cores (on 2 cores, measured, that is slower than leaving the workers unpinned: threads
  that wait for work spin).
- ``threads=share``: before it imports JAX (Ray's ``worker_process_setup_hook``,
  ``start_on_share``), a worker holds itself to its share and starts JAX and BLAS there:
  no thread waits on another's core, the fastest, and the numbers are those of one process
  given that many cores (``taskset -c 0 python -m experiments.sweep ...`` for one).

Which cores: the node's cores in order, ``share`` to a slot, ``share`` being
``cluster.cores_per_worker`` or else the node's cores over the CPUs Ray gives it (its worker
count). A worker takes the first free slot by an exclusive lock on a file of that slot
(``fcntl.flock``), held for its life: the kernel lets the lock go when the process ends, so
a killed worker's cores are free for its successor. No slot free (Ray started more workers
than slots): the worker is not pinned. What a worker chose is kept in its environment
(``WIDTH_ENV``, ``CORES_ENV``), so the setup hook, which Ray runs before the worker can
import the suite from the driver's folder and which therefore travels by value, and the
tasks that read it agree. Nothing here runs in the driver.
"""

from __future__ import annotations

import fcntl
import os
import tempfile

SHARE_ENV = "VPR_JAX_CORES_PER_WORKER"  # the driver's cluster.cores_per_worker ("": none)
WIDTH_ENV = "VPR_JAX_WORKER_THREADS"  # the threads this worker's JAX and BLAS started with
CORES_ENV = "VPR_JAX_WORKER_CORES"  # the cores it holds, comma-separated ("": not pinned)


def start() -> None:
    """``threads=node``: JAX and BLAS over every core, then held to the share (if
    ``cores_per_worker`` names one); once a process, before its first task uses JAX.
    Nothing to do where the setup hook (``start_on_share``) ran."""
    if WIDTH_ENV in os.environ:
        return
    everything = sorted(os.sched_getaffinity(0))
    _start_jax(len(everything))
    share = int(os.environ.get(SHARE_ENV) or 0)
    os.environ[CORES_ENV] = ""
    if share:
        _pin(everything, share)


def start_on_share() -> None:
    """``threads=share`` (Ray's setup hook, before the worker imports JAX): held to its
    share first, then JAX and BLAS on it."""
    everything = sorted(os.sched_getaffinity(0))
    share = int(os.environ.get(SHARE_ENV) or 0) or _node_share(len(everything))
    os.environ[CORES_ENV] = ""
    if share:
        _pin(everything, share)
    _start_jax(len(os.sched_getaffinity(0)))


def width() -> int:
    """The threads this worker's JAX and BLAS started with (0: not started)."""
    return int(os.environ.get(WIDTH_ENV) or 0)


def cores() -> tuple[int, ...]:
    """The cores this worker is held to; () where it is not pinned."""
    return tuple(int(c) for c in os.environ.get(CORES_ENV, "").split(",") if c)


def _start_jax(threads: int) -> None:
    """XLA's CPU client and its thread pool, and BLAS, with ``threads`` threads."""
    import jax
    import scipy.linalg  # noqa: F401  its BLAS, which JAX's LAPACK calls use
    from threadpoolctl import threadpool_limits

    jax.devices("cpu")
    threadpool_limits(limits=threads, user_api="blas")
    os.environ[WIDTH_ENV] = str(threads)


def _node_share(width: int) -> int:
    """The node's cores over the CPUs Ray gives it (at least 1); 0 where Ray says none."""
    import ray

    here = ray.get_runtime_context().get_node_id()
    cpus = next(
        (node["Resources"].get("CPU", 0) for node in ray.nodes() if node["NodeID"] == here), 0
    )
    return max(1, width // int(cpus)) if cpus >= 1 else 0


def _pin(everything: list[int], share: int) -> None:
    """Take the first free slot of ``share`` cores on this node and hold to them (the
    slot's lock is a file descriptor left open for the process's life)."""
    import ray

    folder = os.path.join(
        tempfile.gettempdir(),
        f"vpr_jax-cores-{os.getuid()}",
        ray.get_runtime_context().get_node_id(),
    )
    try:
        os.makedirs(folder, mode=0o700, exist_ok=True)
        for slot in range(max(1, len(everything) // share)):
            lock = os.open(os.path.join(folder, f"slot-{slot}"), os.O_CREAT | os.O_WRONLY, 0o600)
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(lock)
                continue
            held = everything[slot * share : (slot + 1) * share]
            _hold_every_thread(held)
            os.environ[CORES_ENV] = ",".join(map(str, held))
            return
    except OSError:
        return  # a folder not ours, or a full disk: unpinned, as Ray leaves it


def _hold_every_thread(cores: list[int]) -> None:
    """Every thread of this process held to ``cores``: an affinity is a thread's own, and
    XLA's pool, BLAS's and Ray's threads may exist already (threads made later inherit it)."""
    for task in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(task), cores)
        except OSError:
            pass  # a thread that ended meanwhile
