"""A sweep's log directory: which configurations may share one, and the checks before a run.

A logdir holds the results of one configuration's *identity*: the keys that determine the
numbers of every cell. Keys that only add cells (pairs, methods, removed-PC counts, sequence
lengths) or change presentation and where the same numbers are computed may differ between
runs into the same logdir; any other difference is refused, so a table never mixes
configurations. No JAX here: these checks run before it loads.
"""

from __future__ import annotations

import dataclasses
import fcntl
import os
import socket
import tempfile
import time
from pathlib import Path

import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from vpr_jax.config import SweepConfig, TrainConfig, plain, to_dict
from vpr_jax.errors import UserError
from vpr_jax.results import read_results

# Keys that may differ between runs sharing a logdir: they add cells or change presentation,
# or where and in what blocks the same numbers are computed (up to float rounding), never
# the numbers of a cell already written.
EXTENDABLE_KEYS = (
    "preset",
    "season_pairs",
    "methods",
    "removed_pcs",
    "logdir",
    "tb",
    "matching",
    "mesh",
)
# train.* keys that say where and how often models are saved, not what is trained.
TRAIN_BOOKKEEPING = ("checkpoint_dir", "checkpoint_every_s")
# Keys inside a group that add cells, like removed_pcs: the ds axis, the auto-encoders'
# objectives. The groups' other keys change the numbers of their cells.
AXIS_KEYS = {"sequence": ("enabled", "ds"), "fae": ("objective",), "cae": ("objective",)}
# Keys added with a default that changed what the suite computes: a saved config without
# them was computed with the value here (other new keys' defaults reproduce the old runs).
CHANGED_DEFAULTS = {
    ("fae", "input_centre"): 0.0,
    ("fae", "standardise"): False,
    ("cae", "model"): "calc",
    ("cae", "space_to_depth"): 1,
    ("cae", "standardise"): False,
    ("split", "val_fraction"): 0.0,
}  # no validation stretch before it


def identity(cfg: SweepConfig | dict) -> dict:
    """The part of a config (or of its saved YAML) that determines the numbers of every cell,
    as plain YAML data."""
    out = to_dict(cfg) if isinstance(cfg, SweepConfig) else plain(cfg)
    out = {k: v for k, v in out.items() if k not in EXTENDABLE_KEYS}
    out.get("data", {}).pop("cache_dir", None)  # where decoded videos are kept, not what
    for key in TRAIN_BOOKKEEPING:
        out.get("train", {}).pop(key, None)
    for group, keys in AXIS_KEYS.items():
        for key in keys:
            out.get(group, {}).pop(key, None)
    return out


def training_identity(settings: TrainConfig) -> dict:
    """The training settings that determine a trained model's weights (not where or how often
    it is saved)."""
    return {
        k: v for k, v in plain(dataclasses.asdict(settings)).items() if k not in TRAIN_BOOKKEEPING
    }


def with_old_defaults(saved: dict) -> dict:
    """A saved config (plain data) with every key of ``CHANGED_DEFAULTS`` it lacks set to
    the value its runs used."""
    for (group, key), value in CHANGED_DEFAULTS.items():
        if isinstance(saved.get(group), dict):
            saved[group].setdefault(key, value)
    return saved


def saved_identity(path: Path) -> dict:
    """The identity of a logdir's config.yaml; keys added to the suite since it was written
    take their defaults, which reproduce what the suite did before they existed, or where a
    new default changed the numbers, the value the old runs used (CHANGED_DEFAULTS)."""
    try:
        saved = OmegaConf.load(path)
    except (OSError, yaml.YAMLError, OmegaConfBaseException) as err:
        saved = err
    if not isinstance(saved, DictConfig):
        raise UserError(
            f"{path} is not a sweep config ({type(saved).__name__}), so the logdir "
            "cannot be resumed safely: use a new logdir=PATH"
        ) from None
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
        raise UserError(
            f"logdir {logdir} is not writable ({existing}: {err.strerror}): set "
            "logdir=PATH to a folder you can write"
        ) from None
    saved, results = logdir / "config.yaml", logdir / "results.csv"
    if saved.exists():
        now = identity(cfg)
        before = saved_identity(saved)
        differ = sorted(k for k in set(before) | set(now) if before.get(k) != now.get(k))
        if differ:
            raise UserError(
                f"logdir {logdir} holds results of a different configuration "
                f"(differs in {', '.join(differ)}): use a new logdir=PATH, or "
                "delete that folder to start fresh"
            )
    elif results.exists():
        raise UserError(
            f"logdir {logdir} has a results.csv but no config.yaml, so it cannot "
            "be resumed safely: use a new logdir=PATH"
        )
    try:
        read_results(results)
    except (OSError, ValueError) as err:
        raise UserError(
            f"{results} is not a results table this sweep can resume ({err}): "
            "move it away or use a new logdir=PATH"
        ) from None


LOCK_NAME = ".lock"
_held: dict[Path, int] = {}  # logdir -> the open lock file: held until the process ends


def lock_logdir(logdir: Path) -> None:
    """Make this process the logdir's only writer: an exclusive ``flock`` on
    ``logdir/.lock``, kept until the process exits (the kernel drops it then, also on
    SIGKILL, so no stale lock is left). The file says who holds it (pid, host, start time).
    Raises UserError naming the holder when another sweep has it; nothing is changed then.
    """
    lock_folder(logdir, "logdir", "wait for it to finish, or use another logdir=PATH")


def lock_folder(folder: Path, what: str, fix: str) -> None:
    """``lock_logdir`` for any folder only one process may write (e.g. a model's checkpoint
    folder while it trains: two logdirs of one name under different parents share it)."""
    folder = Path(folder)
    if folder in _held:
        return
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(folder / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as err:
        raise UserError(
            f"{what} {folder} cannot be locked ({err.strerror}): set it to a folder you can write"
        ) from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = os.pread(fd, 4096, 0).decode(errors="replace").strip() or "another process"
        os.close(fd)
        raise UserError(f"{what} {folder} is in use by another sweep ({holder}): {fix}") from None
    os.ftruncate(fd, 0)
    os.pwrite(
        fd,
        (
            f"pid {os.getpid()} on {socket.gethostname()} since "
            f"{time.strftime('%Y-%m-%d %H:%M:%S')}\n"
        ).encode(),
        0,
    )
    _held[folder] = fd
