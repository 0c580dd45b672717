"""XLA's compiled programs kept on disk between runs (JAX's persistent compilation cache).

A sweep compiles a couple of hundred programs (the fits, encoders, training steps and the
matcher for each method's shapes): on a 2-core CPU about a third of the default sweep's
time. They are the same programs every run, so the sweep keeps them in ``compile_cache``
(``~/.cache/vpr_jax/xla`` unless set; ``compile_cache=null``: off), one folder per kind of
CPU, because XLA compiles for the CPU it runs on and a home folder may be shared by
machines of several kinds. A program read back is the one compiled: the numbers are the
same with or without it. A cache folder set for JAX itself (``JAX_COMPILATION_CACHE_DIR``)
is left as it is.

The cache holds native code this process runs, so it must be the user's own: a folder (or
a folder above it) that another user owns or that others may write to is refused
(``unsafe``); folders made here are the user's alone (mode 700).
"""

from __future__ import annotations

import hashlib
import os
import platform
import stat
from pathlib import Path

from vpr_jax.errors import UserError
from vpr_jax.progress import Log


def machine_tag() -> str:
    """The kind of CPU this process runs on: its architecture, model and instruction-set
    flags (Linux's /proc/cpuinfo; the architecture alone elsewhere), hashed."""
    described = [platform.machine()]
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() in ("model name", "flags", "Features", "CPU part"):
                    described.append(value.strip())
                if not line.strip():  # the first processor's block is enough
                    break
    except OSError:
        pass
    digest = hashlib.sha256("\n".join(described).encode()).hexdigest()[:12]
    return f"{platform.machine() or 'cpu'}-{digest}"


def unsafe(path: Path) -> str | None:
    """Why compiled programs in ``path`` might not be the user's own (None: they are): it,
    or a folder above it, belongs to another user (root aside) or may be written by others
    (a sticky folder such as /tmp aside: there others cannot move what is yours; a group
    that is the user's private one, as many systems give each user, is the user's)."""
    me = os.getuid()
    for folder in (path, *path.parents):
        info = folder.stat()
        if info.st_uid not in (me, 0):
            return f"{folder} belongs to user {info.st_uid}"
        writers = info.st_mode & stat.S_IWOTH
        if info.st_mode & stat.S_IWGRP and not _private_group(info.st_gid):
            writers = True
        if writers and not info.st_mode & stat.S_ISVTX:
            return f"{folder} may be written by others (mode {stat.S_IMODE(info.st_mode):o})"
    return None


def _private_group(gid: int) -> bool:
    """Whether ``gid`` is this user's own group: their primary group, with no one else in
    it."""
    if gid != os.getgid():
        return False
    try:
        import grp
        import pwd

        members = set(grp.getgrgid(gid).gr_mem)
        return members <= {pwd.getpwuid(os.getuid()).pw_name}
    except (ImportError, KeyError):
        return False


def use(folder: str | None, log: Log = print) -> Path | None:
    """Keep compiled programs in ``folder``/``machine_tag()`` (None: don't), unless JAX has
    a cache folder already. Returns the folder in use. A folder that cannot be made is
    reported in one line and the run goes on without it; one that is not the user's own
    (``unsafe``) is refused (UserError)."""
    import jax

    if jax.config.jax_compilation_cache_dir:
        return Path(jax.config.jax_compilation_cache_dir)
    if folder is None:
        return None
    path = Path(folder).expanduser() / machine_tag()
    try:
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
        why = unsafe(path)
    except OSError as err:
        log(
            f"note: compile_cache={folder} cannot be made ({err.strerror}): programs are "
            "compiled afresh (set compile_cache=PATH to a writable folder, or null)"
        )
        return None
    if why is not None:
        raise UserError(
            f"compile_cache={folder} is not yours alone ({why}): its compiled programs run "
            "as native code in this process; chmod go-w that folder, or set "
            "compile_cache=PATH to a folder of your own, or compile_cache=null"
        )
    jax.config.update("jax_compilation_cache_dir", str(path))
    # Every program: most of the sweep's compile in well under JAX's default second each.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return path
