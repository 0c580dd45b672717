"""The command line: ``python -m experiments.sweep [key=value ...]`` merged with the preset
file and the defaults into the typed ``SweepConfig`` (OmegaConf), and what the command line
named (its given keys)."""

from __future__ import annotations

from omegaconf import ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from vpr_jax import presets
from vpr_jax.config import SweepConfig, SweepKnobs, normalised
from vpr_jax.errors import UserError

# Sweep knobs that take a list; written without brackets (methods=raw,pca) they are one.
_LIST_KEYS = (
    "methods",
    "removed_pcs",
    "seeds",
    "data.seasons",
    "sequence.ds",
    "split.train_places",
)


def _normalise_cli(argv: list[str]) -> list[str]:
    """Accept ``methods=raw,pca`` as well as ``methods=[raw,pca]`` and a list of pairs."""
    out = []
    for arg in argv:
        key, sep, value = arg.partition("=")
        if not sep:
            raise UserError(f"argument {arg!r} is not key=value: write e.g. season_pairs=all")
        if key == "seeds" and value.strip().lstrip("-").isdigit():
            raise UserError(
                f"seeds={value} names one seed, {value}: write seeds=[{value}] for that seed "
                f"alone, or e.g. seeds=[0,1,2] for three seeds"
            )
        if key in _LIST_KEYS and value and not value.startswith("["):
            value = f"[{value}]"
        if key == "season_pairs" and value.startswith("["):
            value = value.strip("[]")
        out.append(f"{key}={value}")
    return out


def given_keys(argv: list[str]) -> frozenset[str]:
    """The dotted keys ``key=value`` arguments set (``ica.n_components``, ``seeds``)."""
    return frozenset(arg.partition("=")[0] for arg in argv)


def _first_line(err: OmegaConfBaseException) -> str:
    key, value = getattr(err, "full_key", ""), getattr(err, "value", None)
    if key and isinstance(value, ListConfig):
        return (
            f"{key}={OmegaConf.to_container(value)} is a list, but {key} takes one value: give one"
        )
    lines = str(err).splitlines()
    key = next((ln.split(":", 1)[1].strip() for ln in lines if "full_key:" in ln), "")
    return f"{lines[0]} (key {key})" if key else lines[0]


def parse_config(argv: list[str]) -> SweepConfig:
    """Build the typed config from ``key=value`` arguments, defaults and the preset file.
    Each method's settings stay as given until the plan checks them with the method's own
    ``Settings`` (``experiments.resolve``)."""
    try:
        cli = OmegaConf.from_dotlist(_normalise_cli(argv))
        preset = cli.get("preset", SweepKnobs.preset)
        preset_file = presets.path(preset)
        if not preset_file.is_file():
            raise UserError(
                f"preset={preset} has no file {preset_file}: use one of "
                f"{', '.join(presets.names())}"
            )
        merged = OmegaConf.merge(
            OmegaConf.structured(SweepConfig), OmegaConf.load(preset_file), cli
        )
        return normalised(OmegaConf.to_object(merged))
    except OmegaConfBaseException as err:
        raise UserError(f"bad config: {_first_line(err)}: see docs/config.md") from None


def config_from_dict(saved: dict) -> SweepConfig:
    """A config saved as plain data (a logdir's config.yaml, without its format) as the
    typed config it was."""
    try:
        merged = OmegaConf.merge(OmegaConf.structured(SweepConfig), saved)
        return normalised(OmegaConf.to_object(merged))
    except OmegaConfBaseException as err:
        raise UserError(f"bad saved config: {_first_line(err)}: rerun the sweep") from None
