"""Training checkpoints on disk (orbax): the only module that talks to orbax.

One folder per trained model, one orbax step per saved epoch (the training loop saves at
most every ``train.checkpoint_every_s`` seconds, and always the last epoch), the last two
kept.
Each step holds three items:
- ``train``: what resuming needs (``params``, ``opt_state``), restored against a target so
  optax states keep their types;
- ``model``: the best parameters so far (what ``vpr_jax.load_encoder`` restores);
- ``meta`` (JSON): epoch, step, best validation loss, early-stopping counter, ``done``, the
  model ``spec`` and an ``identity`` of everything that determines the weights.

Saves are synchronous: an epoch counts as saved only once its step is committed. A process
killed mid-save leaves a ``*.orbax-checkpoint-tmp`` folder that orbax ignores.

With several processes (``mesh.distributed``) every process trains the same replicated
model: process 0 alone saves (host copies), each process reads on its own, so orbax never
waits on the others. The checkpoint folder must then be on a file system all hosts share.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np
import orbax.checkpoint as ocp

from vpr_jax.errors import UserError


class Restored(NamedTuple):
    train: Any | None  # {"params", "opt_state"} or None when not asked for
    model: Any  # best parameters
    meta: dict


def _abstract(tree):
    return jax.tree.map(ocp.utils.to_shape_dtype_struct, tree)


def _manager(directory: Path) -> ocp.CheckpointManager:
    me = jax.process_index()  # this process alone: no barrier with the others
    options = ocp.CheckpointManagerOptions(
        max_to_keep=2,
        enable_async_checkpointing=False,
        create=False,  # save() makes the folder; reading never creates one
        multiprocessing_options=ocp.options.MultiprocessingOptions(
            primary_host=me, active_processes={me}
        ),
    )
    return ocp.CheckpointManager(Path(directory).expanduser().resolve(), options=options)


def has_checkpoint(directory: Path) -> bool:
    directory = Path(directory)
    if not directory.is_dir():
        return False
    with _manager(directory) as manager:
        return manager.latest_step() is not None


def read_meta(directory: Path) -> dict:
    """The JSON metadata of the newest step."""
    with _manager(directory) as manager:
        step = manager.latest_step()
        if step is None:
            raise UserError(f"{directory} holds no checkpoint: train a model there first")
        return manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore())).meta


def restore(directory: Path, model_like, train_like=None) -> Restored:
    """The newest step; ``*_like`` are trees of the right structure, shapes and dtypes."""
    with _manager(directory) as manager:
        step = manager.latest_step()
        if step is None:
            raise UserError(f"{directory} holds no checkpoint: train a model there first")
        items = {
            "model": ocp.args.StandardRestore(_abstract(model_like)),
            "meta": ocp.args.JsonRestore(),
        }
        if train_like is not None:
            items["train"] = ocp.args.StandardRestore(_abstract(train_like))
        out = manager.restore(step, args=ocp.args.Composite(**items))
        return Restored(out.get("train") if train_like is not None else None, out.model, out.meta)


def save(directory: Path, step: int, train, model, meta: dict) -> None:
    """Commit one step (an epoch) synchronously; keep the last two. Process 0 only."""
    if jax.process_index() != 0:
        return
    # Host copies: a model replicated over several processes' devices is not addressable
    # from one process, its numpy copy is.
    train, model = jax.tree.map(np.asarray, (train, model))
    Path(directory).mkdir(parents=True, exist_ok=True)
    with _manager(directory) as manager:
        manager.save(
            step,
            args=ocp.args.Composite(
                train=ocp.args.StandardSave(train),
                model=ocp.args.StandardSave(model),
                meta=ocp.args.JsonSave(meta),
            ),
        )
        manager.wait_until_finished()
