"""A method's settings as a sweep gives them (``ica.n_components=64``,
``plugin.edges.skip=[0,2,5]``): the method's ``settings`` dataclass names them, fills the
defaults and checks every value; a list given for a setting is a sweep axis.

- a setting of any type but a tuple: a list is an axis (``ica.n_components=[64,128]``);
- a tuple setting (``cae.channels``): a list is one value, a list of lists an axis;
- a method without a dataclass (a user's method without ``settings``): any list is an axis,
  and a list of lists passes lists.

``expand`` gives every combination of the axes' values (the cross product), each checked by
the dataclass, with its label (``n_components=64``): results.csv's ``setting`` column and
part of the names of its runs and folders. JAX-free.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import typing
from typing import Any, NamedTuple

from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from vpr_jax.errors import UserError

# Settings a built-in method no longer has: the old name -> (the setting that replaced it,
# its value for each old value). A command that gives one is refused naming the new one.
RENAMED = {
    "standardise": ("input", {True: "standardised", False: "pixels"}),
}
# An old setting's value that gives the same numbers as a new one's: a logdir that recorded
# it resumes as if it had recorded the new one (lda.standardise=true fitted a PCA of its
# own, lda.input=standardised uses the pair's shared one: not the same numbers).
RESUMES_AS = {("standardise", False): ("input", "pixels")}
# An auto-encoder (a schema with residual_pcs) recorded its input and whether it
# standardised apart; the pair is one input now, with the same numbers.
AUTOENCODER_INPUT_OF = {
    ("pixels", True): "standardised",
    ("pixels", False): "pixels",
    ("residual", True): "residual",
    ("residual", False): "residual_pixels",
}


class Combination(NamedTuple):
    """One combination of a method's settings."""

    settings: Any  # the settings dataclass, checked (a dict for a method without one)
    values: dict[str, Any]  # every setting by name: the keywords of fit (and of encode)
    swept: tuple[tuple[str, Any], ...]  # (name, value) of the swept settings, in field order

    @property
    def label(self) -> str:
        return label(self.swept)


def label(swept: tuple[tuple[str, Any], ...]) -> str:
    """``n_components=64``, ``hidden=256 init=pca``: the swept settings, readable."""
    return " ".join(f"{k}={_text(v)}" for k, v in swept)


def _text(value: Any) -> str:
    if isinstance(value, list | tuple):
        return "[" + ",".join(_text(v) for v in value) + "]"
    return str(value)


@functools.cache
def _tuple_fields(schema: type) -> frozenset[str]:
    """The settings of ``schema`` whose values are tuples (a list given is one value)."""
    hints = typing.get_type_hints(schema)
    out = set()
    for f in dataclasses.fields(schema):
        kinds = typing.get_args(hints[f.name]) or (hints[f.name],)
        if any(typing.get_origin(k) is tuple or k is tuple for k in (hints[f.name], *kinds)):
            out.add(f.name)
    return frozenset(out)


def is_axis(schema: type | None, name: str, value: Any) -> bool:
    """Whether ``value`` given for setting ``name`` is a sweep axis (see the module)."""
    if not isinstance(value, list | tuple):
        return False
    if schema is not None and name in _tuple_fields(schema):
        return len(value) > 0 and all(isinstance(v, list | tuple) for v in value)
    return True


def _field_names(schema: type | None, given: dict) -> list[str]:
    """Settings in a stable order: the dataclass's, or by name (a command line's order of
    keys must not rename a setting)."""
    if schema is None:
        return sorted(given)
    return [f.name for f in dataclasses.fields(schema)]


def _coerce(schema: type, given: dict) -> dict:
    """A tuple setting given one value (``fae.objective=cross_season``) or a comma list
    without brackets (``cae.channels=16,32``) as a list."""
    out = dict(given)
    for name in _tuple_fields(schema) & set(out):
        value = out[name]
        if isinstance(value, str) and "," in value:
            out[name] = [v.strip() for v in value.split(",") if v.strip()]
        elif value is not None and not isinstance(value, list | tuple):
            out[name] = [value]
    return out


def _checked(schema: type | None, values: dict, group: str) -> Any:
    """The dataclass of ``values`` (its __post_init__ checks them); UserError naming the
    setting for an unknown name or a wrong type."""
    if schema is None:
        return dict(values)
    known = _field_names(schema, values)
    unknown = sorted(set(values) - set(known))
    renamed = [n for n in unknown if n in RENAMED and RENAMED[n][0] in known]
    if renamed:
        old, (new, values_of) = renamed[0], RENAMED[renamed[0]]
        residual = (
            f"; with {group}.input=residual: residual (for true) or residual_pixels (for false)"
            if "residual_pcs" in known
            else ""
        )
        raise UserError(
            f"{group}.{old} is now {group}.{new}: use "
            + " or ".join(f"{group}.{new}={v} (for {str(k).lower()})" for k, v in values_of.items())
            + residual
            + " (docs/config.md)"
        )
    if unknown:
        raise UserError(
            f"{group}.{unknown[0]} is unknown: {group}'s settings are {', '.join(known)} "
            "(docs/config.md)"
        )
    try:
        merged = OmegaConf.merge(OmegaConf.structured(schema), values)
        return OmegaConf.to_object(merged)
    except OmegaConfBaseException as err:
        key = getattr(err, "key", None) or getattr(err, "full_key", "") or ""
        first = str(err).splitlines()[0]
        raise UserError(f"bad config: {first} (key {group}.{key}): see docs/config.md") from None


def expand(schema: type | None, given: dict, group: str) -> list[Combination]:
    """Every combination of the settings ``given`` for ``group`` (``ica``,
    ``plugin.edges``): defaults from ``schema`` where not given, one combination per element
    of the cross product of the axes, each checked."""
    given = _coerce(schema, given) if schema is not None else dict(given)
    axes = [n for n in _field_names(schema, given) if n in given and is_axis(schema, n, given[n])]
    empty = [n for n in _field_names(schema, given) if given.get(n) in ([], ())]
    if empty and (schema is None or empty[0] not in _tuple_fields(schema)):
        raise UserError(
            f"{group}.{empty[0]}=[] is an empty list: give one value, or the list of values to "
            "sweep"
        )
    out = []
    for values in itertools.product(*(given[n] for n in axes)):
        chosen = {**given, **{n: _plain(v) for n, v in zip(axes, values, strict=True)}}
        settings = _checked(schema, chosen, group)
        every = settings if schema is None else as_dict(settings)
        swept = tuple((n, every[n]) for n in axes)
        out.append(Combination(settings=settings, values=every, swept=swept))
    return out


def _plain(value: Any) -> Any:
    return [_plain(v) for v in value] if isinstance(value, list | tuple) else value


def as_dict(settings: Any) -> dict[str, Any]:
    """A settings dataclass's values by name (a dict is itself)."""
    if isinstance(settings, dict):
        return dict(settings)
    return {f.name: getattr(settings, f.name) for f in dataclasses.fields(settings)}


def effective(schema: type | None, combinations: list[Combination], given: dict) -> dict:
    """What the sweep runs, as config.yaml records it: every setting's value (defaults
    filled in), each axis as the list of its values."""
    if schema is None:
        return dict(given)
    out = dict(combinations[0].values)
    for name, _ in combinations[0].swept:
        out[name] = [_plain(c.values[name]) for c in _unique(combinations, name)]
    return out


def _unique(combinations: list[Combination], name: str) -> list[Combination]:
    seen, out = [], []
    for c in combinations:
        if c.values[name] not in seen:
            seen.append(c.values[name])
            out.append(c)
    return out


def identity(schema: type | None, effective_settings: dict, extendable: str = "") -> dict:
    """The part of a method's settings that decides its cells' numbers: every setting that
    is not an axis (nor the ``extendable`` one, the variants' list), and which settings
    are axes. Values added to an axis, or to the variants, only add cells. Settings as an
    earlier version recorded them read as today's: a setting it did not have yet at its
    default, an old one that gives the same numbers as a new one under the new one
    (``RESUMES_AS``)."""
    effective_settings = as_recorded_today(schema, effective_settings)
    axes = sorted(n for n, v in effective_settings.items() if is_axis(schema, n, v))
    fixed = {n: v for n, v in effective_settings.items() if n not in axes and n != extendable}
    return {**fixed, "axes": axes}


def as_recorded_today(schema: type | None, recorded: dict) -> dict:
    """A method's settings as config.yaml recorded them, with the settings ``schema`` has
    and the record lacks at their defaults, and old settings that give the same numbers as
    a new one (``RESUMES_AS``) under the new one (any other stays, and differs). Without a
    schema: as recorded."""
    if schema is None:
        return dict(recorded)
    fields = {f.name: f for f in dataclasses.fields(schema)}
    recorded = _autoencoder_input_today(fields, recorded)
    out = {}
    for name, value in recorded.items():
        key = (name, value) if isinstance(value, str | int | float | bool) else None
        if name not in fields and key in RESUMES_AS and RESUMES_AS[key][0] in fields:
            out.setdefault(*RESUMES_AS[key])
        else:
            out[name] = value
    for name, f in fields.items():
        if name in out:
            continue
        if f.default is not dataclasses.MISSING:
            out[name] = _plain(f.default)
        elif f.default_factory is not dataclasses.MISSING:
            out[name] = _plain(f.default_factory())
    return out


def _autoencoder_input_today(fields: dict, recorded: dict) -> dict:
    """An auto-encoder's ``input`` and ``standardise`` as recorded before they were one
    setting: today's input (``AUTOENCODER_INPUT_OF``), each value of an axis mapped. Other
    records as they are."""
    standardise = recorded.get("standardise")
    if "residual_pcs" not in fields or "standardise" in fields or not isinstance(standardise, bool):
        return recorded
    old = recorded.get("input", "pixels")
    values = list(old) if isinstance(old, list | tuple) else [old]
    if not all(isinstance(v, str) and (v, standardise) in AUTOENCODER_INPUT_OF for v in values):
        return recorded
    today = [AUTOENCODER_INPUT_OF[v, standardise] for v in values]
    out = {k: v for k, v in recorded.items() if k != "standardise"}
    out["input"] = today if isinstance(old, list | tuple) else today[0]
    return out
