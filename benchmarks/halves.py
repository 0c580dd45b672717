"""Lay out a folder of frame-aligned seasons as two stretches that never share a place: a
**tuning route** (the first stretch, aligned, in the ``folders`` layout) to learn and choose
options on, and a **reporting benchmark** (the rest, in VPR-Bench's layout) to report on.

    python benchmarks/halves.py DATA_ROOT OUT [--seasons summer,winter] [--split 894]
        [--query-step 2] [--tolerance 1]

DATA_ROOT holds one folder per season with the frame number in each file name
(``data.source=folders``, e.g. ``../shared/data/nordland_dev``). Frames 1..SPLIT go to
``OUT/tuning/<season>/`` as they are; frames SPLIT+1.. become ``OUT/reporting/``: every
frame of the first season in ``ref/``, every ``--query-step``-th frame of the second in
``query/``, and ``ground_truth_new.npy`` naming the references within ``--tolerance``
frames of each query (VPR-Bench's layout, as ``data.source=vpr_bench`` reads it). Then a
model trained on an aligned route and applied to a benchmark that has none:

    python -m experiments.sweep preset=real data.source=vpr_bench data.root=OUT/reporting \\
      data.train_source=folders data.train_root=OUT/tuning "data.seasons=[summer,winter]" \\
      split.n_train=600 split.n_test=225 split.gap=10 tolerance=1

(the route's split keys choose its 530 training and 60 validation places per season; its
test places are not used). Files are copied, so OUT is self-contained; an existing OUT is
refused rather than overwritten.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from vpr_jax.data.frames import frame_id_from_name  # noqa: E402
from vpr_jax.data.images import list_images  # noqa: E402
from vpr_jax.errors import UserError  # noqa: E402


def frames(folder: Path) -> dict[int, Path]:
    """Frame number (the last number in a file name, as data.source=folders reads it) ->
    image file."""
    found = {frame_id_from_name(p.name): p for p in list_images(folder, "numbered frames")}
    found.pop(None, None)
    if not found:
        raise SystemExit(f"{folder} holds no numbered images")
    return found


def lay_out(root: Path, out: Path, seasons: list[str], split: int, step: int, tol: int) -> str:
    """Write both layouts; returns a one-line summary."""
    by_season = {s: frames(root / s) for s in seasons}
    common = sorted(set.intersection(*(set(f) for f in by_season.values())))
    tuning = [i for i in common if i <= split]
    reporting = [i for i in common if i > split]
    if not tuning or not reporting:
        span = f"{common[0]}..{common[-1]}" if common else "none in common"
        raise SystemExit(f"--split {split} leaves a stretch empty: frames {span}")
    for season, found in by_season.items():
        target = out / "tuning" / season
        target.mkdir(parents=True)
        for i in tuning:
            shutil.copy2(found[i], target / found[i].name)
    db_season, query_season = seasons
    bench = out / "reporting"
    (bench / "ref").mkdir(parents=True)
    (bench / "query").mkdir()
    queries = reporting[::step]
    for i in reporting:
        shutil.copy2(by_season[db_season][i], bench / "ref" / f"{i:05d}.png")
    for i in queries:
        shutil.copy2(by_season[query_season][i], bench / "query" / f"{i:05d}.png")
    refs = np.asarray(reporting)
    table = np.empty((len(queries), 2), dtype=object)
    for n, i in enumerate(queries):
        table[n, 0] = n
        table[n, 1] = np.flatnonzero(np.abs(refs - i) <= tol).tolist()
    np.save(bench / "ground_truth_new.npy", table, allow_pickle=True)
    return (
        f"tuning route: frames {tuning[0]}..{tuning[-1]} of {', '.join(seasons)} in "
        f"{out / 'tuning'}; reporting benchmark: {len(reporting)} {db_season} references "
        f"{reporting[0]}..{reporting[-1]}, {len(queries)} {query_season} queries (every "
        f"{step}), correct within +-{tol} frames, in {bench}"
    )


MANIFEST = "layout.json"  # what a folder was laid out from: a rerun of the same is a no-op


def _laid_out(out: Path) -> dict | None:
    try:
        return json.loads((out / MANIFEST).read_text())
    except (OSError, ValueError):
        return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", type=Path, help="one folder per season, numbered frames")
    parser.add_argument("out", type=Path, help="a new folder for both layouts")
    parser.add_argument("--seasons", default="summer,winter", help="database,query")
    parser.add_argument("--split", type=int, default=894, help="last frame of the tuning route")
    parser.add_argument("--query-step", type=int, default=2, help="every n-th query frame")
    parser.add_argument("--tolerance", type=int, default=1, help="correct within +-n frames")
    args = parser.parse_args(argv)
    seasons = [s.strip() for s in args.seasons.split(",")]
    missing = [s for s in seasons if not (args.root / s).is_dir()]
    problem = None
    if len(seasons) != 2:
        problem = f"--seasons={args.seasons}: name two seasons, database first"
    elif missing:
        problem = (
            f"{args.root} has no folder {missing[0]}/: ROOT holds one folder of numbered frames "
            f"per season ({', '.join(seasons)}), e.g. ../shared/data/nordland_dev, or "
            "runs/halves/tuning once the halves are laid out"
        )
    manifest = {
        "root": str(args.root.resolve()),
        "seasons": seasons,
        "split": args.split,
        "query_step": args.query_step,
        "tolerance": args.tolerance,
    }
    if problem is None and args.out.exists():
        if _laid_out(args.out) == manifest:
            print(f"{args.out} already holds these layouts: nothing to do")
            return 0
        problem = f"{args.out} exists: name a new folder (nothing is overwritten)"
    if problem is None:
        try:
            layout = (args.split, args.query_step, args.tolerance)
            print(lay_out(args.root, args.out, seasons, *layout))
            (args.out / MANIFEST).write_text(json.dumps(manifest))
            return 0
        except (UserError, FileNotFoundError) as err:
            problem = str(err)
    print(f"error: {problem}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
