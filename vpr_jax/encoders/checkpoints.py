"""Training checkpoints on disk (orbax): the only module that talks to orbax.

One folder per trained model, one orbax step per saved epoch (the training loop saves at
most every ``train.checkpoint_every_s`` seconds, and always the last epoch), the last two
kept. Each step holds two items:
- ``state``: the whole training state (``vpr_jax.encoders.train.TrainState``: parameters,
  optimizer state, best parameters so far and the counters), one pytree, restored against
  a target so optax states keep their types and the counters their exact values;
- ``meta`` (JSON): the model ``spec``, the image shape, an ``identity`` of everything that
  determines the weights, how epochs are selected (``selected_by``), ``done`` /
  ``stopped_early`` and a readable summary (epoch, step, the best epoch, its score and
  validation loss, training seconds).

The metadata carry ``format`` (``FORMAT``); a folder of another format is refused (one
line: use a new folder), never read into today's state.

Saves are synchronous: an epoch counts as saved only once its step is committed. A process
killed mid-save leaves a ``*.orbax-checkpoint-tmp`` folder that orbax ignores.

With several processes (``mesh.distributed``) every process trains the same replicated
model: process 0 alone saves (host copies), each process reads on its own, so orbax never
waits on the others. The checkpoint folder must then be on a file system all hosts share.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, NamedTuple, TypeVar

import jax
import numpy as np
import orbax.checkpoint as ocp

from vpr_jax.errors import UserError

FORMAT = 2  # of the layout above; a checkpoint of another format is refused
State = TypeVar("State", bound=NamedTuple)


def _abstract(tree):
    """Restore targets: arrays by shape and dtype; Python numbers as numpy scalars, so a
    float64 loss or an int64 counter comes back exact (not as a float32 device array)."""

    def leaf(x):
        if isinstance(x, int | float | np.number):
            return np.asarray(x)
        return ocp.utils.to_shape_dtype_struct(x)

    return jax.tree.map(leaf, tree)


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


def _latest(manager: ocp.CheckpointManager, directory: Path) -> int:
    step = manager.latest_step()
    if step is None:
        raise UserError(f"{directory} holds no checkpoint: train a model there first")
    return step


def _check_format(meta: dict, directory: Path) -> dict:
    found = meta.get("format") if isinstance(meta, dict) else None
    if found != FORMAT:
        raise UserError(
            f"{directory} holds a checkpoint of another format ({found}; this version reads "
            f"{FORMAT}): use a new folder (delete that one, or set train.checkpoint_dir=PATH)"
        )
    return meta


def has_checkpoint(directory: Path) -> bool:
    directory = Path(directory)
    if not directory.is_dir():
        return False
    with _manager(directory) as manager:
        return manager.latest_step() is not None


def _newest(manager: ocp.CheckpointManager, directory: Path) -> tuple[int, dict]:
    """The newest step and its metadata, refused (UserError) when of another format."""
    step = _latest(manager, directory)
    meta = manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore())).meta
    return step, _check_format(meta, directory)


def read_meta(directory: Path) -> dict:
    """The JSON metadata of the newest step."""
    with _manager(directory) as manager:
        return _newest(manager, directory)[1]


def restore(directory: Path, like: State) -> tuple[State, dict]:
    """The newest step's training state and metadata; ``like`` is a state of the right
    structure, shapes and dtypes (a freshly initialised one)."""
    with _manager(directory) as manager:
        step, _ = _newest(manager, directory)  # another layout is never restored into ``like``
        out = manager.restore(
            step,
            args=ocp.args.Composite(
                state=ocp.args.StandardRestore(_abstract(like)), meta=ocp.args.JsonRestore()
            ),
        )
    state = jax.tree.map(
        lambda x, y: type(y)(x) if isinstance(y, int | float) else x, out.state, like
    )  # numpy scalars back to Python numbers
    return state, out.meta


def restore_model(directory: Path, params_like) -> Any:
    """The best parameters of the newest step, without the rest of the training state."""
    with _manager(directory) as manager:
        step, _ = _newest(manager, directory)
        # Only the best parameters of the state item, read as host arrays.
        part = {"best_params": jax.tree.map(np.asarray, params_like)}
        restore_args = jax.tree.map(lambda _: ocp.RestoreArgs(restore_type=np.ndarray), part)
        out = manager.restore(
            step,
            args=ocp.args.Composite(
                state=ocp.args.PyTreeRestore(
                    item=part, restore_args=restore_args, partial_restore=True
                )
            ),
        )
    return jax.device_put(out.state["best_params"])


def save(directory: Path, step: int, state: NamedTuple, meta: dict) -> None:
    """Commit one step (an epoch) synchronously; keep the last two. Process 0 only."""
    if jax.process_index() != 0:
        return
    # Host copies: a model replicated over several processes' devices is not addressable
    # from one process, its numpy copy is.
    state = jax.tree.map(np.asarray, state)
    Path(directory).mkdir(parents=True, exist_ok=True)
    try:
        with orbax_noise_held(), _manager(directory) as manager:
            manager.save(
                step,
                args=ocp.args.Composite(
                    state=ocp.args.StandardSave(state),
                    meta=ocp.args.JsonSave({**meta, "format": FORMAT}),
                ),
            )
            manager.wait_until_finished()
    except (ValueError, RuntimeError) as err:
        raise as_os_error(err, directory) from None


@contextlib.contextmanager
def orbax_noise_held():
    """Hold what is written to stderr (file descriptor 2) while orbax saves, and pass it on
    only if the save succeeds. A failed write makes orbax's worker threads log the same fault
    several times over, with tracebacks, before the error reaches us; the sweep then says it
    in one line of its own."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as held:
        os.dup2(held.fileno(), 2)
        try:
            yield
        except BaseException:
            _settle(held)
            _restore_stderr(saved)
            raise
        _restore_stderr(saved)
        held.seek(0)
        noise = held.read()
    if noise:  # back to file descriptor 2, where it was written (sys.stderr may be
        # another stream by now, as under contextlib.redirect_stderr, without a buffer)
        with os.fdopen(os.dup(2), "wb") as out:
            out.write(noise)


def _settle(held, quiet_s: float = 0.3, limit_s: float = 3.0) -> None:
    """Wait (at most ``limit_s``) until orbax's threads have said all they will about a
    failed save: nothing new in ``held`` for ``quiet_s``."""
    end = time.monotonic() + limit_s
    size = -1
    while time.monotonic() < end and os.fstat(held.fileno()).st_size != size:
        size = os.fstat(held.fileno()).st_size
        time.sleep(quiet_s)


def _restore_stderr(saved: int) -> None:
    sys.stderr.flush()
    os.dup2(saved, 2)
    os.close(saved)


def as_os_error(err: Exception, directory: Path) -> Exception:
    """A write fault orbax (TensorStore) reports as ``ValueError: RESOURCE_EXHAUSTED ...
    [os_error_code='28']`` becomes the ``OSError`` it was (ENOSPC here), naming the model's
    folder, so the sweep reports it like any other full disk; anything else is kept."""
    code = re.search(r"os_error_code='(\d+)'", str(err))
    if code is None:
        return err
    number = int(code.group(1))
    return OSError(number, os.strerror(number), str(directory))
