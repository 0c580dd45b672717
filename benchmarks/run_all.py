"""Every speed goal in one table, each row a ratio to the peer timed in this same run.

    python benchmarks/run_all.py [--repeats 3] [--skip-protocol] [--protocol-args "k=v ..."]
                                 [--json runs/run_all.json] [--tiny]

Rows (paper's sizes: 5,000 x 2,048 training images, 3,569 queries x 3,569 database):
  PCA fit, every component   vs scikit-learn PCA(svd_solver="covariance_eigh")   <= 1.0x
  PCA fit, 100 components    vs scikit-learn PCA(100, svd_solver="randomized")   <= 1.0x
                             and vs the full covariance_eigh                     <= 0.35x
  removed-PC sweep, 6 counts vs one count (encode + match)                       <= 1.2x
  FastICA, 256 components    vs scikit-learn FastICA(algorithm="parallel")       <= 0.125x
                             (both whiten from the raw images: ours fits the leading 256
                             principal components, scikit-learn its whole SVD)
  matching, top-10 cosine    vs numpy brute force                                <= 0.9x
                             and vs the bare matrix product in JAX, same run     <= 1.15x
                             at matching.precision=default vs float32            <= 1.1x
                             (the same on a CPU; TF32 products on a recent NVIDIA GPU)
  sequence matching, ds=10   vs the same search in numpy, a loop over queries    <= 1.0x
  inputs (what a method sees: vpr_jax.encoders.inputs), the paper's training images:
                             raw's encode on gradients and on standardised+gradients vs
                             the paper's Table 5 PCA row (0.1 ms an image)           <= 1.0x;
                             the shared PCA fit (200 components, lda's) on each vs the
                             same fit on pixels, its values beside it <= their ratio;
                             the transform of the training images vs that fit        <= 1.0x
  encode ms/image            vs the paper's Table 5 (GTX 1060): auto-encoders <= 0.1x;
                             PCA and ICA <= 1.0x: projecting onto all 2,048
                             components is 8.4 MFLOP an image, and 0.1x of the paper's 0.1 ms
                             would take 840 GFLOP/s, several times this CPU's peak
  the paper protocol         vs 5 minutes on a 2-core CPU, and the paper's Table 4 total
                             (14 h 50 min) for scale
  the whole route            peak RSS of ``preset=full`` (35,768 frames a season)  <= 2.5 GiB
  cost against route length  ``scaling.py``: exponents of matching's time (~ n^2) and
                             working memory (~ n), within 10% of those
The paper protocol is ``python -m experiments.sweep preset=paper`` in a fresh process, into a
temporary logdir and checkpoint folder (three pairs x raw, six PCA counts, six ICA counts,
FAE, CAE; compilation and data generation included), with its peak RSS. ``--skip-protocol``,
``--skip-full-route`` and ``--skip-scaling`` leave out the three longest rows;
``--scaling-plot PATH`` draws the scaling exponents' log-log plot (docs/scaling_speed.png).
It prints the CPU (``/proc/cpuinfo``'s name, family and model: one name covers several
boxes) beside jax's device and the BLAS libraries, and writes the table with them as JSON
(``--json``, default runs/run_all.json), so a figure can be compared with the next run's.
Ours: warm medians of --repeats runs in this process; peers the same, each in a fresh
process without OPENBLAS_CORETYPE / OPENBLAS_L2_SIZE (``peers.py``: their native kernel).
``--tiny`` (for the tests; the figures mean nothing): ``common.TINY_SIZES`` on both sides,
FastICA of 8 components, one warm run, the peers and the protocol in this process (on a
tiny route, ``TINY_PROTOCOL``), scaling at ``scaling.TINY_FRAMES``, and no whole-route row.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np
from bench_autoencoders import MODELS as AE_MODELS
from bench_ica import fit_ours as fit_ica
from bench_linear import REMOVED_PCS
from bench_sequence import measure as measure_sequence
from common import (
    TINY_HELP,
    cpu_name,
    ica_components,
    paper_route,
    route_sizes,
    sweep_in_fresh_process,
    timed,
    timed_alternately,
)
from peers import FORCING, ours_report, run_peer
from scaling import FRAMES as SCALING_FRAMES
from scaling import TINY_FRAMES as TINY_SCALING_FRAMES
from scaling import measure as measure_scaling
from scaling import plot as plot_scaling

from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders import ica, inputs, pca
from vpr_jax.evaluation.matching import top_k_matches
from vpr_jax.files import atomic_write_text
from vpr_jax.method_table import METHODS
from vpr_jax.methods import raw as raw_method
from vpr_jax.outputs.results import read_results
from vpr_jax.precision import f32_matmul

REPO = Path(__file__).resolve().parent.parent
PAPER_TABLE_4 = ("1:12:05", "1:57:32", "3:43:46", "7:56:09")  # baseline, ICA, FAE, CAE
PAPER_TABLE_4_S = sum(
    int(h) * 3600 + int(m) * 60 + int(s) for h, m, s in (t.split(":") for t in PAPER_TABLE_4)
)
PROTOCOL_GOAL_S = 300.0
LDA_COMPONENTS = 200  # lda.n_components's default: the shared PCA fit's size in input_rows
FULL_ROUTE_GOAL_GIB = 2.5
# --tiny's protocol: preset=paper on a 400-place route (4,000 frames, every 10th), one pair,
# a linear and a trained method, two removed-PC counts, a tiny FAE trained for one epoch:
# seconds, not minutes (each method compiles its own programs).
TINY_PROTOCOL = [
    "data.n_frames=4000",
    "split.n_train=150",
    "split.n_test=60",
    "split.gap=100",
    "season_pairs=summer-fall",
    "methods=[pca,fae]",
    "removed_pcs=[0,5]",
    "fae.hidden=32",
    "train.epochs=1",
]


class Table:
    def __init__(self):
        self.rows: list[tuple[str, str, str, str, str, str]] = []

    def add(
        self, what: str, ours: float, peer: float, peer_name: str, goal: float, unit: str = "s"
    ) -> None:
        ratio = ours / peer
        fmt = (lambda v: f"{v:.4f} {unit}") if unit == "ms" else (lambda v: f"{v:.3f} {unit}")
        met = "yes" if ratio <= goal else "no"
        self.rows.append(
            (what, fmt(ours), f"{peer_name} {fmt(peer)}", f"{ratio:.3f}x", f"<= {goal:g}x", met)
        )
        print(f"  {what}: {ratio:.3f}x", flush=True)

    def write_json(self, path: Path, about: dict) -> None:
        """The table as JSON (``about``: the box, the versions, the date), written whole."""
        names = ("what", "ours", "peer", "ratio", "goal", "met")
        rows = [dict(zip(names, row, strict=True)) for row in self.rows]
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps({**about, "rows": rows}, indent=1) + "\n")

    def print(self) -> None:
        header = ("what", "ours", "peer, same run", "ratio", "goal", "met")
        widths = [max(len(r[i]) for r in [header, *self.rows]) for i in range(len(header))]
        for i, r in enumerate([header, *self.rows]):
            print("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)))
            if i == 0:
                print("  ".join("-" * w for w in widths))


def linear_rows(table: Table, train, db, query, repeats: int, tiny: bool) -> None:
    """The linear methods' and matching's rows; ``tiny``: the peers build the tiny data."""
    peer = run_peer("pca_covariance_eigh", repeats, tiny)
    print(f"  peers' BLAS (run without {', '.join(FORCING)}): {peer['blas']}")
    print(f"  ours: {ours_report()}", flush=True)
    _, ours = timed(lambda: pca.fit_pca(train, solver="covariance"), repeats)
    table.add(
        f"PCA fit, every component, {train.shape[0]:,} x {train.shape[1]:,}",
        ours,
        peer["seconds"],
        "sklearn covariance_eigh",
        1.0,
    )
    _, ours = timed(lambda: pca.fit_pca(train, 100), repeats)  # auto: subspace
    table.add(
        "PCA fit, 100 components",
        ours,
        run_peer("pca_randomized_100", repeats, tiny)["seconds"],
        "sklearn randomized",
        1.0,
    )
    table.add("  the same vs the full fit", ours, peer["seconds"], "sklearn covariance_eigh", 0.35)

    state = pca.fit_pca(train, max(REMOVED_PCS))

    def sweep(ks):
        return top_k_matches(
            pca.suffix_descriptors(state, query), pca.suffix_descriptors(state, db), 10, starts=ks
        )

    _, all_k = timed(lambda: sweep(REMOVED_PCS), repeats)
    _, one_k = timed(lambda: sweep((50,)), repeats)
    table.add(f"removed-PC sweep, {len(REMOVED_PCS)} counts", all_k, one_k, "one count", 1.2)

    n_ics = ica_components(tiny)
    _, ours = timed(lambda: fit_ica(train, n_ics), max(1, repeats // 2))
    table.add(
        f"FastICA, {n_ics} components",
        ours,
        run_peer("fastica_256", repeats, tiny)["seconds"],
        "sklearn parallel",
        0.125,
    )

    _, ours = timed(lambda: top_k_matches(query, db, 10), repeats)
    size = f"{len(query):,} x {len(db):,}"
    table.add(
        f"matching, top-10 of {size}",
        ours,
        run_peer("numpy_top_k", repeats, tiny)["seconds"],
        "numpy brute force",
        0.9,
    )
    q_dev, db_dev = jax.device_put(query), jax.device_put(db)
    product = jax.jit(lambda q, d: f32_matmul(q, d.T))  # the matcher's precision
    _, bare = timed(lambda: product(q_dev, db_dev), repeats)
    table.add("  the same vs the bare product", ours, bare, "jnp q @ db.T", 1.15)
    # What matching.precision=default buys: on a CPU nothing (float32 either way); on a
    # recent NVIDIA GPU, TF32 products. Timed alternately: the two are often within noise.
    exact, fastest = timed_alternately(
        [lambda p=p: top_k_matches(query, db, 10, precision=p) for p in ("float32", "default")],
        repeats,
    )
    table.add("  the same at matching.precision=default", fastest, exact, "float32", 1.1)
    seq = measure_sequence(query, db, 10, repeats)
    table.add(
        f"sequence matching ds=10, {size}",
        seq["ours"],
        seq["peer"],
        "numpy loop over queries",
        1.0,
    )

    both = np.concatenate([db, query])
    _, enc = timed(lambda: pca.suffix_descriptors(state, both), repeats)
    table.add("encode PCA", 1000 * enc / len(both), 0.1, "seed Table 5", 1.0, "ms")
    ica_state = fit_ica(train, n_ics)
    _, enc = timed(lambda: ica.encode(ica_state, both), repeats)
    table.add(f"encode ICA ({n_ics})", 1000 * enc / len(both), 0.3, "seed Table 5", 1.0, "ms")


def encoder_rows(table: Table, db, query, repeats: int) -> None:
    shape = ae.IMAGE_SHAPE
    db, query = db.reshape(len(db), *shape), query.reshape(len(query), *shape)
    for name, spec, seed_ms in AE_MODELS:
        graphdef, params = ae.build(spec, jax.random.key(0))
        encode = ae.make_encode(graphdef)

        def both(encode=encode, params=params):
            return encode(params, db), encode(params, query)

        _, warm = timed(both, repeats)
        ms = 1000 * warm / (len(db) + len(query))
        table.add(f"encode {name}", ms, seed_ms, "seed Table 5", 0.1, "ms")


def input_rows(table: Table, train, db, query, repeats: int) -> None:
    """What an input costs (module docstring): ``train``, ``db`` and ``query`` whole
    images, flattened. The PCA fit is the one pca, ica and lda share, in lda's default 200
    leading components (``auto`` picks the solver: subspace iteration for so few)."""
    shape = ae.IMAGE_SHAPE
    images = train.reshape(len(train), *shape)
    both = np.concatenate([db, query]).reshape(-1, *shape)
    raw = raw_method.method
    k = min(LDA_COMPONENTS, len(train) - 1)
    _, on_pixels = timed(lambda: pca.fit_pca(train, k), repeats)
    for name in ("gradients", "standardised+gradients"):
        state = inputs.fit(name, images)
        values = np.asarray(inputs.apply(state, images))
        d = values.shape[1]
        fitted = raw.fit(images, None, None, input=name)
        _, enc = timed(lambda fitted=fitted: raw.encode(fitted, both), repeats)
        table.add(f"encode raw on {name} ({d:,} values)", 1000 * enc / len(both), 0.1,
                  "seed Table 5 PCA", 1.0, "ms")  # fmt: skip
        _, fit = timed(lambda values=values: pca.fit_pca(values, k), repeats)
        ratio = round(d / train.shape[1], 2)
        table.add(f"  PCA fit on it, {k} of {len(values):,} x {d:,}", fit, on_pixels,
                  f"on pixels ({train.shape[1]:,} values)", ratio)  # fmt: skip
        _, transform = timed(lambda state=state: inputs.apply(state, images), repeats)
        table.add("  the transform of the training images", transform, fit, "that fit", 1.0)


def protocol_row(table: Table, extra: list[str], tiny: bool) -> None:
    """``preset=paper`` (``tiny``: on ``TINY_PROTOCOL``'s route) with ``extra`` overrides."""
    with tempfile.TemporaryDirectory(prefix="vpr_jax-bench-") as tmp:
        logdir = Path(tmp) / "paper"
        args = ["preset=paper", *(TINY_PROTOCOL if tiny else []), *extra]
        wall, peak = sweep_in_fresh_process(args, logdir, fresh=not tiny)
        rows = read_results(logdir / "results.csv")
    from experiments.resolve import load

    # needs of the default settings: whether a method trains does not depend on them
    trained = {m for m, info in METHODS.items() if "training" in load(info).needs(None)}
    by_method: dict[str, float] = {}
    for row in rows:  # the trained methods' fit is their training; the linear fits are small
        seconds = row.fit_seconds if row.method in trained else 0.0
        by_method[row.method] = by_method.get(row.method, 0.0) + seconds
    label = "paper protocol" + (", tiny" if tiny else "")
    label += f" ({' '.join(extra)})" if extra else ""
    table.add(label, wall, PROTOCOL_GOAL_S, "goal: 5 min", 1.0)
    table.add("  the same vs the paper's Table 4", wall, PAPER_TABLE_4_S, "paper, 14 h 50 min", 1.0)
    print(
        f"  {len(rows)} cells, peak RSS {peak / 2**30:.2f} GiB; training seconds "
        f"{ {m: round(s, 1) for m, s in by_method.items() if m in trained} }"
    )


def full_route_row(table: Table) -> None:
    """Peak RSS of ``preset=full`` in a fresh process (its own logdir, thrown away)."""
    with tempfile.TemporaryDirectory(prefix="vpr_jax-bench-") as tmp:
        wall, peak = sweep_in_fresh_process(["preset=full"], Path(tmp) / "full")
    table.add(
        "whole route (preset=full) peak RSS",
        peak / 2**30,
        FULL_ROUTE_GOAL_GIB,
        "goal",
        1.0,
        "GiB",
    )
    print(f"  preset=full took {wall:.0f} s")


def scaling_rows(
    table: Table, repeats: int, plot_path: Path | None, frames, tiny: bool = False
) -> None:
    result = measure_scaling(list(frames), repeats, tiny)
    if plot_path is not None:
        plot_scaling(result, plot_path)
    fits = result["exponents"]
    table.add("matching time ~ n^x, x", fits["matching time"], 2.0, "expected", 1.1, "")
    table.add("matching memory ~ n^x, x", fits["matching memory"], 1.0, "expected", 1.1, "")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--repeats", type=int, default=None, help="warm runs per timing (median; 3, --tiny: 1)"
    )
    parser.add_argument(
        "--skip-protocol",
        action="store_true",
        help="leave out the paper protocol (the longest row)",
    )
    parser.add_argument(
        "--skip-full-route", action="store_true", help="leave out preset=full's peak RSS"
    )
    parser.add_argument(
        "--skip-scaling", action="store_true", help="leave out benchmarks/scaling.py's exponents"
    )
    parser.add_argument(
        "--scaling-plot", type=Path, default=None, help="draw scaling.py's log-log plot here"
    )
    parser.add_argument(
        "--protocol-args",
        default="",
        help="extra key=value overrides for the paper protocol, space-separated",
    )
    parser.add_argument(
        "--json", type=Path, default=Path("runs/run_all.json"), help="the table as JSON here"
    )
    parser.add_argument("--tiny", action="store_true", help=TINY_HELP)
    args = parser.parse_args()
    if args.repeats is None:
        args.repeats = 1 if args.tiny else 3
    start = time.perf_counter()
    device = jax.devices()[0]
    about = {
        "cpu": cpu_name(),
        "device": f"{device.platform} ({device.device_kind}), {jax.device_count()} device(s)",
        "jax": jax.__version__,
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "arguments": " ".join(sys.argv[1:]),
    }
    print(f"jax {about['jax']} on {about['device']}, os.cpu_count() = {os.cpu_count()}")
    print(f"cpu: {about['cpu']}", flush=True)

    table = Table()
    train, db, query = paper_route(**route_sizes(args.tiny))
    linear_rows(table, train, db, query, args.repeats, args.tiny)
    if args.tiny:  # the linear rows' tiny data keep every 8th pixel: whole images here
        _, db, query = paper_route(**route_sizes(args.tiny, images=True))
    encoder_rows(table, db, query, args.repeats)
    if args.tiny:  # the training images whole too
        train, _, _ = paper_route(**route_sizes(args.tiny, images=True))
    input_rows(table, train, db, query, args.repeats)
    if not args.skip_protocol:
        protocol_row(table, args.protocol_args.split(), args.tiny)
    if args.tiny and not args.skip_full_route:
        print("  whole route (preset=full) peak RSS: left out with --tiny (minutes, GiB)")
    elif not args.skip_full_route:
        full_route_row(table)
    if not args.skip_scaling:
        frames = TINY_SCALING_FRAMES if args.tiny else SCALING_FRAMES
        scaling_rows(table, max(1, args.repeats // 2), args.scaling_plot, frames, args.tiny)
    print()
    table.print()
    table.write_json(args.json, about)
    print(f"\ntotal {time.perf_counter() - start:.0f} s; the table as JSON: {args.json}")


if __name__ == "__main__":
    main()
