"""Descriptors computed elsewhere (NetVLAD, a foundation model): ``.npy`` files read as one
more method of a benchmark sweep (``precomputed.<name>.database`` / ``.queries``).

A file holds float descriptors ``(n_images, d)`` (float16, float32 or float64; read as
float32), one row per image, in either order:

- the suite's rows: every image of that side as the benchmark uses it, in the order it
  reads them (sorted file names for ``vpr_bench`` and ``positions``; the frames kept, in
  frame order, for ``nordland_star``);
- one row per image file of the side's folder in sorted file-name order (Python's
  ``sorted``), whether or not the suite keeps the image: for ``nordland_star``, whose
  frame list (the clean list by default), range or dropped frames leave files out, the
  suite picks the rows of the frames it uses.

For ``vpr_bench`` and ``positions`` the two are the same. Files are loaded memory-mapped,
never unpickled; a file that cannot serve is one line naming it and the fix.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from vpr_jax.data.images import list_images, relative_names
from vpr_jax.errors import UserError
from vpr_jax.untrusted import check_npy_fits

SIDES = ("database", "queries")
PICKLE = b"\x80"  # the first byte of a pickle (protocol 2 and later)
SAVE_HINT = "save them with numpy.save(path, descriptors.astype('float32'))"


def open_descriptors(path: str | Path, key: str) -> np.ndarray:
    """The ``(n, d)`` float array in ``path`` (memory-mapped), ``key`` naming its setting
    (``precomputed.netvlad.database``) in errors."""
    path = Path(path).expanduser()
    where = f"{key}={path}"
    if not path.is_file():
        what = "is a folder" if path.is_dir() else "does not exist"
        raise UserError(f"{where} {what}: point it at a .npy file of descriptors ({SAVE_HINT})")
    pickled = f"{where} holds pickled Python objects, never loaded (they can run code)"
    try:
        with open(path, "rb") as f:
            magic = f.read(6)
        if magic != b"\x93NUMPY":
            what = "a .npz archive" if magic.startswith(b"PK") else "not a .npy file"
            problem = pickled if magic.startswith(PICKLE) else f"{where} is {what}"
            raise UserError(f"{problem}: {SAVE_HINT}")
        check_npy_fits(path, where, SAVE_HINT)  # a header claiming more than the file holds
        array = np.load(path, mmap_mode="r", allow_pickle=False)
    except ValueError:  # an object array inside a .npy file
        raise UserError(f"{pickled}: {SAVE_HINT}") from None
    except OSError as err:
        raise UserError(f"{where} cannot be read ({err.strerror or err}): {SAVE_HINT}") from None
    if array.dtype.kind != "f":
        raise UserError(
            f"{where} holds {array.dtype} values, not floating-point descriptors: {SAVE_HINT}"
        )
    if array.ndim != 2:
        raise UserError(
            f"{where} has shape {array.shape}: save one row per image, (n_images, d); flatten "
            "each descriptor"
        )
    return array


def descriptor_rows(
    array: np.ndarray, names: np.ndarray, root: str | Path, key: str, path: str
) -> np.ndarray:
    """The rows of ``array`` for the images ``names`` (every image of one side of the
    benchmark, in its order), float32, checked finite: the file's rows in that order, or one
    per image file of the side's folder (listed under ``root`` only then)."""
    n = len(array)
    if n == len(names):
        rows = np.arange(n)
    else:
        all_names = folder_names(root, names)
        position = {name: i for i, name in enumerate(all_names)}
        if n != len(all_names):
            folder = Path(all_names[0]).parent.as_posix()
            raise UserError(
                f"{key}={path} has {n:,} rows, but {folder}/ holds {len(all_names):,} images "
                f"({len(names):,} of them used): write one row per image, in sorted file "
                "order (docs/guide.md, Outside descriptors)"
            )
        rows = np.array([position[name] for name in names], dtype=np.int64)
    out = np.asarray(array[rows], dtype=np.float32)
    bad = ~np.isfinite(out).all(axis=1)
    if bad.any():
        first = int(np.argmax(bad))
        raise UserError(
            f"{key}={path} row {int(rows[first])} ({names[first]}) holds NaN or infinite values "
            f"({int(bad.sum()):,} such rows): recompute those descriptors"
        )
    return out


def folder_names(root: str | Path, names: np.ndarray) -> np.ndarray:
    """Every image file of the folder ``names`` live in (relative to ``root``, sorted as the
    readers sort them)."""
    root = Path(root).expanduser()
    folder = root / Path(str(names[0])).parent
    return relative_names(list_images(folder, "the images"), root)


def setting_key(name: str, side: str) -> str:
    """How the command line names a set's file: ``precomputed.netvlad.database``, or
    ``precomputed.database`` for the set named ``precomputed`` (the one-set form)."""
    return f"precomputed.{side}" if name == "precomputed" else f"precomputed.{name}.{side}"


class OutsideSide(NamedTuple):
    """One side of a set of outside descriptors, every image of that side of the benchmark:
    its rows, each image name's row, and the names whose row is zero."""

    rows: np.ndarray  # float32 (n_images, d)
    row_of: dict[str, int]
    zero: tuple[str, ...] = ()  # images whose descriptor is zero: matched arbitrarily
    # (vpr_jax.methods.precomputed.checked_sides finds them)

    def of(self, names: np.ndarray) -> np.ndarray:
        """The descriptors of the images ``names`` (a pair's test or validation part)."""
        return self.rows[[self.row_of[name] for name in names]]


def read_precomputed(
    files: dict[str, str], name: str, sides: dict[str, np.ndarray], root: str | Path
) -> dict[str, OutsideSide]:
    """Set ``name``'s descriptors (``files``: its ``{"database": path, "queries": path}``)
    for every image of each side (``sides``: side -> the benchmark's image names, relative to
    ``root``, ``data.root``), read and checked once."""
    out = {}
    for side, names in sides.items():
        path, key = files[side], setting_key(name, side)
        rows = descriptor_rows(open_descriptors(path, key), names, root, key, path)
        out[side] = OutsideSide(rows=rows, row_of={n: i for i, n in enumerate(names)})
    widths = {side: out[side].rows.shape[1] for side in out}
    if len(set(widths.values())) > 1:
        db, query = (f"{setting_key(name, s)}={files[s]} has {widths[s]:,}" for s in SIDES)
        raise UserError(
            f"{db} columns but {query}: database and query descriptors must have the same "
            "width, each row one image's descriptor from the same model"
        )
    return out
