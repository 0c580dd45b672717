"""The names of what a method may see (``<method>.input``), JAX-free: the plan checks them
before anything is loaded (``vpr_jax.encoders.inputs`` computes them)."""

from __future__ import annotations

PARTS = ("pixels", "standardised", "patchnorm", "gradients")


def parts_of(name: str) -> tuple[str, ...]:
    """``"standardised+gradients"`` -> its parts; ValueError saying what is wrong."""
    parts = tuple(name.split("+"))
    unknown = [p for p in parts if p not in PARTS]
    if unknown:
        raise ValueError(f"{', '.join(repr(p) for p in unknown)} is not an input part")
    if len(set(parts)) < len(parts):
        raise ValueError("a part named twice")
    return parts
