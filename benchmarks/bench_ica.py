"""FastICA speed and separation quality against scikit-learn, measured in the same run.

    python benchmarks/bench_ica.py [--repeats 2] [--components 64,256] [--tiny]

Seed's size: 5,000 x 2,048 training images (2,500 frames of summer and fall of the built-in
route). Both sides fit from raw images (centring, whitening, iterations) with the same
contrast (logcosh), tol (1e-4) and max_iter (200), on the same float32 array; scikit-learn is
FastICA(algorithm="parallel", whiten="unit-variance") with its default whiten_solver="svd",
and with whiten_solver="eigh" as a second, faster peer. Ours: warm median (compilation
excluded, reported separately). Goal: ours >= 5x faster.

A known-source problem of the same size shows the separation quality: n independent sources
(half Laplace, half uniform) mixed into 2,048 pixels by a random matrix, plus 1% noise;
Amari distance of the recovered unmixing from the true mixing (0 = perfect).

``--tiny`` (for the tests): ``common.TINY_SIZES`` (300 images of 256 pixels), 8 components
unless ``--components`` names others, one warm run.
"""

from __future__ import annotations

import argparse
import time
import warnings

import jax
import numpy as np
from common import TINY_HELP, TINY_ICA_COMPONENTS, paper_route, route_sizes, timed
from peers import native_blas_process
from sklearn.decomposition import FastICA

from vpr_jax.encoders import ica

SETTINGS = dict(fun="logcosh", max_iter=200, tol=1e-4)


def fit_ours(x: np.ndarray, c: int) -> ica.ICAState:
    return ica.fit_ica(x, jax.random.key(0), n_components=c, **SETTINGS)


def fit_sklearn(x: np.ndarray, c: int, solver: str) -> tuple[FastICA, float]:
    model = FastICA(
        c,
        algorithm="parallel",
        whiten="unit-variance",
        whiten_solver=solver,
        random_state=0,
        **SETTINGS,
    )
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # ConvergenceWarning: n_iter is printed instead
        model.fit(x)
    return model, time.perf_counter() - start


def known_sources(n: int, d: int, c: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    half = c // 2
    sources = np.concatenate([rng.laplace(size=(n, half)), rng.uniform(-1, 1, (n, c - half))], 1)
    mixing = rng.normal(size=(d, c))
    x = sources @ mixing.T
    x += 0.01 * x.std() * rng.normal(size=x.shape)
    return x.astype(np.float32), mixing


def main() -> None:
    native_blas_process()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--repeats", type=int, default=None, help="warm runs of ours (median; 2, --tiny: 1)"
    )
    parser.add_argument(
        "--components", default=None, help="n_components to measure (64,256; --tiny: 8)"
    )
    parser.add_argument("--tiny", action="store_true", help=TINY_HELP)
    args = parser.parse_args()
    if args.repeats is None:
        args.repeats = 1 if args.tiny else 2
    if args.components is None:
        args.components = str(TINY_ICA_COMPONENTS) if args.tiny else "64,256"
    sizes = [int(c) for c in args.components.split(",")]

    train, _, _ = paper_route(**route_sizes(args.tiny))
    print(
        f"jax {jax.__version__} on {jax.devices()[0].platform}; images {train.shape} "
        f"{train.dtype}; fun={SETTINGS['fun']} tol={SETTINGS['tol']} "
        f"max_iter={SETTINGS['max_iter']}\n"
    )
    header = f"{'problem':<22} {'fit':<26} {'seconds':>8} {'n_iter':>7} {'speed-up':>9}"

    print("Route images (speed-up = peer seconds / ours; goal >= 5x against the default)")
    print(header)
    for c in sizes:
        first, ours = timed(lambda c=c: fit_ours(train, c), args.repeats)
        state = fit_ours(train, c)
        name = f"images, {c} ICs"
        print(
            f"{name:<22} {'ours (JAX)':<26} {ours:8.2f} {int(state.n_iter):7d} {'':>9}"
            f"   first call {first:.2f} s incl. compilation"
        )
        for solver in ("svd", "eigh"):
            model, peer = fit_sklearn(train, c, solver)
            print(
                f"{'':<22} {'sklearn whiten_solver=' + solver:<26} {peer:8.2f} "
                f"{model.n_iter_:7d} {peer / ours:8.1f}x"
            )

    print(
        f"\nKnown sources mixed into {train.shape[0]:,} x {train.shape[1]:,} "
        "(Amari distance: lower is better)"
    )
    print(header + f" {'amari':>7}")
    for c in sizes:
        x, mixing = known_sources(train.shape[0], train.shape[1], c)
        _, ours = timed(lambda c=c, x=x: fit_ours(x, c), args.repeats)
        state = fit_ours(x, c)
        d_ours = ica.amari_distance(np.asarray(state.unmixing @ state.whitening), mixing)
        model, peer = fit_sklearn(x, c, "svd")
        d_peer = ica.amari_distance(model.components_, mixing)
        name = f"{c} sources"
        print(
            f"{name:<22} {'ours (JAX)':<26} {ours:8.2f} {int(state.n_iter):7d} {'':>9} "
            f"{d_ours:7.4f}"
        )
        print(
            f"{'':<22} {'sklearn whiten_solver=svd':<26} {peer:8.2f} {model.n_iter_:7d} "
            f"{peer / ours:8.1f}x {d_peer:7.4f}"
        )


if __name__ == "__main__":
    main()
