"""Run sweeps in this process and print, as JSON, what XLA compiled during each.

    python tests/count_compiles.py LOGDIR 'key=value ...' ['key=value ...' ...]

Each argument after LOGDIR is one sweep's overrides (space-separated); the output is one
list of "name | argument shapes" strings per sweep, from ``jax.log_compiles``. A helper of
tests/test_compiles.py, run in a fresh process so no earlier test has compiled anything.
"""

import json
import logging
import sys

import jax

from experiments.sweep import run_sweep
from vpr_jax.command_line import parse_config

PREFIX, SEP = "Compiling ", " with global shapes and types "


class Recorder(logging.Handler):
    def __init__(self):
        super().__init__()
        self.seen: list[str] = []

    def emit(self, record):
        message = record.getMessage()
        if message.startswith(PREFIX) and SEP in message:
            name, rest = message[len(PREFIX) :].split(SEP, 1)
            self.seen.append(f"{name} | {rest.split('. Argument mapping')[0]}")


def main() -> None:
    logdir, sweeps = sys.argv[1], sys.argv[2:]
    recorder = Recorder()
    logging.getLogger("jax").addHandler(recorder)
    out = []
    with jax.log_compiles(True):
        for i, overrides in enumerate(sweeps):
            recorder.seen = []
            run_sweep(
                parse_config(
                    [
                        *overrides.split(),
                        f"logdir={logdir}/{i}",
                        f"train.checkpoint_dir={logdir}/checkpoints",
                    ]
                )
            )
            out.append(recorder.seen)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
