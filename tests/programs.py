"""Reading JAX's programs for the products in them and their precision: the helpers of
tests/test_precision.py and tests/sharded_checks.py (``vpr_jax/precision.py`` says what is
pinned and why)."""

from __future__ import annotations

import contextlib
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import jax

PRODUCTS = ("dot_general", "conv_general_dilated")
DUMP = ("jax_dump_ir_to", "jax_dump_ir_modes")
FLOAT32 = ("precision=(Precision.HIGHEST, Precision.HIGHEST)", "F32_F32_F32")


@contextlib.contextmanager
def lowered_programs() -> Iterator[dict[str, list[str]]]:
    """``{program name: [its jaxpr, once per lowering]}`` of every program JAX lowers inside
    the block (eager operations too), filled when it ends. The block runs under a default
    of bfloat16 products, as a user's program that asks for speed would: the default is
    part of every compiled program's key, so every program is lowered anew (none is
    taken from what this process compiled before), and a product that states no
    precision shows up as ``Precision.DEFAULT``."""
    folder = tempfile.mkdtemp(prefix="vpr_jax_jaxprs_")
    saved = {name: jax.config.read(name) for name in DUMP}
    programs: dict[str, list[str]] = {}
    try:
        jax.config.update("jax_dump_ir_to", folder)
        jax.config.update("jax_dump_ir_modes", "jaxpr")
        with jax.default_matmul_precision("bfloat16"):
            yield programs
    finally:
        for name, value in saved.items():
            jax.config.update(name, value)
        for path in sorted(Path(folder).glob("*.jaxpr.txt")):
            name = re.fullmatch(r"jax_\d+_(.*)\.jaxpr\.txt", path.name).group(1)
            programs.setdefault(name, []).append(path.read_text())
        shutil.rmtree(folder, ignore_errors=True)


def jaxpr_of(fn, *args) -> list[str]:
    """``[the jaxpr of fn(*args)]``, as ``lowered_programs`` lists a program's: a jitted
    function's with its nested calls inline, traced, not compiled."""
    return [str(jax.make_jaxpr(fn)(*args))]


def products(jaxpr: str) -> list[str]:
    """The parameters of every product equation in a jaxpr's text, ``name[...]``."""
    found = []
    for match in re.finditer(r"\b(" + "|".join(PRODUCTS) + r")\[", jaxpr):
        depth, end = 0, match.end() - 1
        for end in range(match.end() - 1, len(jaxpr)):
            depth += {"[": 1, "]": -1}.get(jaxpr[end], 0)
            if depth == 0:
                break
        found.append(jaxpr[match.start() : end + 1])
    return found


def unpinned(programs: dict[str, list[str]], exempt: tuple[str, ...] = ()) -> dict[str, str]:
    """``{program: its first product that states no float32}`` of the programs not in
    ``exempt``."""
    out = {}
    for name, texts in programs.items():
        loose = [p for t in texts for p in products(t) if not any(f in p for f in FLOAT32)]
        if loose and name not in exempt:
            out[name] = " ".join(loose[0].split())
    return out


def n_products(programs: dict[str, list[str]]) -> int:
    return sum(len(products(t)) for texts in programs.values() for t in texts)
