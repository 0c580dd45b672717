"""A sweep's log directory: which configurations may share one, and the checks before a run.

A logdir holds the results of one configuration's *identity*: the keys that determine the
numbers of every cell. Keys that only add cells (pairs, methods, removed-PC counts, seeds,
sequence lengths, values of a method's swept settings) or change presentation and where the
same numbers are computed may differ between runs into the same logdir; any other
difference is refused, so a table never mixes configurations. A method's settings are
compared for the methods both runs have, by the method's own rule (the plan passes it). No
JAX here.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from pathlib import Path

import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from vpr_jax.config import TRAIN_BOOKKEEPING, SweepConfig, plain, to_dict
from vpr_jax.errors import UserError
from vpr_jax.files import lock_folder
from vpr_jax.method_table import NAMES
from vpr_jax.outputs.results import SWEEP_KEYS, read_results

# Keys that may differ between runs sharing a logdir: they add cells or change presentation,
# or where and in what blocks the same numbers are computed (up to float rounding), never
# the numbers of a cell already written.
EXTENDABLE_KEYS = (
    "preset",
    "season_pairs",
    "methods",
    *SWEEP_KEYS,
    "seeds",
    "logdir",
    "tb",
    "matching",
    "mesh",
    "cluster",
)
# Keys inside a group that add cells, like the sweep keys: the ds axis. The group's other keys
# change the numbers of its cells.
AXIS_KEYS = {"sequence": ("enabled", "ds"), "split": ("train_places",)}
# The layout of a logdir (config.yaml, results.csv's columns, the runs' files): written as
# config.yaml's ``format``; a logdir of another format is refused, never read or extended.
FORMAT = 3


ENCODERS_CSV = "encoders.csv"  # logdir/encoders.csv: every saved encoder and its folder
LISTING = (
    "pair",
    "method",
    "objective",
    "setting",
    "cell",  # every swept setting of the chosen cell, as name=value
    "seed",
    "kept_epoch",  # a trained model: the epoch kept (0: its start, untouched by training)
    "val_recall_at_1",
    "selected",
    "folder",
)


def fitted_root(cfg: SweepConfig, logdir: Path) -> Path:
    """Where a logdir's fitted states and trained models go, a folder per pair:
    ``<train.checkpoint_dir>/<logdir's name>/<pair>/<method's folder>``."""
    return Path(cfg.train.checkpoint_dir).expanduser().resolve() / Path(logdir).name


def identity(cfg: SweepConfig | dict) -> dict:
    """The part of a config (or of its saved YAML) that determines the numbers of every cell,
    as plain YAML data."""
    out = to_dict(cfg) if isinstance(cfg, SweepConfig) else _with_new_keys(plain(cfg))
    # A method's settings (<name>.*, plugin.<name>.*) and precomputed.<name>.* change only
    # their method's cells: compared per method (check_same_config)
    skipped = (*EXTENDABLE_KEYS, *NAMES, "plugin", "precomputed")
    out = {k: v for k, v in out.items() if k not in skipped}
    out.get("data", {}).pop("cache_dir", None)  # where decoded videos are kept, not what
    out.pop("compile_cache", None)  # where compiled programs are kept: the same programs
    for key in TRAIN_BOOKKEEPING:
        out.get("train", {}).pop(key, None)
    for group, keys in AXIS_KEYS.items():
        for key in keys:
            out.get(group, {}).pop(key, None)
    return out


def _with_new_keys(saved: dict, defaults: dict | None = None) -> dict:
    """A config.yaml an earlier version wrote, with the keys it did not have yet (a group
    such as ``gradients``) at their defaults: what that version did, before the key was
    there to change it."""
    defaults = to_dict(SweepConfig()) if defaults is None else defaults
    out = dict(saved)
    for key, value in defaults.items():
        if key not in out:
            out[key] = value
        elif isinstance(value, dict) and value and isinstance(out[key], dict):
            out[key] = _with_new_keys(out[key], value)
    return out


def config_yaml(cfg: SweepConfig) -> str:
    """config.yaml: the format of the logdir, then the whole config."""
    return OmegaConf.to_yaml({"format": FORMAT, **to_dict(cfg)})


def outside_settings(cfg: SweepConfig | dict) -> dict[str, dict]:
    """Per set of outside descriptors, its ``precomputed.<name>.*`` files."""
    out = to_dict(cfg) if isinstance(cfg, SweepConfig) else plain(cfg)
    return {f"precomputed.{n}": v for n, v in out.get("precomputed", {}).items()}


def saved_config(path: Path) -> dict:
    """A logdir's config.yaml as plain data, without its format; one of another format (or
    not a sweep config at all) is refused."""
    try:
        saved = OmegaConf.load(path)
    except (OSError, yaml.YAMLError, OmegaConfBaseException) as err:
        saved = err
    if not isinstance(saved, DictConfig):
        raise UserError(
            f"{path} is not a sweep config ({type(saved).__name__}), so the logdir "
            "cannot be resumed safely: use a new logdir=PATH"
        ) from None
    saved = OmegaConf.to_container(saved)  # interpolations kept as written, unresolved
    where = _interpolation(saved)
    if where is not None:
        raise UserError(
            f"{path} holds an interpolation at {where} (a value with ${{...}}), which would "
            "read this machine's environment or other keys: a sweep never writes one, so "
            "nothing was resolved; use the logdir a sweep wrote, or a new logdir=PATH"
        )
    found = saved.pop("format", None)
    if found != FORMAT:
        raise UserError(
            f"logdir {path.parent} was written in another format ({found}; this version "
            f"writes {FORMAT}): use a new logdir=PATH"
        )
    return saved


def _interpolation(data, key: str = "") -> str | None:
    """The first key of ``data`` whose value holds an OmegaConf interpolation (``${...}``:
    an environment variable, another key, a resolver), or None."""
    if isinstance(data, dict):
        items = data.items()
    elif isinstance(data, list):
        items = ((str(i), v) for i, v in enumerate(data))
    else:
        return key if isinstance(data, str) and "${" in data else None
    for name, value in items:
        found = _interpolation(value, f"{key}.{name}" if key else str(name))
        if found is not None:
            return found
    return None


def prepare_logdir(logdir: Path) -> None:
    """Refuse unusable log directories (a file, not writable, an unreadable config.yaml or
    results.csv); ``check_same_config`` refuses foreign ones once the config is final.
    Creates nothing: the folder is made when the first file is written into it."""
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
        saved_config(saved)
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


def check_same_config(
    logdir: Path, cfg: SweepConfig, method_identities: Callable[[dict], dict[str, dict]]
) -> None:
    """Refuse a logdir whose config.yaml has another identity than ``cfg`` (the config as it
    will run: counts fitted to the training set), or other settings for a method (or set of
    outside descriptors) both have; ``method_identities(config as plain data)``: each
    method's (``experiments.resolve.settings_identities``)."""
    saved = logdir / "config.yaml"
    if not saved.exists():
        return
    now, before_config = identity(cfg), saved_config(saved)
    before = identity(before_config)
    differ = sorted(k for k in set(before) | set(now) if before.get(k) != now.get(k))
    mine = {**method_identities(to_dict(cfg)), **outside_settings(cfg)}
    theirs = {**method_identities(before_config), **outside_settings(before_config)}
    differ += [n for n in sorted(set(mine) & set(theirs)) if mine[n] != theirs[n]]
    if differ:
        raise UserError(
            f"logdir {logdir} holds results of a different configuration "
            f"(differs in {', '.join(differ)}): use a new logdir=PATH, or "
            "delete that folder to start fresh"
        )


def lock_logdir(logdir: Path) -> None:
    """Make this process the logdir's only writer: an exclusive ``flock`` on
    ``logdir/.lock``, kept until the process exits (the kernel drops it then, also on
    SIGKILL, so no stale lock is left). The file says who holds it (pid, host, start time).
    Raises UserError naming the holder when another sweep has it; nothing is changed then.
    """
    lock_folder(logdir, "logdir", "wait for it to finish, or use another logdir=PATH")
