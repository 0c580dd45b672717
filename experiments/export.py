"""Take a sweep's results out: per pair and method, the retrieved pairs, the descriptors and
the encoder, in a folder another pipeline reads without vpr_jax.

    python -m experiments.export LOGDIR [out=DIR] [top_k=10] [all_settings=false]
                                        [overwrite=false] [plugins=MODULE:NAME,...]

For each pair and each method at its validation-selected setting (every setting with
``all_settings=true``) writes ``DIR/<pair>/<method>/`` (default DIR: ``LOGDIR/export``):
names, descriptors, hloc's ``pairs.txt``, ``scores.csv``, a copy of the saved encoder and a
README (``vpr_jax.outputs.export`` describes the files). It reads the sweep's data again
(the same config.yaml, the same images) and encodes them with the saved encoders, the way
the sweep did. A logdir is read as data: a method of your own that its config.yaml lists is
imported only when ``plugins=`` names it (as in the sweep's ``methods=``), and only encoder
folders under the logdir's own checkpoint folder are read. Bad input: one line on stderr,
exit code 2, nothing written; each folder is written aside and moved into place whole.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import NamedTuple

from vpr_jax.errors import UserError, exit_code

USAGE = (
    "python -m experiments.export LOGDIR [out=DIR] [top_k=10] [all_settings=false] "
    "[overwrite=false] [plugins=MODULE:NAME,...]"
)


class ExportOptions(NamedTuple):
    logdir: Path
    out: Path
    top_k: int = 10
    all_settings: bool = False
    overwrite: bool = False
    plugins: tuple[str, ...] = ()  # users' methods to import (module:name, or module)


def _flag(key: str, value: str) -> bool:
    if value.lower() not in ("true", "false"):
        raise UserError(f"{key}={value} is not true or false: write {key}=true or {key}=false")
    return value.lower() == "true"


def parse_args(argv: list[str]) -> ExportOptions:
    """``LOGDIR`` and ``key=value`` options; anything else is one line naming the usage."""
    logdirs = [a for a in argv if "=" not in a]
    if len(logdirs) != 1:
        raise UserError(f"name one logdir: {USAGE}")
    logdir = Path(logdirs[0]).expanduser().resolve()
    options = dict(a.split("=", 1) for a in argv if "=" in a)
    unknown = sorted(set(options) - {"out", "top_k", "all_settings", "overwrite", "plugins"})
    if unknown:
        raise UserError(f"unknown option {unknown[0]}: {USAGE}")
    top_k = options.get("top_k", "10")
    if not top_k.isdigit() or int(top_k) < 1:
        raise UserError(f"top_k={top_k} is not a count of matches: write e.g. top_k=10")
    out = options.get("out")
    return ExportOptions(
        logdir=logdir,
        out=Path(out).expanduser().resolve() if out else logdir / "export",
        top_k=int(top_k),
        all_settings=_flag("all_settings", options.get("all_settings", "false")),
        overwrite=_flag("overwrite", options.get("overwrite", "false")),
        plugins=tuple(p for p in options.get("plugins", "").strip("[]").split(",") if p),
    )


def check_paths(opts: ExportOptions) -> None:
    """``logdir`` holds a sweep; an existing non-empty ``out`` is kept unless
    ``overwrite=true``."""
    if not all((opts.logdir / name).is_file() for name in ("config.yaml", "results.csv")):
        raise UserError(
            f"logdir {opts.logdir} holds no sweep (no config.yaml and results.csv): name the "
            f"logdir of a sweep, {USAGE}"
        )
    out = opts.out
    if out.exists() and not out.is_dir():
        raise UserError(f"out={out} is a file: name a folder")
    if out.is_dir() and any(out.iterdir()) and not opts.overwrite:
        raise UserError(
            f"out={out} is not empty: pass overwrite=true to replace the folders this export "
            "writes (nothing else in it is touched), or name another out=DIR"
        )


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    return exit_code(lambda: _export(argv))


def _export(argv: list[str]) -> None:
    opts = parse_args(argv)
    check_paths(opts)
    from experiments.export_cells import export  # JAX: after the cheap checks

    export(
        opts.logdir,
        opts.out,
        top_k=opts.top_k,
        all_settings=opts.all_settings,
        plugins=opts.plugins,
        log=print,
    )


if __name__ == "__main__":
    sys.exit(main())
