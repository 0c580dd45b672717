"""Does the matcher return numpy brute force's top-10? Every query, every rank, on real frames.

    python benchmarks/match_exactness.py ROOT [--db summer] [--query winter] [--k 10] [--tiny]

ROOT holds one folder of frame-aligned images per season (the layout of
``data.source=folders``, e.g. the dev frames). Descriptors are the raw pixels (32x64 grey,
2,048 values) and, as a second case, PCA's change-removal descriptors (the database
season's own fit, 10 leading components removed). For each, ``top_k_matches`` and numpy's
brute force (``peers.numpy_top_k``: normalise, one product, argpartition, sort) rank the
database for every query; the script counts rank positions whose index differs and, for
each, prints the two scores numpy gives the two indices: a difference between entries
whose scores agree to float32 rounding is a tie, broken by the order of summation.
Exit code 1 when any difference is not a tie. ``--tiny`` (for the tests): the first 100
frames of each season, a PCA of 20 components.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from common import TINY_HELP
from peers import numpy_top_k

from vpr_jax.data.images import list_images, read_images
from vpr_jax.encoders import pca
from vpr_jax.evaluation.matching import top_k_matches

COMPONENTS, REMOVED = 100, 10  # PCA's fit, and the leading components removed
TINY_FRAMES, TINY_COMPONENTS = 100, 20
TIE = 1e-6  # scores closer than this (float32 cosines near 1: ~8 ulp) are a tie


def compare(name: str, query: np.ndarray, db: np.ndarray, k: int) -> int:
    """Print the comparison; return the number of differences that are not ties."""
    _, ours = top_k_matches(query, db, k)
    peer_scores, peer = numpy_top_k(query, db, k)
    ours = ours[0]
    qn = query / np.linalg.norm(query, axis=1, keepdims=True)
    dn = db / np.linalg.norm(db, axis=1, keepdims=True)
    differ = np.argwhere(ours != peer)
    not_ties = 0
    for qi, rank in differ:
        a, b = qn[qi] @ dn[ours[qi, rank]], qn[qi] @ dn[peer[qi, rank]]
        tie = abs(float(a) - float(b)) < TIE
        not_ties += not tie
        if len(differ) <= 20 or not tie:
            print(
                f"  query {qi} rank {rank}: ours {ours[qi, rank]} ({a:.8f}), numpy "
                f"{peer[qi, rank]} ({b:.8f}){'' if tie else '  NOT A TIE'}"
            )
    print(
        f"{name}: {len(query):,} queries x {len(db):,} database, top-{k}: "
        f"{len(differ)} of {ours.size:,} rank positions differ, {not_ties} of them not ties; "
        f"top-1 identical for {np.mean(ours[:, 0] == peer[:, 0]):.4%} of queries"
    )
    return not_ties


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path)
    parser.add_argument("--db", default="summer")
    parser.add_argument("--query", default="winter")
    parser.add_argument("--k", type=int, default=10)
    parser.add_argument("--tiny", action="store_true", help=TINY_HELP)
    args = parser.parse_args()
    max_frames = TINY_FRAMES if args.tiny else None
    components = TINY_COMPONENTS if args.tiny else COMPONENTS
    images = {}
    for season in (args.db, args.query):
        paths = list_images(args.root / season, f"the {season} images")[:max_frames]
        images[season] = read_images(paths, season, resize=True)[0].reshape(len(paths), -1)
    db, query = images[args.db].astype(np.float32), images[args.query].astype(np.float32)
    bad = compare("raw pixels", query, db, args.k)
    state = pca.fit_pca(db, components)
    bad += compare(
        f"PCA, {REMOVED} components removed",
        np.asarray(pca.suffix_descriptors(state, query))[:, REMOVED:],
        np.asarray(pca.suffix_descriptors(state, db))[:, REMOVED:],
        args.k,
    )
    raise SystemExit(1 if bad else 0)


if __name__ == "__main__":
    main()
