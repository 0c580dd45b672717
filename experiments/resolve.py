"""The sweep's methods as the plan runs them: each entry of ``methods`` (a built-in's line of
the method table, or a user's ``module:name``) loaded as a ``Method``, its settings checked
by its own ``Settings``, fitted to the training set by its own ``check``, and expanded into
the fits of each pair (``Fit``), each with the cells its state serves. Nothing is fitted
here; the methods' modules load JAX.

A method's settings come from ``<method>.*`` (``plugin.<name>.*``), from the sweep's own
keys it has a setting of (``SWEEP_KEYS``: ``removed_pcs`` reaches pca, ica and diff_pca as
their setting of that name) and, for a setting named like a ``train.*`` key, from ``train``
(the shared defaults; ``train.augment=auto`` is the axis ``[true, false]``). A list is an
axis. A fit is one combination of the settings less those one fit serves (``axes``), one
value of a setting whose values are rows of their own (the auto-encoders' objective), and
one seed where the method draws random numbers (``seeds``); its cells: each served value x
each sequence length.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

from vpr_jax.config import TRAIN_BOOKKEEPING, SweepConfig, TrainConfig, plain
from vpr_jax.errors import UserError
from vpr_jax.method_table import (
    ALIGNED_FIX,
    METHODS,
    SHARED_PCA,
    MethodInfo,
    info_of,
    load_object,
    model_name,
    outside_info,
)
from vpr_jax.methods import settings as axes
from vpr_jax.methods.contract import ROWS, SERVED, SUFFIX, Method, TrainingSet, as_method
from vpr_jax.methods.inputs import input_of
from vpr_jax.methods.settings import Combination
from vpr_jax.outputs.results import SWEEP_KEYS, cell_name
from vpr_jax.progress import Log

TRAIN_KEYS = tuple(
    f.name for f in dataclasses.fields(TrainConfig) if f.name not in TRAIN_BOOKKEEPING
)


class Resolved(NamedTuple):
    """One entry of ``methods``: its object and its settings, checked."""

    info: MethodInfo
    method: Method
    group: str  # where its settings are given: "ica", "plugin.edges"
    given: dict  # its settings as the command line and the preset gave them
    combinations: tuple[Combination, ...]  # its settings, one per point of its axes

    @property
    def name(self) -> str:
        return self.info.name

    @property
    def effective(self) -> dict:
        """Its settings as it runs them (defaults filled in, checked, fitted to the training
        set, each axis as the list of its values): what config.yaml records."""
        return plain(axes.effective(self.method.settings, list(self.combinations), self.given))


class Served(NamedTuple):
    """A cell's part of a fit: what encode is called with, and how the cell is named."""

    values: dict[str, Any]  # encode's keyword settings (the served ones)
    swept: dict[str, Any]  # the cell's swept values, by name (what tells it from its neighbours)
    run: str  # its run's name less the pair and ds: ica_n_components=64_k005, fae_seed1


class Fit(NamedTuple):
    """One call of a method's fit in each pair, and the cells its state serves."""

    method: Resolved
    settings: Any  # the fit's settings dataclass (a dict for a method without one)
    values: dict[str, Any]  # fit's keyword settings
    objective: str  # its value of the setting whose values are rows ("" for none)
    folder: str  # its fitted state's folder under the pair's, and its training runs' name
    seed: int  # its key's: one of ``seeds``, or ``seed`` for a method that draws none
    served: tuple[Served, ...]
    train_places: int | None = None  # fitted on this many training places (None: all)


def group_of(info: MethodInfo) -> str:
    """Where a method's settings are given: ``ica.*``, ``plugin.<name>.*``,
    ``precomputed.<name>.*``."""
    if info.precomputed:
        return f"precomputed.{info.name}"
    return f"plugin.{info.name}" if info.plugin else info.name


def given_settings(cfg: SweepConfig, info: MethodInfo, method: Method) -> dict:
    """A method's settings as the command line and the preset gave them, with the sweep's
    keys and the training defaults it has a setting of (its dataclass's fields; without
    one, the settings its ``axes`` name)."""
    if info.precomputed:
        return dict(cfg.precomputed[info.name])
    given = dict(cfg.plugin.get(info.name, {}) if info.plugin else getattr(cfg, info.name))
    if method.settings is not None:
        fields = {f.name for f in dataclasses.fields(method.settings)}
    else:
        fields = set(method.axes(given))
    for key in SWEEP_KEYS:
        if key in fields and key not in given:
            given[key] = list(getattr(cfg, key))
    for key in TRAIN_KEYS:
        if key in fields and given.get(key) is None:
            value = getattr(cfg.train, key)
            given[key] = [True, False] if key == "augment" and value == "auto" else value
    return given


def _given_in(keys: frozenset[str], group: str) -> frozenset[str]:
    """The settings of ``group`` among dotted ``keys`` (``ica.n_components`` ->
    n_components); the sweep's own keys and ``train.*`` count as given to every method."""
    prefix = f"{group}."
    own = {k[len(prefix) :] for k in keys if k.startswith(prefix)}
    shared = {k for k in keys if k in SWEEP_KEYS}
    shared |= {k.removeprefix("train.") for k in keys if k.removeprefix("train.") in TRAIN_KEYS}
    return frozenset(own | shared)


def load(info: MethodInfo) -> Method:
    return as_method(load_object(info), info.method)


def resolve(info: MethodInfo, cfg: SweepConfig) -> Resolved:
    """A method loaded and its settings expanded and checked (not yet against the data)."""
    method = load(info)
    group = group_of(info)
    given = given_settings(cfg, info, method)
    combinations = tuple(axes.expand(method.settings, given, group))
    return Resolved(info=info, method=method, group=group, given=given, combinations=combinations)


def pca_settings(cfg: SweepConfig) -> Resolved:
    """pca with its settings, whether or not it is in ``methods``: they shape the pair's
    shared PCA fit (resource ``pca_fit``). A method that needs the fit gets it with pca's
    first combination of settings; pca's own cells, with each of theirs."""
    return resolve(METHODS[SHARED_PCA], cfg)


def resolve_methods(
    cfg: SweepConfig, aligned: bool, source: str, given: frozenset[str]
) -> tuple[Resolved, ...]:
    """Every entry of ``methods`` loaded and its settings checked. A method that learns from
    aligned training places is refused on data without them when ``methods`` is named on
    the command line (and always when it is the user's), and left out otherwise."""
    resolved, left_out = [], []
    infos = [info_of(entry) for entry in cfg.methods]
    infos += [outside_info(name) for name in cfg.precomputed]  # after the methods, by name
    for info in infos:
        one = resolve(info, cfg)
        if one.method.needs_alignment(one.combinations[0].settings) and not aligned:
            left_out.append(one)
            continue
        resolved.append(one)
    refused = [r.name for r in left_out if r.info.plugin or "methods" in given]
    if refused:
        raise UserError(
            f"methods {refused} learn from aligned training places (needs 'aligned'), which "
            f"data.source={source} does not have: {ALIGNED_FIX}"
        )
    if not resolved:
        raise UserError(
            f"methods={list(cfg.methods)} all learn from aligned training places, which "
            f"data.source={source} does not have: {ALIGNED_FIX}"
        )
    _check_run_names(resolved)
    _check_patchnorm_once(cfg, resolved)
    return tuple(resolved)


def _check_patchnorm_once(cfg: SweepConfig, resolved: list[Resolved]) -> None:
    """``preprocess=patchnorm`` has normalised every image already: a method's input with
    the part ``patchnorm`` would normalise it again."""
    if cfg.preprocess != "patchnorm":
        return
    for r in resolved:
        for c in r.combinations:
            if "patchnorm" in input_of(c.settings).split("+"):
                raise UserError(
                    f"{r.group}.input={input_of(c.settings)} patch-normalises images that "
                    "preprocess=patchnorm has normalised already: drop one (the input is part "
                    "of the method's encoder; preprocess applies to every method)"
                )


def _check_run_names(resolved: list[Resolved]) -> None:
    """A user's method may not take the name of another method's run (``fae_cross_season``)."""
    taken = {
        model_name(r.name, objective)
        for r in resolved
        if not r.info.plugin
        for c in r.combinations
        for objective in _rows(r, c)
    }
    clash = [r.name for r in resolved if r.info.plugin and r.name in taken]
    if clash:
        raise UserError(
            f"your method {clash[0]!r} has the name of a built-in method or run: rename the "
            "object in its module (its name is what results.csv and the runs call it)"
        )


def _rows_setting(method: Method, settings: Any) -> str:
    """The setting whose values are rows of their own ('' for none)."""
    rows = [n for n, kind in method.axes(settings).items() if kind == ROWS]
    return rows[0] if rows else ""


def _rows(r: Resolved, combination: Combination) -> tuple[str, ...]:
    """The values of a method's rows setting (its objectives), or one empty one."""
    name = _rows_setting(r.method, combination.settings)
    if not name:
        return ("",)
    value = combination.values[name]
    return (value,) if isinstance(value, str) else tuple(value)


def training_set(
    r: Resolved,
    n_images: int,
    n_pixels: int,
    aligned: bool,
    given: frozenset[str],
    pca_components: int,
    devices: int,
) -> TrainingSet:
    swept: dict[str, list] = {}
    for c in r.combinations:
        for name, value in c.swept:
            if value not in swept.setdefault(name, []):
                swept[name].append(value)
    return TrainingSet(
        n_images=n_images,
        n_pixels=n_pixels,
        aligned=aligned,
        swept={name: tuple(values) for name, values in swept.items()},
        given=_given_in(given, r.group),
        pca_components=pca_components,
        devices=devices,
    )


def check_training_set(
    resolved: tuple[Resolved, ...], sets: dict[str, TrainingSet], log: Log
) -> tuple[Resolved, ...]:
    """Each method's settings fitted to the training set by its own ``check`` (notes for
    what it changes, a combination it returns None for left out, UserError for what it
    cannot serve). A note is said once, however many combinations give it."""
    said: set[str] = set()

    def once(line: str) -> None:
        if line not in said:
            said.add(line)
            log(line)

    out = []
    for r in resolved:
        if r.method.check is None:
            out.append(r)
            continue
        kept = []
        for c in r.combinations:
            s = r.method.check(c.settings, sets[r.name], once)
            if s is not None:
                kept.append(c._replace(settings=s, values={**c.values, **axes.as_dict(s)}))
        if not kept:
            raise UserError(
                f"no setting of {r.name} fits the training set (the notes above say why): "
                f"change {r.group}.* or the split"
            )
        out.append(r._replace(combinations=tuple(kept)))
    return tuple(out)


def _served_names(method: Method, settings: Any) -> set[str]:
    return {n for n, kind in method.axes(settings).items() if kind in (SERVED, SUFFIX)}


def fits(r: Resolved, cfg: SweepConfig) -> list[Fit]:
    """The fits of one method in each pair, in the order they run."""
    seeds = cfg.fit_seeds if r.method.random else (cfg.seed,)
    places = cfg.split.train_places or (None,)
    groups: dict[str, list[Combination]] = {}
    for c in r.combinations:  # combinations that differ only in served settings share a fit
        served = _served_names(r.method, c.settings)
        key = repr(sorted((n, v) for n, v in c.values.items() if n not in served))
        groups.setdefault(key, []).append(c)
    out = []
    for p in places:  # each a learning curve's point: rows of their own
        for group in groups.values():
            if p is not None:  # fitted on p training places: a setting of every cell
                group = [c._replace(swept=(*c.swept, ("train_places", p))) for c in group]
            for objective in _rows(r, group[0]):
                for seed in seeds:
                    out.append(_fit(r, group, objective, seed, cfg.seed, p))
    return out


def _fit(r: Resolved, group: list[Combination], objective: str, seed, data_seed, places) -> Fit:
    first = group[0]
    served_names = _served_names(r.method, first.settings)
    rows_name = _rows_setting(r.method, first.settings)
    values = {n: v for n, v in first.values.items() if n not in served_names}
    if rows_name:
        values[rows_name] = objective
    seed_named = seed if seed != data_seed else None
    served = tuple(
        Served(
            values={n: c.values[n] for n in served_names if n in c.values},
            swept=dict(c.swept),
            run=cell_name(r.name, objective, c.swept, seed_named),
        )
        for c in group
    )
    fit_swept = tuple((n, v) for n, v in first.swept if n not in served_names)
    return Fit(
        method=r,
        settings=first.settings,
        values=values,
        objective=objective,
        folder=cell_name(r.name, objective, fit_swept, seed_named),
        seed=seed,
        served=served,
        train_places=places,
    )


def settings_identities(config: dict, named: tuple[str, ...]) -> dict[str, dict]:
    """Per method of a config as config.yaml holds it, what of its settings decides its
    cells (``settings.identity``): a logdir may gain methods and axis values, not change
    the others. A user's method is imported only when ``named`` (the command's
    ``methods``) names it: a config.yaml is a file, and a file never imports anything."""
    out = {}
    for entry in config.get("methods", []):
        if not isinstance(entry, str) or entry not in (*METHODS, *named):
            continue  # not compared: only methods both runs have are (check_same_config)
        info = info_of(entry)
        if info.plugin:
            given = config.get("plugin", {}).get(info.name, {})
        else:
            given = config.get(info.name, {})
        try:
            method = load(info)
        except UserError:  # a user's method that no longer imports: its settings as given
            method = None
        schema = method.settings if method else None
        out[group_of(info)] = axes.identity(schema, given, _rows_of_defaults(method))
    return out


def _rows_of_defaults(method: Method | None) -> str:
    """The setting whose values are rows of their own, at the method's default settings
    ('' where it has none, or no defaults to ask with)."""
    if method is None:
        return ""
    try:
        return _rows_setting(method, method.settings() if method.settings else {})
    except (TypeError, AttributeError, KeyError):  # a user's settings without defaults
        return ""
