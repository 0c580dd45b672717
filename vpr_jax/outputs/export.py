"""The files of an exported cell: what a larger pipeline takes from a sweep.

One folder per pair and method (``experiments.export`` fills it):

- ``database.txt``, ``queries.txt``: one image name per line, in row order (``Route.names``:
  the file's path relative to ``data.root``, or ``<season>/<frame id>``);
- ``database.npy``, ``queries.npy``: float32 descriptors in those rows, the vectors the
  sweep compared by cosine, as the encoder produced them (single-image cells only);
- ``global-feats.h5``: the same descriptors in hloc's global-feature layout, a group per
  image name (the names of the txt files; a ``/`` in a name nests groups, as in hloc) holding
  ``global_descriptor``, float32 and L2-normalised, so hloc's dot-product ranking
  (``pairs_from_retrieval``) is the sweep's cosine ranking (single-image cells only);
- ``pairs.txt``: hloc's pairs-file format, ``query_name database_name`` per line, ``top_k``
  lines per query, best first; ``scores.csv``: ``query,database,rank,score,correct``;
- the saved encoder's files (``vpr_jax.load_encoder`` works on the folder itself), with
  ``encoder.json`` naming this cell's removed-PC count;
- ``README.txt``: what produced it.

The retrieval files are written query by query from the top-K lists: no similarity
matrix is ever held.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import h5py  # ~30 ms beside numpy; loaded with JAX, after the CLI's cheap checks
import numpy as np

from vpr_jax.encoders.saved import ENCODER_JSON
from vpr_jax.errors import UserError
from vpr_jax.evaluation.matching import l2_normalize

PAIRS_TXT, SCORES_CSV = "pairs.txt", "scores.csv"
NAMES_TXT = {"database": "database.txt", "queries": "queries.txt"}
DESCRIPTORS_NPY = {"database": "database.npy", "queries": "queries.npy"}
GLOBAL_FEATS_H5, GLOBAL_DESCRIPTOR = "global-feats.h5", "global_descriptor"  # hloc's names
SCORE_COLUMNS = ("query", "database", "rank", "score", "correct")
_SKIPPED = {".lock", ENCODER_JSON}  # not copied from a saved encoder's folder


def write_names(folder: Path, side: str, names: np.ndarray) -> None:
    """``database.txt`` or ``queries.txt``: one name per line, in row order."""
    with open(folder / NAMES_TXT[side], "w", encoding="utf-8") as f:
        f.writelines(f"{name}\n" for name in names)


def write_descriptors(folder: Path, side: str, descriptors: np.ndarray) -> None:
    """``database.npy`` or ``queries.npy``: float32 ``(n, d)``, no pickle."""
    np.save(folder / DESCRIPTORS_NPY[side], np.asarray(descriptors, np.float32), allow_pickle=False)


def unit_rows(descriptors: np.ndarray) -> np.ndarray:
    """float32 ``(n, d)``: each row L2-normalised by the matcher's own ``l2_normalize`` (a
    zero row stays zero)."""
    return np.asarray(l2_normalize(np.asarray(descriptors, np.float32)), np.float32)


def write_global_features(
    folder: Path,
    db_names: np.ndarray,
    db: np.ndarray,
    query_names: np.ndarray,
    query: np.ndarray,
) -> None:
    """``global-feats.h5`` in hloc's layout: a group per image name holding
    ``global_descriptor``, the row L2-normalised (``unit_rows``). hloc keys images by name
    alone, so a name on both sides (which would also be masked as a self-match there) is
    refused rather than renamed: the names must stay those of pairs.txt."""
    shared = sorted(set(db_names) & set(query_names))
    if shared:
        raise UserError(
            f"image {shared[0]} is both a database and a query name ({len(shared):,} such "
            "names): hloc's global-feats.h5 keys images by name, so keep the database and "
            "the queries in different folders"
        )
    with h5py.File(folder / GLOBAL_FEATS_H5, "w") as f:
        for names, rows in ((db_names, unit_rows(db)), (query_names, unit_rows(query))):
            for name, row in zip(names, rows, strict=True):
                f.create_group(str(name)).create_dataset(GLOBAL_DESCRIPTOR, data=row)


def write_retrieval(
    folder: Path,
    query_names: np.ndarray,
    db_names: np.ndarray,
    scores: np.ndarray,
    indices: np.ndarray,
    correct: np.ndarray,
) -> None:
    """``pairs.txt`` and ``scores.csv`` from each query's top-K list (``scores``,
    ``indices``, ``correct``: (n_queries, K), best first), a line per query and rank."""
    with (
        open(folder / PAIRS_TXT, "w", encoding="utf-8") as pairs,
        open(folder / SCORES_CSV, "w", encoding="utf-8", newline="") as table,
    ):
        writer = csv.writer(table, lineterminator="\n")
        writer.writerow(SCORE_COLUMNS)
        for q, name in enumerate(query_names):
            matched = db_names[indices[q]]
            pairs.writelines(f"{name} {db}\n" for db in matched)
            writer.writerows(
                (name, db, rank, f"{float(s):.7g}", int(c))
                for rank, (db, s, c) in enumerate(
                    zip(matched, scores[q], correct[q], strict=True), start=1
                )
            )


def copy_encoder(saved: Path, folder: Path, selection: dict) -> None:
    """The saved encoder's files into ``folder`` (not its lock), and its ``encoder.json``
    with ``selection`` (this cell's removed-PC count, recalls and run) over the saved one."""
    for entry in saved.iterdir():
        if entry.name in _SKIPPED:
            continue
        if entry.is_dir():
            shutil.copytree(entry, folder / entry.name)
        else:
            shutil.copy2(entry, folder / entry.name)
    description = json.loads((saved / ENCODER_JSON).read_text())
    (folder / ENCODER_JSON).write_text(json.dumps({**description, **selection}, indent=1))


def readme(facts: dict[str, str], config_yaml: str) -> str:
    """``README.txt``: ``facts`` as ``key: value`` lines, then the sweep's config."""
    width = max(len(k) for k in facts)
    lines = [f"{k.ljust(width)}  {v}" for k, v in facts.items()]
    config = "".join(f"  {line}\n" for line in config_yaml.splitlines())
    return "\n".join(lines) + "\n\nconfig.yaml of the sweep:\n" + config
