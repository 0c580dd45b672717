"""Host arrays that XLA on a CPU reads in place.

A numpy array whose data starts on a 64-byte boundary goes into a jitted function, or
through ``jax.device_put``, without a copy on a CPU backend; any other array is copied
first (numpy's own allocations are 16-byte aligned), so an unaligned array costs its own
size again in resident memory each time it enters a jitted function, and an aligned one
nothing. ``jnp.asarray`` without a dtype copies even an aligned array; ``jax.device_put``
does not.

The route's seasons, the pair's image arrays and blocked descriptors are allocated here, so
the whole route (``preset=full``) fits in what its arrays need. Pure numpy: loading data
must not start JAX.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools

import numpy as np

ALIGNMENT = 64  # bytes: XLA's CPU client aliases host buffers aligned to this


def empty(shape, dtype=np.float32) -> np.ndarray:
    """An uninitialised C-contiguous array whose data is ``ALIGNMENT``-byte aligned."""
    dtype = np.dtype(dtype)
    size = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    raw = np.empty(size + ALIGNMENT, np.uint8)
    start = -raw.ctypes.data % ALIGNMENT
    return raw[start : start + size].view(dtype).reshape(shape)


def is_aligned(x: np.ndarray) -> bool:
    return x.flags.c_contiguous and x.ctypes.data % ALIGNMENT == 0


def aligned(x, dtype=np.float32) -> np.ndarray:
    """``x`` as an aligned C-contiguous array of ``dtype``: itself when it already is one,
    else one copy."""
    x = np.asarray(x)
    if x.dtype == dtype and is_aligned(x):
        return x
    out = empty(x.shape, dtype)
    out[...] = x
    return out


def _indices(rows, n: int) -> np.ndarray:
    rows = np.asarray(rows)
    if rows.dtype == bool:
        return np.flatnonzero(rows)
    if rows.size and (rows.min() < 0 or rows.max() >= n):
        raise IndexError(f"rows outside 0..{n - 1}")
    return rows


def take(x: np.ndarray, rows, out: np.ndarray | None = None) -> np.ndarray:
    """Rows ``rows`` (indices in range, or a boolean mask) of ``x``, gathered straight into
    an aligned array (or ``out``). ``mode="clip"`` after the range check: numpy's default
    mode gathers into a temporary first."""
    rows = _indices(rows, len(x))
    if out is None:
        out = empty((len(rows), *x.shape[1:]), x.dtype)
    return np.take(x, rows, axis=0, out=out, mode="clip")


def stack_rows(parts) -> np.ndarray:
    """``np.concatenate`` of ``x[rows]`` for each ``(x, rows)`` of ``parts``, every part's
    rows gathered straight into one aligned array."""
    parts = [(x, _indices(rows, len(x))) for x, rows in parts]
    first = parts[0][0]
    out = empty((sum(len(r) for _, r in parts), *first.shape[1:]), first.dtype)
    start = 0
    for x, rows in parts:
        take(x, rows, out[start : start + len(rows)])
        start += len(rows)
    return out


@functools.cache
def _libc():
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
    except OSError:
        return None
    return libc if libc is not None and hasattr(libc, "malloc_trim") else None


def release_free_memory() -> bool:
    """Hand the heap's free pages back to the OS (glibc's ``malloc_trim``; False where there
    is none). XLA's temporaries come from malloc's per-thread heaps, which keep freed
    pages, so without a trim they pile up over a sweep's pairs and raise its peak memory.
    Cheap enough that the runner calls it after each method."""
    libc = _libc()
    return bool(libc and libc.malloc_trim(0))
