"""Files someone else made, read as data only (docs/guide.md, "Files you did not make").

Two things a file can do beyond its bytes are refused here: claim an array larger than
memory (a header or a shape is checked before memory is taken), and run code (numpy's
object arrays are pickles: they are rebuilt by a restricted unpickler that admits only the
few numpy functions such an array is made of). No JAX here.
"""

from __future__ import annotations

import io
import math
import os
import pickle
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from vpr_jax.errors import UserError

# A file may claim at most this share of the machine's memory for one array or state: more
# cannot be restored (or would leave nothing to compute with), and a claim is free to write.
MEMORY_SHARE = 0.5


def memory_bytes() -> int:
    """The machine's physical memory in bytes (a large stand-in where it cannot be read)."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 1 << 40


def check_claim(nbytes: int, where: str, fix: str) -> None:
    """Refuse (UserError) a file's claim of ``nbytes`` bytes above ``MEMORY_SHARE`` of
    memory, naming ``where`` it was made and ``fix``."""
    limit = int(memory_bytes() * MEMORY_SHARE)
    if nbytes > limit:
        raise UserError(
            f"{where} claims {nbytes / 2**30:,.1f} GiB of arrays, more than "
            f"{MEMORY_SHARE:.0%} of this machine's memory ({limit / 2**30:,.1f} GiB): "
            f"nothing was read; {fix}"
        )


def claimed_bytes(shape: Any, dtype: Any) -> int:
    """The bytes an array of ``shape`` and ``dtype`` (as a file wrote them) would take;
    ValueError when they are not a shape of counts or a dtype of numbers."""
    if not isinstance(shape, list | tuple) or not all(
        isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape
    ):
        raise ValueError(f"shape {shape!r} is not a list of counts")
    kind = np.dtype(dtype) if isinstance(dtype, str | np.dtype) else None
    if kind is None or kind.kind not in "biuf":
        raise ValueError(f"dtype {dtype!r} is not one of numbers")
    return math.prod(shape) * kind.itemsize


def npy_header(f: io.BufferedIOBase) -> tuple[tuple[int, ...], bool, np.dtype]:
    """The shape, Fortran order and dtype of the ``.npy`` stream ``f`` (left at its data),
    from its header alone; ValueError when it is not one."""
    version = np.lib.format.read_magic(f)
    if version == (1, 0):
        return np.lib.format.read_array_header_1_0(f)
    return np.lib.format.read_array_header_2_0(f)  # 2.0 and 3.0 differ only in encoding


def check_npy_fits(path: Path, where: str, fix: str) -> None:
    """Refuse a ``.npy`` file whose header claims more data than the file holds (numpy
    would take the memory first), or an ``.npz`` archive with such a member or a
    compressed one (its data could inflate past any size its file suggests)."""
    try:
        with open(path, "rb") as f:
            if f.read(2) != b"PK":
                f.seek(0)
                shape, _, dtype = npy_header(f)
                _check_fits(shape, dtype, os.fstat(f.fileno()).st_size - f.tell(), where, fix)
                return
        with zipfile.ZipFile(path) as archive:
            for member in archive.infolist():
                if member.compress_type != zipfile.ZIP_STORED:
                    raise UserError(f"{where} holds {member.filename} compressed: {fix}")
                with archive.open(member) as f:
                    shape, _, dtype = npy_header(f)
                    inside = f"{where} ({member.filename})"
                    _check_fits(shape, dtype, member.compress_size, inside, fix)
    except (ValueError, EOFError, zipfile.BadZipFile) as err:
        raise UserError(f"{where} cannot be read as a numpy file ({err}): {fix}") from None


def _check_fits(shape, dtype: np.dtype, available: int, where: str, fix: str) -> None:
    if dtype.hasobject:
        return  # numpy refuses it unpickled (allow_pickle=False); read_object_array reads it
    needed = math.prod(shape) * dtype.itemsize
    if needed > available:
        raise UserError(
            f"{where} claims an array of shape {tuple(shape)} ({needed:,} bytes) but holds "
            f"{available:,}: nothing was read; {fix}"
        )


def _multiarray():
    try:
        from numpy._core import multiarray  # numpy 2
    except ImportError:  # numpy 1
        from numpy.core import multiarray
    return multiarray


def _number_or_object(dtype: Any) -> bool:
    return isinstance(dtype, np.dtype) and (dtype.kind in "biuf" or dtype == np.dtype(object))


class _ArrayUnpickler(pickle.Unpickler):
    """Admits only what an object array of numbers and lists names (numpy 1 writes
    ``numpy.core.multiarray``, numpy 2 ``numpy._core.multiarray``), each checked: an array's
    claimed shape before numpy takes memory for it (numpy allocates an object array's
    claimed size before reading it), so no more elements than the file has bytes."""

    def __init__(self, f: io.BufferedIOBase, limit: int):
        super().__init__(f)

        class Checked(np.ndarray):
            def __setstate__(self, state):
                shape, dtype, data = state[-4], state[-3], state[-1]
                if not isinstance(shape, tuple) or not all(isinstance(n, int) for n in shape):
                    raise pickle.UnpicklingError(f"an array of shape {shape!r}")
                if math.prod(shape) > limit:
                    raise pickle.UnpicklingError(f"an array of shape {shape} in a smaller file")
                if not _number_or_object(dtype) or (dtype.hasobject and not isinstance(data, list)):
                    raise pickle.UnpicklingError(f"an array of {dtype!r}")
                super().__setstate__(state)

        def reconstruct(subtype, shape, code):  # as numpy's pickles call it: an empty array
            if subtype is not np.ndarray or shape != (0,):
                raise pickle.UnpicklingError(f"_reconstruct({subtype!r}, {shape!r})")
            return _multiarray()._reconstruct(Checked, shape, code)

        def scalar(dtype, data):  # a number, as numpy writes np.int64(3)
            if not _number_or_object(dtype) or dtype.hasobject or not isinstance(data, bytes):
                raise pickle.UnpicklingError(f"a scalar of {dtype!r}")
            return _multiarray().scalar(dtype, data)

        self.admitted = {("numpy", "ndarray"): np.ndarray, ("numpy", "dtype"): np.dtype}
        for module in ("numpy.core.multiarray", "numpy._core.multiarray"):
            self.admitted[(module, "_reconstruct")] = reconstruct
            self.admitted[(module, "scalar")] = scalar

    def find_class(self, module: str, name: str) -> Any:
        found = self.admitted.get((module, name))
        if found is None:
            raise pickle.UnpicklingError(f"{module}.{name}")
        return found

    def persistent_load(self, pid):
        raise pickle.UnpicklingError(f"a persistent object {pid!r}")


def read_object_array(path: Path, where: str, fix: str) -> np.ndarray:
    """The numpy object array in ``path`` (numbers, lists and arrays of them, as numpy 1 or 2
    saved it), rebuilt without running anything the file names: one line (UserError)
    naming what it asked for otherwise. A file of a plain numeric array reads as numpy
    reads it (no pickle in it). Nested arrays come back as a subclass of ndarray
    (``np.asarray`` makes them plain)."""
    try:
        f = open(path, "rb")
    except OSError as err:
        raise UserError(f"{where} cannot be read ({err.strerror}): {fix}") from None
    with f:
        try:
            shape, _, dtype = npy_header(f)
        except ValueError as err:
            raise UserError(f"{where} is not a numpy file ({err}): {fix}") from None
        size = os.fstat(f.fileno()).st_size
        if not dtype.hasobject:
            _check_fits(shape, dtype, size - f.tell(), where, fix)
            return np.load(path, allow_pickle=False)
        try:
            array = _ArrayUnpickler(f, limit=size).load()
        except pickle.UnpicklingError as err:
            raise UserError(
                f"{where} asks for {err}, which a table of numbers never holds: refused, "
                f"nothing run; {fix}"
            ) from None
        except (EOFError, ValueError, TypeError, AttributeError, IndexError, KeyError) as err:
            raise UserError(f"{where} is not a numpy object array ({err}): {fix}") from None
    if not isinstance(array, np.ndarray) or array.shape != tuple(shape):
        raise UserError(f"{where} does not hold the array its header names: {fix}")
    return array.view(np.ndarray)
