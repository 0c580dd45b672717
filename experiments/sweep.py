"""The sweep runner: season pairs x methods x removed-PC counts (x sequence lengths) into
TensorBoard and tables.

    python -m experiments.sweep                       # default preset=quick, all pairs
    python -m experiments.sweep season_pairs=summer-fall,spring-fall removed_pcs=[0,50]

Writes under ``logdir`` (default runs/<preset>): one TensorBoard run per cell, results.csv
(a row per finished cell, written atomically as the cell ends), results.md, figures/ and
sweep.log. Rerunning the same command skips finished cells. Bad input: one line on stderr,
exit code 2, nothing in the logdir touched.
"""

from __future__ import annotations

import itertools
import os
import shlex
import signal
import sys
import tempfile
from pathlib import Path

import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

# Only light modules here (no JAX): bad input is answered before JAX, Flax and orbax load.
from vpr_jax.config import (
    SWEEPS_REMOVED_PCS,
    SequenceConfig,
    SweepConfig,
    identity,
    parse_config,
    with_old_defaults,
)
from vpr_jax.data import SEASON_ORDER, load_route
from vpr_jax.data.splits import make_split
from vpr_jax.errors import UserError
from vpr_jax.preprocess import preprocess_route
from vpr_jax.results import read_results


class RunLog:
    """Prints every line and, once the logdir is validated, appends it to sweep.log."""

    def __init__(self):
        self._lines: list[str] = []
        self._path: Path | None = None

    def open(self, path: Path) -> None:
        self._path = path
        with open(path, "a") as f:
            f.writelines(line + "\n" for line in self._lines)

    def __call__(self, line: str) -> None:
        print(line, flush=True)
        if self._path is None:
            self._lines.append(line)
        else:
            with open(self._path, "a") as f:
                f.write(line + "\n")


def resolve_pairs(spec: str, seasons: tuple[str, ...]) -> list[tuple[str, str]]:
    """``all`` -> every unordered pair, database season first (SEASON_ORDER); else db-query."""
    if spec.strip() == "all":
        rank = {s: i for i, s in enumerate(SEASON_ORDER)}
        ordered = sorted(seasons, key=lambda s: rank.get(s, len(rank)))
        return list(itertools.combinations(ordered, 2))
    pairs = []
    for name in (p.strip() for p in spec.split(",") if p.strip()):
        db, sep, query = name.partition("-")
        if not sep or not db or not query or "-" in query:
            raise UserError(f"season pair {name!r} is not db-query: write e.g. "
                            "season_pairs=summer-fall,spring-fall or season_pairs=all")
        if db == query:
            raise UserError(f"season pair {name!r} names {db} twice: a pair needs two "
                            "different seasons, e.g. summer-fall")
        unknown = [s for s in (db, query) if s not in seasons]
        if unknown:
            raise UserError(f"season pair {name!r} uses {', '.join(unknown)}, not in "
                            f"data.seasons={list(seasons)}: add it there or fix the pair")
        if (db, query) not in pairs:
            pairs.append((db, query))
    if not pairs:
        raise UserError("season_pairs is empty: write season_pairs=all or e.g. summer-fall")
    return pairs


def saved_identity(path: Path) -> dict:
    """The identity of a logdir's config.yaml; keys added to the suite since it was written
    take their defaults, which reproduce what the suite did before they existed, or where a
    new default changed the numbers, the value the old runs used (CHANGED_DEFAULTS)."""
    try:
        saved = OmegaConf.load(path)
    except (OSError, yaml.YAMLError, OmegaConfBaseException) as err:
        saved = err
    if not isinstance(saved, DictConfig):
        raise UserError(f"{path} is not a sweep config ({type(saved).__name__}), so the logdir "
                        "cannot be resumed safely: use a new logdir=PATH") from None
    saved = with_old_defaults(OmegaConf.to_container(saved))
    try:
        saved = OmegaConf.to_container(OmegaConf.merge(OmegaConf.structured(SweepConfig), saved))
    except OmegaConfBaseException:
        pass  # keys this version does not know: compared as they are, and so they differ
    return identity(saved)


def prepare_logdir(logdir: Path, cfg: SweepConfig) -> None:
    """Refuse unusable or foreign log directories. Creates nothing: the folder is made when
    the first file is written into it."""
    existing = next(p for p in (logdir, *logdir.parents) if p.exists())
    if not existing.is_dir():
        where = "is a file" if existing == logdir else f"cannot be made: {existing} is a file"
        raise UserError(f"logdir {logdir} {where}: set logdir=PATH to a folder")
    try:
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as err:
        raise UserError(f"logdir {logdir} is not writable ({existing}: {err.strerror}): set "
                        "logdir=PATH to a folder you can write") from None
    saved, results = logdir / "config.yaml", logdir / "results.csv"
    if saved.exists():
        now = identity(cfg)
        before = saved_identity(saved)
        differ = sorted(k for k in set(before) | set(now) if before.get(k) != now.get(k))
        if differ:
            raise UserError(f"logdir {logdir} holds results of a different configuration "
                            f"(differs in {', '.join(differ)}): use a new logdir=PATH, or "
                            "delete that folder to start fresh")
    elif results.exists():
        raise UserError(f"logdir {logdir} has a results.csv but no config.yaml, so it cannot "
                        "be resumed safely: use a new logdir=PATH")
    try:
        read_results(results)
    except (OSError, ValueError) as err:
        raise UserError(f"{results} is not a results table this sweep can resume ({err}): "
                        "move it away or use a new logdir=PATH") from None


def check_removed_pcs(cfg: SweepConfig, n_train_images: int, n_pixels: int) -> None:
    if not SWEEPS_REMOVED_PCS & set(cfg.methods):
        return
    limit = min(n_train_images - 1, n_pixels)
    if max(cfg.removed_pcs) >= limit:
        raise UserError(f"removed_pcs={list(cfg.removed_pcs)} leaves no component: PCA of "
                        f"{n_train_images} training images has {limit} components, so use "
                        f"counts below {limit}")
    n_ica = cfg.ica.n_components
    if "ica" in cfg.methods and n_ica != "all" and max(cfg.removed_pcs) + n_ica > limit:
        raise UserError(
            f"ica.n_components={n_ica} with removed_pcs up to {max(cfg.removed_pcs)} needs "
            f"{max(cfg.removed_pcs) + n_ica} components but PCA of {n_train_images} training "
            f"images has {limit}: use ica.n_components <= {limit - max(cfg.removed_pcs)}, "
            "ica.n_components=all, or smaller removed_pcs"
        )


def run_sweep(cfg: SweepConfig) -> Path:
    """Validate config, logdir and data, then run every cell not yet in results.csv."""
    log = RunLog()
    logdir = Path(cfg.logdir).expanduser().resolve()
    pairs = resolve_pairs(cfg.season_pairs, cfg.data.seasons)
    prepare_logdir(logdir, cfg)
    if not cfg.sequence.enabled and cfg.sequence.ds != SequenceConfig().ds:
        log(f"note: sequence.ds={list(cfg.sequence.ds)} is ignored while sequence.enabled="
            "false: single images only (add sequence.enabled=true for the ds axis)")
    route = load_route(cfg.data, cfg.seed, log)
    route = preprocess_route(route, cfg.preprocess, cfg.patchnorm.size, cfg.patchnorm.rounded,
                             log)  # fmt: skip
    split = make_split(route.frame_ids, cfg.split)
    check_removed_pcs(cfg, 2 * len(split.train), int(route.images[pairs[0][0]][0].size))

    from experiments.cells import run_cells  # JAX, Flax, orbax: once the cheap checks pass

    return run_cells(cfg, log, logdir, pairs, route, split)


class Terminated(KeyboardInterrupt):
    """SIGTERM (a cluster's scheduler ending the job, ``kill``): stop as on Ctrl-C."""


def _terminate(signum, frame):
    raise Terminated()


def interrupted_line(argv: list[str], cfg: SweepConfig | None) -> str:
    """What was saved and the command that resumes."""
    command = shlex.join(["python", "-m", "experiments.sweep", *argv])
    if cfg is None:
        return f"interrupted before anything was written; run again with: {command}"
    results = Path(cfg.logdir).expanduser().resolve() / "results.csv"
    try:
        n = len(read_results(results))
    except (OSError, ValueError):  # not ours: prepare_logdir refused it, nothing was written
        n = 0
    saved = f"{n} finished cell(s) are saved in {results}" if n else "no cell had finished"
    return f"interrupted: {saved}; resume with: {command}"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    # Our readers report unreadable files themselves, in one line; OpenCV's and FFmpeg's own
    # logs would add more, less helpful ones. FFmpeg reads its level when cv2 is imported.
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET
    import cv2  # every data source reads or renders with it

    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    signal.signal(signal.SIGTERM, _terminate)
    cfg = None
    try:
        cfg = parse_config(argv)
        run_sweep(cfg)
    except UserError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as stop:
        print(interrupted_line(argv, cfg), file=sys.stderr)
        return 128 + (signal.SIGTERM if isinstance(stop, Terminated) else signal.SIGINT)
    return 0


if __name__ == "__main__":
    sys.exit(main())
