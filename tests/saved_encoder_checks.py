"""Load every encoder a finished sweep saved and score it on the sweep's own test places;
print, as JSON, per encoder folder: its recall@1 and how far each query's best cosine score
lies from the one the sweep recorded (the cell's curve.npz).

    python tests/saved_encoder_checks.py LOGDIR PAIR key=value ...   (the sweep's arguments)

A helper of tests/test_saved_encoders.py, run in a fresh process that imports only vpr_jax.
The images are read as the sweep read them, before any preprocessing: the encoder applies
what the sweep applied after reading.
"""

import csv
import json
import sys
from pathlib import Path

import numpy as np

import vpr_jax
from vpr_jax.command_line import parse_config
from vpr_jax.data import load_data
from vpr_jax.data.pair import pair_data
from vpr_jax.data.splits import make_split
from vpr_jax.outputs.results import read_results


def main() -> None:
    logdir, only, args = Path(sys.argv[1]), sys.argv[2], sys.argv[3:]
    cfg = parse_config([*args, f"logdir={logdir}"])
    route = load_data(cfg.data, cfg.seed, lambda line: None)
    split = make_split(route.frame_ids, cfg.split)
    rows = read_results(logdir / "results.csv")
    with open(logdir / "encoders.csv", newline="") as f:
        listing = list(csv.DictReader(f))
    out = {}
    for entry in (e for e in listing if e["pair"] == only):
        db, query = entry["pair"].split("-")
        pair = pair_data(route, split, db, query, cfg.split.database, cfg.tolerance)
        plugins = [m for m in cfg.methods if ":" in m]  # the sweep's methods of the user's
        encode, params = vpr_jax.load_encoder(entry["folder"], plugins=plugins)
        q, d = np.asarray(encode(params, pair.query)), np.asarray(encode(params, pair.db))
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        similarity = q @ d.T
        best = np.argmax(similarity, axis=1)
        correct = np.abs(pair.query_ids - pair.db_ids[best]) <= cfg.tolerance
        with open(Path(entry["folder"]) / "encoder.json") as f:
            run = json.load(f)["run"]
        with np.load(logdir / run / "curve.npz") as z:
            recorded = z["best_scores"]
        (row,) = [r for r in rows if r.run == run]
        out[entry["folder"]] = {
            "recall_at_1": float(correct.mean()),
            "sweep_recall_at_1": row.recall_at_1,
            "score_gap": float(np.abs(similarity.max(axis=1) - recorded).max()),
        }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
