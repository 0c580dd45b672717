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

import errno
import os
import shlex
import signal
import sys
from pathlib import Path

# Only light modules here (no JAX): bad input is answered before JAX, Flax and orbax load.
from experiments.plan import make_plan
from vpr_jax import compile_cache
from vpr_jax.command_line import given_keys, parse_config
from vpr_jax.config import SweepConfig
from vpr_jax.errors import UserError
from vpr_jax.outputs.results import read_results
from vpr_jax.progress import RunLog


def run_sweep(cfg: SweepConfig, given: frozenset[str] = frozenset()) -> Path:
    """Validate config, logdir and data, then run every cell not yet in results.csv.
    ``given``: the keys set on the command line (defaults and presets may be trimmed to the
    data, these are refused)."""
    log = RunLog()
    plan = make_plan(cfg, log, given)

    from experiments.run import run_cells  # JAX, Flax, orbax: once the cheap checks pass

    compile_cache.use(cfg.compile_cache, log)  # before the fits, encoders and matcher compile
    if cfg.cluster.address is not None:
        from experiments import cluster

        cluster.connect(cfg.cluster, log)  # nothing written before it answers

    try:
        return run_cells(plan, log)
    except UserError as err:
        log.record(f"error: {err}")
        if err.detail:  # e.g. the traceback of a user's method: for the run log only
            log.record(err.detail)
        raise
    finally:
        if cfg.cluster.address is not None:
            cluster.disconnect()


class Terminated(KeyboardInterrupt):
    """SIGTERM (a cluster's scheduler ending the job, ``kill``): stop as on Ctrl-C."""


def _terminate(signum, frame):
    raise Terminated()


def interrupted_line(argv: list[str], cfg: SweepConfig | None) -> str:
    """What was saved and the command that resumes."""
    command = shlex.join(["python", "-m", "experiments.sweep", *argv])
    if cfg is None:
        return f"interrupted before anything was written; run again with: {command}"
    n, results = _saved_cells(cfg)
    saved = f"{n} finished cell(s) are saved in {results}" if n else "no cell had finished"
    return f"interrupted: {saved}; resume with: {command}"


# Faults of the disk, not of the input: the run stops, everything finished stays saved.
WRITE_FAULTS = {
    errno.ENOSPC: "free space",
    errno.EDQUOT: "free space within your quota",
    errno.EFBIG: "free space or raise the file-size limit (ulimit -f)",
    errno.EROFS: "make the logdir writable or set logdir=PATH",
    errno.EIO: "check the disk",
}


def _saved_cells(cfg: SweepConfig | None) -> tuple[int, Path | None]:
    """How many finished cells results.csv holds (0 when it is missing or not ours)."""
    if cfg is None:
        return 0, None
    results = Path(cfg.logdir).expanduser().resolve() / "results.csv"
    try:
        return len(read_results(results)), results
    except (OSError, ValueError):  # not ours: prepare_logdir refused it, nothing was written
        return 0, results


def write_fault_line(err: OSError, argv: list[str], cfg: SweepConfig | None) -> str:
    """One line for a disk fault while writing: the path, the cause, the fix, what is
    saved and the command that resumes."""
    where = err.filename or (Path(cfg.logdir).expanduser().resolve() if cfg else "the logdir")
    n, results = _saved_cells(cfg)
    saved = f"{n} finished cell(s) are saved in {results}" if n else "no cell had finished"
    command = shlex.join(["python", "-m", "experiments.sweep", *argv])
    return (
        f"cannot write {where}: {err.strerror} ({errno.errorcode[err.errno]}): "
        f"{WRITE_FAULTS[err.errno]}, then rerun the same command: {saved}; {command}"
    )


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
        run_sweep(cfg, given_keys(argv))
    except UserError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        if err.errno not in WRITE_FAULTS:
            raise
        print(f"error: {write_fault_line(err, argv, cfg)}", file=sys.stderr)
        # Exit now: at exit tensorboardX would retry its failed writes and print their
        # tracebacks; everything finished is already on disk.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(1)
    except KeyboardInterrupt as stop:
        print(interrupted_line(argv, cfg), file=sys.stderr)
        return 128 + (signal.SIGTERM if isinstance(stop, Terminated) else signal.SIGINT)
    return 0


if __name__ == "__main__":
    sys.exit(main())
