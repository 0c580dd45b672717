"""Cost against work: time and peak memory of matching and of a raw + PCA sweep by length.

Each is measured against the route's length, and the exponent of each fitted on a log-log
scale.

    python benchmarks/scaling.py [--frames 1000,4000,16000,35768] [--repeats 2]
                                 [--plot docs/scaling_speed.png] [--tiny]

Matching: the database is every frame of the built-in route's summer (n frames, raw pixels,
2,048 values), the queries every 10th frame of its fall, so queries grow with the route and
brute-force top-10 matching should cost time ~ n^2 and memory ~ n. Each length runs in a
fresh process: the warm median of ``--repeats`` calls after one that compiles, and the peak
RSS of those calls above the RSS before them (the matcher's own working memory: the data
and the compiled program are already there).

Sweep: ``python -m experiments.sweep`` with ``methods=[raw,pca]``, one pair (summer-fall),
``data.n_frames=n`` and ``preset=full``'s partition scaled to n (three test sections of
n x 1,150 / 35,768 frames, every other frame trains), in a fresh process: wall time (JAX's
start and the route's generation included) and peak RSS. Its time grows faster than linear
(the PCA fit ~ n, matching ~ n^2) from a fixed start-up cost, so the exponent over 1,000 -
35,768 frames lies between.

Prints one line per measurement and one per fitted exponent; ``--plot`` draws both on
log-log axes. ``--tiny`` (for the tests): lengths 200 and 400 (``TINY_FRAMES``) unless
``--frames`` names others, one warm run, and only the first length matched and swept in a
fresh process, the others in this one (a fresh interpreter is most of a tiny run's time).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from common import TINY_HELP, sweep_in_fresh_process

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
FULL_ROUTE = 35_768
FRAMES = (1000, 4000, 16000, FULL_ROUTE)  # route lengths measured
TINY_FRAMES = (200, 400)  # --tiny's
QUERY_STEP = 10
PROCESS_TIMEOUT_S = 1800


def _status_bytes(field: str) -> int:
    """A memory line of /proc/self/status (VmRSS: now; VmHWM: the peak since the last
    reset), in bytes."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    raise SystemExit(f"/proc/self/status has no {field}: this benchmark needs Linux")


def _reset_peak() -> None:
    """Start VmHWM again from the current RSS (Linux >= 4.0: clear_refs, value 5)."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def match_once(n: int, repeats: int) -> dict:
    """In this process: time and working memory of top-10 matching at route length n."""
    import jax
    from common import timed

    from vpr_jax.data.synthetic import render_season
    from vpr_jax.evaluation.matching import top_k_matches

    db = render_season(np.arange(n), "summer", seed=0).reshape(n, -1)
    query = render_season(np.arange(0, n, QUERY_STEP), "fall", seed=0).reshape(-1, db.shape[1])
    start = time.perf_counter()
    jax.block_until_ready(top_k_matches(query, db, 10))  # compiles; not part of the peak
    first = time.perf_counter() - start
    before = _status_bytes("VmRSS")
    _reset_peak()
    _, seconds = timed(lambda: top_k_matches(query, db, 10), repeats)
    peak = _status_bytes("VmHWM")
    return {
        "n": n,
        "queries": len(query),
        "seconds": seconds,
        "first": first,
        "working_bytes": max(peak - before, 0),
    }


def _in_fresh_process(n: int, repeats: int) -> dict:
    cmd = [sys.executable, str(Path(__file__)), "--match-one", str(n), "--repeats", str(repeats)]
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{HERE}"}
    proc = subprocess.run(
        cmd, capture_output=True, text=True, env=env, timeout=PROCESS_TIMEOUT_S, check=False
    )
    if proc.returncode != 0:
        raise SystemExit(f"matching at n={n} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def sweep_args(n: int) -> list[str]:
    """preset=full's partition scaled to a route of n frames, one pair, raw and PCA."""
    n_test = max(2, round(n * 1150 / FULL_ROUTE))
    gap = max(2, round(n * 200 / FULL_ROUTE))
    return [
        "preset=full",
        f"data.n_frames={n}",
        f"split.n_test={n_test}",
        f"split.gap={gap}",
        "season_pairs=summer-fall",
        "methods=[raw,pca]",
    ]


def sweep_once(n: int, fresh: bool = True) -> dict:
    """Wall time and peak RSS of a raw + PCA sweep at route length n, in a fresh process
    (``fresh=False``: in this one)."""
    with tempfile.TemporaryDirectory(prefix="vpr_jax-scaling-") as tmp:
        seconds, peak = sweep_in_fresh_process(
            sweep_args(n), Path(tmp) / "run", timeout=PROCESS_TIMEOUT_S, fresh=fresh
        )
    return {"n": n, "seconds": seconds, "peak_bytes": peak}


def exponent(ns, values) -> float:
    """The slope of log(value) against log(n): value ~ n^slope."""
    return float(np.polyfit(np.log(ns), np.log(values), 1)[0])


def measure(frames: list[int], repeats: int, tiny: bool = False) -> dict:
    """Every measurement and fitted exponent; prints as it goes. ``tiny``: only the first
    length is matched and swept in a fresh process, the others in this one."""
    matching, sweeps = [], []
    for i, n in enumerate(frames):
        m = match_once(n, repeats) if tiny and i else _in_fresh_process(n, repeats)
        matching.append(m)
        print(
            f"  matching n={n:,} ({m['queries']:,} queries): {m['seconds']:.3f} s, "
            f"working memory {m['working_bytes'] / 2**20:.0f} MiB",
            flush=True,
        )
    for i, n in enumerate(frames):
        s = sweep_once(n, fresh=not (tiny and i))
        sweeps.append(s)
        print(
            f"  raw+pca sweep n={n:,}: {s['seconds']:.1f} s, peak RSS "
            f"{s['peak_bytes'] / 2**30:.2f} GiB",
            flush=True,
        )
    fits = {
        "matching time": exponent(frames, [m["seconds"] for m in matching]),
        "matching memory": exponent(frames, [max(m["working_bytes"], 1) for m in matching]),
        "sweep time": exponent(frames, [s["seconds"] for s in sweeps]),
        "sweep peak RSS": exponent(frames, [s["peak_bytes"] for s in sweeps]),
    }
    expected = {
        "matching time": "2 (queries and database grow with n)",
        "matching memory": "1 (blocks of fixed size; the route itself ~ n)",
        "sweep time": "1 to 2 (the PCA fit ~ n, matching ~ n^2)",
        "sweep peak RSS": "1 at most",
    }
    for what, slope in fits.items():
        print(f"{what} ~ n^{slope:.2f}   (expected ~ n^{expected[what]})", flush=True)
    return {"matching": matching, "sweeps": sweeps, "exponents": fits}


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_t, ax_m) = plt.subplots(1, 2, figsize=(10, 4))
    fits = result["exponents"]
    for key, rows, label in (
        ("seconds", result["matching"], "matching time"),
        ("seconds", result["sweeps"], "sweep time"),
    ):
        ns = [r["n"] for r in rows]
        ax_t.loglog(ns, [r[key] for r in rows], "o-", label=f"{label} ~ n^{fits[label]:.2f}")
    for key, rows, label in (
        ("working_bytes", result["matching"], "matching memory"),
        ("peak_bytes", result["sweeps"], "sweep peak RSS"),
    ):
        ns = [r["n"] for r in rows]
        ax_m.loglog(
            ns, [r[key] / 2**20 for r in rows], "o-", label=f"{label} ~ n^{fits[label]:.2f}"
        )
    ax_t.set(xlabel="frames per season", ylabel="seconds", title="time")
    ax_m.set(xlabel="frames per season", ylabel="MiB", title="memory")
    for ax in (ax_t, ax_m):
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"plot: {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--frames",
        default=None,
        help=f"route lengths ({','.join(map(str, FRAMES))}; --tiny: "
        f"{','.join(map(str, TINY_FRAMES))})",
    )
    parser.add_argument("--repeats", type=int, default=None, help="warm runs (2; --tiny: 1)")
    parser.add_argument("--plot", type=Path, default=None)
    parser.add_argument("--tiny", action="store_true", help=TINY_HELP)
    parser.add_argument("--match-one", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.repeats is None:
        args.repeats = 1 if args.tiny else 2
    if args.frames is None:
        args.frames = ",".join(map(str, TINY_FRAMES if args.tiny else FRAMES))
    if args.match_one is not None:
        print(json.dumps(match_once(args.match_one, args.repeats)))
        return
    frames = [int(f) for f in args.frames.split(",")]
    if len(frames) < 2:
        raise SystemExit("--frames needs at least two lengths to fit an exponent")
    start = time.perf_counter()
    result = measure(frames, args.repeats, args.tiny)
    if args.plot:
        plot(result, args.plot)
    print(f"total {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
