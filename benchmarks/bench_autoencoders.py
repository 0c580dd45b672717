"""Auto-encoder speed: encode ms per image against the paper's Table 5, and training s per epoch.

    python benchmarks/bench_autoencoders.py [--repeats 3] [--epoch-steps N] [--tiny]

Models: FAE (2,048 -> 256 -> 2,048), the default CAE (``cae.model=fast``: 2x2 pixel blocks to
channels, 3x3 convolutions of 24 and 48 channels, a 4x8x32 code), the quick preset's (the
same at 16 and 32 channels) and the CALC-sized CAE (``cae.model=calc``:
channels 64, 128; kernels 5, 4; code channels 8), float32, initialised from
jax.random.key(0) (speed does not depend on training). Encoder MFLOP per image are XLA's
count of the jitted encoder.

Encode: the database and the queries of the paper's test stretch (3,569 + 3,569 images of
32x64), each season in one call, as the sweep does it (host numpy arrays in, device codes
out). Warm median of --repeats runs (compilation excluded; the first call is reported
separately). Peer: the paper's Table 5 on a GTX 1060, FAE 3.26 ms and CAE 17.5 ms per image;
goal: ours <= 0.1x of it (FAE <= 0.326 ms, CAE <= 1.75 ms).

Training: the paper's size, 4,500 images (2 x 2,500 training frames less each season's 10%
validation tail, as the sweep splits them), batch 64 -> 70 steps per epoch, adam 1e-3, Table 2
augmentation on; the jitted train_step over one shuffled epoch after one warm-up step (its
compilation is reported separately). With --epoch-steps N < 70 only N steps are timed and the
epoch is extrapolated. No peer: the paper reports training totals for the whole study only.

``--tiny`` (for the tests): ``common.TINY_SIZES``'s whole images (100 + 100 to encode, 270 to
train on), one warm run, 2 training steps of batch 16 per model.
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from common import TINY_HELP, paper_route, route_sizes, timed

from vpr_jax.config import TrainConfig
from vpr_jax.data.augment import AugmentConfig
from vpr_jax.encoders import autoencoders as ae
from vpr_jax.encoders.train_programs import make_optimizer, make_train_step
from vpr_jax.methods import cae, training

TINY_EPOCH_STEPS, TINY_BATCH = 2, 16


def _cae(model: str, **changes) -> ae.CAESpec:
    """The CAE the sweep builds for ``cae.model=MODEL`` and ``cae.KEY=VALUE`` changes: the
    named architecture with the parts set overriding it (``cae.architecture``)."""
    settings = cae.Settings(model=model, **changes)
    a = cae.architecture(settings)
    return ae.CAESpec(
        channels=tuple(a["channels"]),
        kernel_sizes=tuple(a["kernel_sizes"]),
        code_channels=a["code_channels"],
        space_to_depth=a["space_to_depth"],
        standardise=training.is_standardised(settings.input),
    )


MODELS = (  # name, spec, paper's Table 5 ms per image on a GTX 1060 (its peer)
    ("FAE hidden 256", ae.FAESpec(standardise=True), 3.26),
    ("CAE fast (24,48) s2d2", _cae("fast"), 17.5),
    ("CAE quick (16,32) s2d2", _cae("fast", channels=(16, 32)), 17.5),
    ("CAE calc (64,128) c8", _cae("calc"), 17.5),
)
GOAL = 0.1  # ours / seed at most
PAPER_TRAINING = "FAE 3 h 44 min, CAE 7 h 56 min"  # the paper's totals for the whole study


def encoder_params(params: dict) -> int:
    """Parameters the code depends on (the encoder half)."""
    if "encoder" in params:
        return ae.count_params(params["encoder"])
    return ae.count_params(params["down"]) + ae.count_params(params["to_code"])


def flops(jitted, *args) -> float | None:
    """XLA's flop count of one call (None where the backend gives none)."""
    try:
        cost = jitted.lower(*args).cost_analysis()
    except Exception:  # noqa: BLE001 - the count is a nicety, never a reason to fail
        return None
    if isinstance(cost, list | tuple):
        cost = cost[0] if cost else None
    return float(cost["flops"]) if cost and cost.get("flops") else None


def gflops(flop: float | None, seconds: float) -> str:
    return f"{flop / seconds / 1e9:7.1f}" if flop else f"{'n/a':>7}"


def bench_encode(
    spec, seed_ms: float, name: str, db: np.ndarray, query: np.ndarray, repeats: int
) -> None:
    graphdef, params = ae.build(spec, jax.random.key(0))
    encode = ae.make_encode(graphdef)
    first, warm = timed(lambda: (encode(params, db), encode(params, query)), repeats)
    code = encode(params, db[:1]).shape[1]
    shape = jax.ShapeDtypeStruct(db.shape, jnp.float32)
    flop = flops(encode, params, shape)
    flop = 2 * flop if flop else None  # database and queries
    ms = 1000 * warm / (len(db) + len(query))
    ratio = ms / seed_ms
    met = "yes" if ratio <= GOAL else "NO"
    mflop = f"{flop / (len(db) + len(query)) / 1e6:7.1f}" if flop else f"{'n/a':>7}"
    print(
        f"{name:<24} {ae.count_params(params):>9,} {encoder_params(params):>9,} {code:>5} "
        f"{mflop} {first:8.2f} {max(first - warm, 0.0):8.2f} {warm:8.3f} {ms:9.4f} "
        f"{gflops(flop, warm)} {seed_ms:8.2f} {ratio:7.4f}x {met:>4}"
    )


def bench_train(spec, name: str, images: np.ndarray, steps: int, settings: TrainConfig) -> None:
    graphdef, params = ae.build(spec, jax.random.key(0))
    tx = make_optimizer(settings)
    opt_state = tx.init(params)
    train_step = make_train_step(graphdef, tx, AugmentConfig() if settings.augment else None)
    key = jax.random.key(0)
    n, b = len(images), settings.batch_size
    per_epoch = n // b  # fit_autoencoder drops the tail: one compiled batch shape
    steps = min(steps, per_epoch)
    data = jnp.asarray(images)
    order = jax.random.permutation(jax.random.fold_in(key, 0), n)

    def batch(s: int) -> jax.Array:  # as fit_autoencoder draws it: a gather on the device
        return data[order[s * b : (s + 1) * b]]

    start = time.perf_counter()  # warm-up: compile the step (and the gather) on step 0
    params, opt_state, metrics = jax.block_until_ready(
        train_step(params, opt_state, batch(0), jax.random.fold_in(key, 1))
    )
    compile_s = time.perf_counter() - start
    flop = flops(train_step, params, opt_state, batch(0), jax.random.fold_in(key, 1))

    start = time.perf_counter()
    for s in range(steps):
        params, opt_state, metrics = train_step(
            params, opt_state, batch(s), jax.random.fold_in(key, s + 2)
        )
    jax.block_until_ready((params, opt_state, metrics))
    seconds = time.perf_counter() - start
    epoch = seconds / steps * per_epoch
    timed_note = f"{steps}/{per_epoch}" + ("" if steps == per_epoch else " (extrapolated)")
    print(
        f"{name:<24} {timed_note:<20} {compile_s:8.2f} {seconds:8.2f} {epoch:9.2f} "
        f"{per_epoch * b / epoch:9.0f} {gflops(flop and flop * steps, seconds)} "
        f"{float(metrics['loss']):9.5f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--repeats", type=int, default=None, help="warm encode runs (median; 3, --tiny: 1)"
    )
    parser.add_argument(
        "--epoch-steps",
        type=int,
        default=None,
        help="training steps timed per model (default: the whole epoch, 70; --tiny: "
        f"{TINY_EPOCH_STEPS}); fewer are extrapolated to the epoch",
    )
    parser.add_argument("--tiny", action="store_true", help=TINY_HELP)
    args = parser.parse_args()
    if args.repeats is None:
        args.repeats = 1 if args.tiny else 3
    if args.epoch_steps is None and args.tiny:
        args.epoch_steps = TINY_EPOCH_STEPS
    if args.epoch_steps is not None and args.epoch_steps < 1:
        parser.error("--epoch-steps must be >= 1")
    start = time.perf_counter()

    train, db, query = paper_route(**route_sizes(args.tiny, images=True))
    shape = ae.IMAGE_SHAPE
    db, query = db.reshape(len(db), *shape), query.reshape(len(query), *shape)
    # The paper's 4,500 training images: each season's stretch less its last tenth.
    seasons = np.split(train.reshape(len(train), *shape), 2)
    train_images = np.concatenate([s[: round(0.9 * len(s))] for s in seasons])
    device = jax.devices()[0]
    print(
        f"jax {jax.__version__} on {device.platform} ({device.device_kind}); "
        f"os.cpu_count() = {os.cpu_count()}; float32 images {shape[0]}x{shape[1]}\n"
    )

    print(
        f"Encode {len(db):,} database + {len(query):,} query images, one call per season; "
        f"warm median of {args.repeats}"
    )
    print(f"(peer: the paper's Table 5 on a GTX 1060; goal: ours <= {GOAL}x of it)")
    print(
        f"{'model':<24} {'params':>9} {'encoder':>9} {'code':>5} {'MFLOP':>7} {'first s':>8} "
        f"{'compile':>8} {'warm s':>8} {'ms/image':>9} {'GFLOP/s':>7} {'seed ms':>8} "
        f"{'ratio':>8} {'goal':>4}"
    )
    for name, spec, seed_ms in MODELS:
        bench_encode(spec, seed_ms, name, db, query, args.repeats)
    print(
        "  compile = first call (compilation + one run) - warm run; "
        "every CAE is compared with the paper's CAE; MFLOP: encoder, per image"
    )

    settings = TrainConfig(batch_size=TINY_BATCH) if args.tiny else TrainConfig()
    per_epoch = len(train_images) // settings.batch_size
    steps = per_epoch if args.epoch_steps is None else args.epoch_steps
    print(
        f"\nTraining: {len(train_images):,} images, batch {settings.batch_size} "
        f"({per_epoch} steps/epoch), {settings.optimizer} {settings.learning_rate:g}, "
        f"augmentation {AugmentConfig()}"
    )
    print(
        f"{'model':<24} {'steps timed':<20} {'compile':>8} {'timed s':>8} {'s/epoch':>9} "
        f"{'images/s':>9} {'GFLOP/s':>7} {'loss':>9}"
    )
    for name, spec, _ in MODELS:
        bench_train(spec, name, train_images, steps, settings)
    print(
        f"  no peer: the paper gives training totals for its whole study only "
        f"({PAPER_TRAINING}, GTX 1060)"
    )
    print(f"\ntotal {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
