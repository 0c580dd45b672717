"""VPR-Bench's dataset layout: ``ROOT/ref/`` (the database), ``ROOT/query/`` and
``ROOT/ground_truth_new.npy``.

The ground-truth file is what VPR-Bench writes: a numpy object array with one row per query,
``(query_index, [ref_index, ...])``, indices into the two folders' images sorted by file
name (Python's ``sorted``, as VPR-Bench lists them). The file is a pickle, read without
pickle's power (``vpr_jax.untrusted.read_object_array``): numbers, lists and arrays of them
are rebuilt, anything else it names is refused unrun. Queries missing from the file have no
correct reference (they count against recall@1, as in VPR-Bench). Images of any size and
colour are read as 32x64 grey like every source.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from vpr_jax.data.benchmark import Benchmark
from vpr_jax.data.ground_truth import match_sets
from vpr_jax.data.images import list_images, note_colour, read_images, relative_names
from vpr_jax.errors import UserError
from vpr_jax.progress import Log
from vpr_jax.shapes import MAX_PIXELS
from vpr_jax.untrusted import read_object_array

GROUND_TRUTH = "ground_truth_new.npy"
LAYOUT = "ref/, query/ and ground_truth_new.npy (VPR-Bench's layout)"


def read_vpr_bench(
    root: str | os.PathLike, *, max_pixels: int = MAX_PIXELS, log: Log = print
) -> Benchmark:
    root = Path(root).expanduser()
    if not root.is_dir():
        raise UserError(
            f"data root {root} is not a folder: set data.root=PATH to the folder holding {LAYOUT}"
        )
    for side in ("ref", "query"):
        if not (root / side).is_dir():
            raise UserError(
                f"{root / side} is missing: data.source=vpr_bench reads {LAYOUT}; "
                "point data.root at such a folder"
            )
    refs = list_images(root / "ref", "the reference (database) images")
    queries = list_images(root / "query", "the query images")
    rows = _ground_truth(root / GROUND_TRUTH, len(queries), len(refs), root)
    truth = match_sets(rows, len(refs), source=GROUND_TRUTH)
    db, colour_db = read_images(refs, "ref", resize=True, max_pixels=max_pixels)
    query, colour_q = read_images(queries, "query", resize=True, max_pixels=max_pixels)
    note_colour({"ref": colour_db, "query": colour_q}, log)
    unmatched = int((~truth.has_match()).sum())
    log(
        f"vpr_bench: {len(refs):,} references, {len(queries):,} queries "
        f"({unmatched:,} without a correct reference) from {root}"
    )
    return Benchmark(
        source="vpr_bench",
        db_name="ref",
        query_name="query",
        db=db,
        query=query,
        truth=truth,
        db_ids=np.arange(len(refs)),
        query_ids=np.arange(len(queries)),
        db_names=relative_names(refs, root),
        query_names=relative_names(queries, root),
    )


def _ground_truth(path: Path, n_query: int, n_ref: int, root: Path) -> list[list[int]]:
    """One list of correct reference indices per query (empty for queries not in the file)."""
    fix = (
        f"write {GROUND_TRUTH} as VPR-Bench does: an object array of rows (query_index, "
        "[ref_index, ...])"
    )
    if not path.is_file():
        raise UserError(f"{path} is missing: data.source=vpr_bench reads {LAYOUT}; {fix}")
    table = read_object_array(path, str(path), fix)
    if table.ndim == 0:
        raise UserError(f"{path} holds one value, not a table of rows: {fix}")
    rows: list[list[int]] = [[] for _ in range(n_query)]
    seen = set()
    for r, row in enumerate(table):
        q, refs = _row(row)
        if q is None or refs is None:
            raise UserError(f"{path} row {r} is not (query_index, [ref_index, ...]): {fix}")
        if not 0 <= q < n_query:
            raise UserError(
                f"{path} row {r} names query image {q}, but {root / 'query'} "
                f"holds {n_query:,} images (0..{n_query - 1}): fix the file or "
                "put the missing images back"
            )
        bad = [j for j in refs if not 0 <= j < n_ref]
        if bad:
            raise UserError(
                f"{path} row {r} (query {q}) names reference image {bad[0]}, but "
                f"{root / 'ref'} holds {n_ref:,} images (0..{n_ref - 1}): fix the "
                "file or put the missing images back"
            )
        if q in seen:
            raise UserError(f"{path} lists query {q} twice (row {r}): keep one row per query")
        seen.add(q)
        rows[q] = refs
    return rows


def _index(value) -> int | None:
    """An index as the file holds it (a Python or numpy integer, or a whole float), or None."""
    if isinstance(value, float | np.floating) and float(value).is_integer():
        return int(value)
    if isinstance(value, bool | np.bool_) or not isinstance(value, int | np.integer):
        return None
    return int(value)


def _row(row) -> tuple[int | None, list[int] | None]:
    """A row's query index and reference indices (None where they are not that): only
    integers, a list or tuple of them or a 1-d integer array, looked at one level deep."""
    if not isinstance(row, list | tuple | np.ndarray) or len(row) != 2:
        return None, None
    q, refs = row
    if isinstance(refs, np.ndarray) and refs.ndim <= 1 and refs.dtype.kind in "iu":
        return _index(q), [int(j) for j in np.atleast_1d(refs)]
    if isinstance(refs, np.ndarray) and refs.ndim == 1 and refs.dtype.hasobject:
        refs = list(refs)
    if not isinstance(refs, list | tuple):
        single = _index(refs)  # one reference written as a bare number
        return _index(q), None if single is None else [single]
    found = [_index(j) for j in refs]
    return _index(q), None if None in found else found
