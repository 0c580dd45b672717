"""Files written whole and folders written by one process: every stage that leaves
something on disk (a results table, a video cache, a config, a checkpoint folder) uses these.
No JAX here."""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import socket
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from vpr_jax.errors import UserError


@contextlib.contextmanager
def atomic_open(path: Path, mode: str = "w") -> Iterator[IO]:
    """A file to write ``path`` through: a temporary file in the same folder, fsynced and
    ``os.replace``-d into place when the block ends, then the folder fsynced: all or
    nothing, also across a power loss. An error in the block leaves ``path`` as it was and no
    temporary file behind."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, mode, **({} if "b" in mode else {"newline": ""})) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)  # the rename itself survives a power loss
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` all or nothing (``atomic_open``)."""
    with atomic_open(path) as f:
        f.write(text)


def replace_folder(new: Path, folder: Path) -> None:
    """Move the finished folder ``new`` to ``folder``, over an older one: the older is moved
    aside first and deleted last, so ``folder`` is always whole (the old or the new)."""
    new, folder = Path(new), Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    aside = None
    if folder.exists():
        aside = Path(tempfile.mkdtemp(prefix=f".{folder.name}.old.", dir=folder.parent))
        os.replace(folder, aside / folder.name)
    os.replace(new, folder)
    if aside is not None:
        shutil.rmtree(aside, ignore_errors=True)


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


LOCK_NAME = ".lock"
_held: dict[Path, int] = {}  # folder -> the open lock file: held until the process ends


def lock_folder(folder: Path, what: str, fix: str) -> None:
    """Make this process the only writer of ``folder`` (a logdir, a model's checkpoint
    folder while it trains): an exclusive ``flock`` on ``folder/.lock``, kept until the
    process exits (the kernel drops it then, also on SIGKILL, so no stale lock is left). The
    file says who holds it (pid, host, start time). Raises UserError naming ``what``, the
    holder and ``fix`` when another process has it; nothing is changed then."""
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
    since = time.strftime("%Y-%m-%d %H:%M:%S")
    os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()} since {since}\n".encode(), 0)
    _held[folder] = fd
