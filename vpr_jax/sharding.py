"""Where arrays live when there are several devices: one mesh axis, ``data``, over all of them.

The suite splits one axis per stage across the mesh, with JAX's own SPMD (``NamedSharding``,
``jax.shard_map``), never a scheduler of ours:

- PCA: the training samples, for the covariance (each device sums its rows, one ``psum``);
- matching: the database, for the running top-K (each device keeps the K best of its part,
  the K-lists are gathered and merged);
- auto-encoder training: the batch (parameters replicated, gradients all-reduced by XLA).

A mesh spans every device JAX sees, those of other processes too once
``jax.distributed.initialize`` has run, so the same code serves one GPU, eight, or several
hosts. Arrays enter the mesh through ``jax.make_array_from_callback``, for which every
process passes the same whole host array (each process has loaded the same data).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import AxisType, Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from vpr_jax import host_arrays
from vpr_jax.compute_config import MeshConfig
from vpr_jax.errors import UserError, first_line

AXIS = "data"


def make_mesh(devices: int = 0) -> Mesh | None:
    """A one-axis mesh over ``devices`` devices; ``None`` means plain single-device code.

    ``devices=0`` takes every device when there are several (``None`` when there is one);
    ``devices=1`` always gives ``None``; ``devices=N`` takes the first N of ``jax.devices()``.
    """
    available = jax.devices()
    if devices < 0:
        raise ValueError(f"mesh.devices={devices} is negative: use 0 (all), 1, or a count")
    if devices > len(available):
        raise ValueError(
            f"mesh.devices={devices} but JAX sees {len(available)} "
            f"{available[0].platform} device(s): use mesh.devices=0 for all of them"
        )
    n = devices or len(available)
    if n == 1:
        return None
    # Auto axes: XLA propagates the batch sharding through the training step by itself.
    return jax.make_mesh((n,), (AXIS,), axis_types=(AxisType.Auto,), devices=available[:n])


def start_devices(cfg: MeshConfig, log: Callable[[str], Any]) -> Mesh | None:
    """Join the other processes (``mesh.distributed``), then build the device mesh: before
    the methods' checks, which ask how many devices a batch splits over."""
    if cfg.distributed:
        # CPU devices of several processes talk through gloo; GPUs use NCCL regardless.
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        try:
            jax.distributed.initialize(cfg.coordinator, cfg.num_processes, cfg.process_id)
        except (RuntimeError, ValueError) as err:
            raise UserError(
                f"mesh.distributed=true could not join the other processes ({first_line(err)}): "
                "start one process per host under a launcher JAX detects (SLURM, Open MPI), or "
                "set mesh.coordinator=HOST:PORT, mesh.num_processes and mesh.process_id"
            ) from None
    try:
        mesh = make_mesh(cfg.devices)
    except ValueError as err:
        raise UserError(str(err)) from None
    if mesh is not None:
        devices = mesh.devices.flat
        log(
            f"mesh: {mesh_size(mesh)} {devices[0].platform} devices in "
            f"{jax.process_count()} process(es); PCA samples, matching database and "
            "training batches are split over them"
        )
    return mesh


def mesh_size(mesh: Mesh | None) -> int:
    return 1 if mesh is None else mesh.shape[AXIS]


def pad_rows(x, multiple: int):
    """``x`` (numpy or JAX) with zero rows appended up to a multiple of ``multiple``."""
    extra = -len(x) % multiple
    if not extra:
        return x
    xp = jnp if isinstance(x, jax.Array) else np
    return xp.concatenate([x, xp.zeros((extra, *x.shape[1:]), x.dtype)])


def put(x: np.ndarray, mesh: Mesh, spec: P) -> jax.Array:
    """A host array onto the mesh with ``spec``; each device receives only its part."""
    x = np.asarray(x)
    return jax.make_array_from_callback(x.shape, NamedSharding(mesh, spec), lambda i: x[i])


def put_rows(x: np.ndarray, mesh: Mesh) -> jax.Array:
    """Rows split across the mesh (rows must divide evenly: see ``pad_rows``)."""
    return put(x, mesh, P(AXIS))


def replicate(tree, mesh: Mesh):
    """Every leaf of a pytree copied to every device of the mesh."""
    return jax.tree.map(lambda leaf: put(np.asarray(leaf), mesh, P()), tree)


def on_device(x) -> jax.Array:
    """float32 ``x`` on the default device: a JAX array as it is; a host array by
    ``device_put``, which on a CPU reads a 64-byte-aligned array in place
    (``vpr_jax.host_arrays``; any other is copied once, as ``jnp.asarray`` copies even an
    aligned one)."""
    if isinstance(x, jax.Array):
        return x.astype(jnp.float32)
    return jax.device_put(host_arrays.aligned(x))


def to_host(x) -> np.ndarray:
    """A numpy copy of an array, even one split over several processes' devices (then every
    process must call this: it gathers)."""
    if isinstance(x, jax.Array) and not (x.is_fully_addressable or x.is_fully_replicated):
        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(x)
