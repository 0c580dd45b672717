"""A Ray worker's first task (``start``): JAX and BLAS sized as in a process of its own,
then the worker held to its share of the node's cores for its life (Ray reuses a worker
process for task after task).

XLA's CPU client sizes its thread pool from the process's CPU affinity when it starts, and
its reductions (sums, the eigensolver's BLAS) round differently with another count of
threads: measured, the default sweep on one core differs from the 2-core run in 62
validation margins, 16 FastICA iteration counts and one CAE recall@1. So a worker starts
JAX's CPU client and numpy's and scipy's BLAS over every core the node gives it (as one
process on that node would, so the rows are the one process's), and only then narrows its
affinity to its own cores: the pool's threads stay as many, and all of them run there, so
workers side by side do not oversubscribe the node.

Which cores: the node's cores in order, ``share`` to a slot, ``share`` being
``cluster.cores_per_worker`` or else the node's cores over the CPUs Ray gives it (its
worker count). A worker takes the first free slot by an exclusive lock on a file of that
slot (``fcntl.flock``), held for its life: the kernel lets the lock go when the process
ends, so a killed worker's cores are free for its successor. No slot free (Ray started
more workers than slots): the worker is not pinned. Nothing here runs in the driver. (Not
Ray's ``worker_process_setup_hook``: it runs before a worker can import the suite from the
driver's folder, where a user runs it uninstalled.)
"""

from __future__ import annotations

import fcntl
import os
import tempfile
from pathlib import Path

SHARE_ENV = "VPR_JAX_CORES_PER_WORKER"  # the driver's cluster.cores_per_worker, if set

_width = 0  # the node's cores this worker's JAX and BLAS were sized for (0: not started)
_cores: tuple[int, ...] = ()  # the cores it is held to (): not pinned
_lock = None  # the open slot file whose lock holds the cores


def start() -> None:
    """Size JAX and BLAS, then pin (see the module's docstring); once a process, before its
    first task uses JAX."""
    global _width
    if _width:
        return
    import jax
    import scipy.linalg  # noqa: F401  its BLAS, which JAX's LAPACK calls use
    from threadpoolctl import threadpool_limits

    everything = sorted(os.sched_getaffinity(0))
    _width = len(everything)
    jax.devices("cpu")  # XLA's CPU client and its thread pool, over every core
    # Ray starts a worker with OMP_NUM_THREADS=1; a process of its own takes every core
    threadpool_limits(limits=_width, user_api="blas")
    share = _share(_width)
    if share:
        _pin(everything, share)


def width() -> int:
    """The threads a process of its own takes on this node (``start``'s count)."""
    return _width


def cores() -> tuple[int, ...]:
    """The cores this worker is held to; () where it is not pinned."""
    return _cores


def _share(width: int) -> int:
    """Cores a worker on this node takes: ``SHARE_ENV``, else the node's cores over Ray's
    CPUs for it (at least 1); 0: not pinned."""
    given = os.environ.get(SHARE_ENV, "")
    if given:
        return int(given)
    import ray

    here = ray.get_runtime_context().get_node_id()
    cpus = next(
        (node["Resources"].get("CPU", 0) for node in ray.nodes() if node["NodeID"] == here), 0
    )
    return max(1, width // int(cpus)) if cpus >= 1 else 0


def _pin(everything: list[int], share: int) -> None:
    """Take the first free slot of ``share`` cores on this node and hold to them."""
    global _cores, _lock
    import ray

    folder = (
        Path(tempfile.gettempdir())
        / f"vpr_jax-cores-{os.getuid()}"
        / ray.get_runtime_context().get_node_id()
    )
    try:
        folder.mkdir(parents=True, exist_ok=True, mode=0o700)
        for slot in range(max(1, len(everything) // share)):
            handle = open(folder / f"slot-{slot}", "a")  # noqa: SIM115  held for life
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                handle.close()
                continue
            _lock, _cores = handle, tuple(everything[slot * share : (slot + 1) * share])
            _hold_every_thread(_cores)
            return
    except OSError:
        return  # a folder not ours, or a full disk: unpinned, as Ray leaves it


def _hold_every_thread(cores: tuple[int, ...]) -> None:
    """Every thread of this process held to ``cores``: an affinity is a thread's own, and
    XLA's pool, BLAS's and Ray's threads exist already (threads made later inherit it)."""
    for task in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(task), cores)
        except OSError:
            pass  # a thread that ended meanwhile
