"""The docs' sweep commands do not lead into a refusal: any two commands of README.md and
docs/*.md that would write one logdir hold the same configuration there (a logdir refuses
another one, ``vpr_jax.outputs.logdir.check_same_config``), so a reader who runs them in any
order never meets "holds results of a different configuration"."""

import re
import shlex
from pathlib import Path

import pytest

from experiments.resolve import settings_identities
from vpr_jax.command_line import parse_config
from vpr_jax.config import to_dict
from vpr_jax.outputs.logdir import identity, outside_settings

REPO = Path(__file__).resolve().parent.parent
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
SWEEP = "python -m experiments.sweep"


def sweep_commands(text: str) -> list[str]:
    """Every ``python -m experiments.sweep ...`` of a markdown text: in its code blocks
    (continuation lines joined; what follows ``&&``, ``;`` or a pipe is another command)
    and in its inline code (which may wrap across lines)."""
    blocks = re.findall(r"^```[^\n]*\n(.*?)^```", text, re.S | re.M)
    prose = re.sub(r"^```[^\n]*\n.*?^```", "", text, flags=re.S | re.M)
    lines = [ln for b in blocks for ln in re.sub(r"\s*\\\n\s*", " ", b).splitlines()]
    lines += [" ".join(span.split()) for span in re.findall(r"`([^`]+)`", prose)]
    found = []
    for line in lines:
        for piece in re.split(r"&&|;|\|", line):
            piece = piece.strip()
            if piece.startswith(SWEEP):
                found.append(piece)
    return found


def _configuration(command: str):
    """(logdir, what decides its cells) of a sweep command; None for one that names its
    logdir by a shell variable (each run of a loop its own) or for text that is not one
    command of key=value arguments (commands set side by side)."""
    args = shlex.split(command)[len(SWEEP.split()) :]
    if "#" in args:
        args = args[: args.index("#")]
    if not all(re.match(r"^[\w.]+=", a) for a in args):  # not one command (two columns)
        return None
    if any("$" in a for a in args if a.startswith("logdir=")):
        return None
    cfg = parse_config(args)
    methods = {**settings_identities(to_dict(cfg), tuple(cfg.methods)), **outside_settings(cfg)}
    return cfg.logdir, (identity(cfg), methods)


def test_the_extraction_sees_every_form_the_docs_use():
    text = (
        "```bash\npython -m experiments.sweep a=1 \\\n  b=2\n"
        "pip install -e . && python -m experiments.sweep\n```\n"
        "run `python -m experiments.sweep preset=real\n  c=3` or\n"
    )
    assert sweep_commands(text) == [f"{SWEEP} a=1 b=2", SWEEP, f"{SWEEP} preset=real c=3"]


@pytest.mark.timeout(120)
def test_no_two_documented_sweeps_meet_in_one_logdir_with_different_settings():
    seen: dict[str, tuple] = {}
    clashes = []
    for path in DOCS:
        for command in sweep_commands(path.read_text()):
            if any(sketch in command for sketch in ("...", "\u2026", "<", "KEY=")):
                continue  # a sketch of a command, not one to run as written
            found = _configuration(command)
            if found is None:
                continue
            logdir, config = found
            where = f"{path.relative_to(REPO)}: {command}"
            if logdir in seen and seen[logdir][0] != config:
                clashes.append(f"{where}\n  vs {seen[logdir][1]}")
            seen.setdefault(logdir, (config, where))
    assert not clashes, "give these their own logdir=:\n" + "\n".join(clashes)
