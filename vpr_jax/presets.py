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


def source(name: str) -> str | None:
    """The ``data.source`` a preset file names (None: it names none, or there is no file)."""
    if not path(name).is_file():
        return None
    data = OmegaConf.to_container(OmegaConf.load(path(name))).get("data") or {}
    return data.get("source")
