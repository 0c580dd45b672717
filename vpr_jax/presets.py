"""The presets: files of settings under ``experiments/configs/`` (``preset=<name>``), a
comment at the top of each saying what it is for."""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

DIR = Path(__file__).resolve().parent.parent / "experiments" / "configs"
SOURCE_FREE = ("real",)  # presets that set no data keys: their logdirs name the source


def path(name: str) -> Path:
    return DIR / f"{name}.yaml"


def names() -> list[str]:
    return sorted(p.stem for p in DIR.glob("*.yaml"))


def keys(name: str) -> frozenset[str]:
    """The dotted keys a preset file sets (none for a preset that is not there)."""
    if not path(name).is_file():
        return frozenset()
    return _dotted(OmegaConf.to_container(OmegaConf.load(path(name))))


def _dotted(tree: dict, prefix: str = "") -> frozenset[str]:
    out = set()
    for key, value in tree.items():
        out.add(f"{prefix}{key}")
        if isinstance(value, dict):
            out |= _dotted(value, f"{prefix}{key}.")
    return frozenset(out)
