"""The sweep's methods as the plan runs them: each entry of ``methods`` (a built-in's line of
the method table, or a user's ``module:name``) loaded as a ``Method``, its settings checked
by its own ``Settings``, fitted to the training set, and expanded into the fits of each pair
(``Fit``), each with the cells its state serves. Nothing is fitted here; the methods'
modules load JAX.

A fit is one combination of the method's settings less those one fit serves (``serves``),
one value of its variants (the auto-encoders' objective), one removed count where it fits
per count (ica), and one seed where it draws random numbers (``seeds``). Its cells: each
served value (pca's removed counts) x each sequence length.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

from vpr_jax.config import SweepConfig
from vpr_jax.errors import UserError
from vpr_jax.method_table import (
    ALIGNED_FIX,
    METHODS,
    SHARED_FIT,
    MethodInfo,
    info_of,
    load_object,
    model_label,
    model_name,
)
from vpr_jax.methods import settings as axes
from vpr_jax.methods.contract import Method, SharedFit, TrainingSet, as_method
from vpr_jax.methods.settings import Combination
from vpr_jax.progress import Log


class Resolved(NamedTuple):
    """One entry of ``methods``: its object and its settings, checked."""

    info: MethodInfo
    method: Method
    group: str  # where its settings are given: "ica", "plugin.edges"
    combinations: tuple[Combination, ...]  # its settings, one per point of its axes

    @property
    def name(self) -> str:
        return self.info.name


class Served(NamedTuple):
    """A cell's part of a fit: what encode is called with, and how the cell is named."""

    values: dict[str, Any]  # encode's keyword settings (the served ones)
    setting: str  # the cell's swept settings (results.csv's setting)
    removed_pcs: int  # 0 for a method without the removed-PC axis
    run: str  # its run's name less the pair and ds: ica_n_components=64_k005, fae_seed1


class Fit(NamedTuple):
    """One call of a method's fit in each pair, and the cells its state serves."""

    method: Resolved
    settings: Any  # the fit's settings dataclass (a dict for a method without one)
    values: dict[str, Any]  # fit's keyword settings
    objective: str  # its variant ("" for a method without variants)
    folder: str  # its fitted state's folder under the pair's, and its training runs' name
    seed: int  # its key's: one of ``seeds``, or ``seed`` for a method that draws none
    served: tuple[Served, ...]


def group_of(info: MethodInfo) -> str:
    """Where a method's settings are given: ``ica.*``, ``plugin.<name>.*``."""
    return f"plugin.{info.name}" if info.plugin else info.name


def given_settings(cfg: SweepConfig, info: MethodInfo) -> dict:
    """A method's settings as the command line and the preset gave them."""
    return dict(cfg.plugin.get(info.name, {}) if info.plugin else getattr(cfg, info.name))


def _given_in(keys: frozenset[str], group: str) -> frozenset[str]:
    """The settings of ``group`` among dotted ``keys`` (``ica.n_components`` -> n_components)."""
    prefix = f"{group}."
    return frozenset(k[len(prefix) :] for k in keys if k.startswith(prefix))


def load(info: MethodInfo) -> Method:
    return as_method(load_object(info), info.method)


def resolve(info: MethodInfo, given: dict) -> Resolved:
    """A method loaded and its settings expanded and checked (not yet against the data)."""
    method = load(info)
    group = group_of(info)
    combinations = tuple(axes.expand(method.settings, given, group))
    return Resolved(info=info, method=method, group=group, combinations=combinations)


def shared_fit_settings(cfg: SweepConfig) -> tuple[SharedFit, Any]:
    """The pair's shared PCA fit: its declaration and its settings (``method_table.SHARED_FIT``
    's, whether or not that method is in ``methods``)."""
    info = METHODS[SHARED_FIT]
    provider = resolve(info, given_settings(cfg, info))
    if len(provider.combinations) != 1:
        swept = ", ".join(f"{provider.group}.{n}" for n, _ in provider.combinations[0].swept)
        raise UserError(
            f"{swept} is a list, but {provider.group}'s settings also shape the pair's shared "
            "PCA fit, which every method that uses it shares: give one value, and sweep it "
            "in logdirs of their own"
        )
    return provider.method.shared_fit, provider.combinations[0].settings


def resolve_methods(
    cfg: SweepConfig, aligned: bool, source: str, asked: frozenset[str]
) -> tuple[Resolved, ...]:
    """Every entry of ``methods`` loaded and its settings checked. A method that learns from
    aligned training places is refused on data without them when asked for by name (and
    always when it is the user's), and left out otherwise."""
    resolved, left_out = [], []
    for entry in cfg.methods:
        info = info_of(entry)
        one = resolve(info, given_settings(cfg, info))
        if one.method.needs_alignment and not aligned:
            left_out.append(one)
            continue
        resolved.append(one)
    refused = [r.name for r in left_out if r.info.plugin or "methods" in asked]
    if refused:
        raise UserError(
            f"methods {refused} learn from aligned training places (needs_alignment), which "
            f"data.source={source} does not have: {ALIGNED_FIX}"
        )
    if not resolved and not cfg.precomputed:
        raise UserError(
            f"methods={list(cfg.methods)} all learn from aligned training places, which "
            f"data.source={source} does not have: {ALIGNED_FIX}"
        )
    _check_run_names(resolved)
    return tuple(resolved)


def _check_run_names(resolved: list[Resolved]) -> None:
    """A user's method may not take the name of another method's run (``fae_cross_season``)."""
    taken = {
        model_name(r.name, objective)
        for r in resolved
        if not r.info.plugin
        for objective in _variants(r, r.combinations[0])
    }
    clash = [r.name for r in resolved if r.info.plugin and r.name in taken]
    if clash:
        raise UserError(
            f"your method {clash[0]!r} has the name of a built-in method or run: rename the "
            "object in its module (its name is what results.csv and the runs call it)"
        )


def _variants(r: Resolved, combination: Combination) -> tuple[str, ...]:
    """The values of a method's variants (its objectives), or one empty one."""
    if not r.method.variants:
        return ("",)
    value = combination.values[r.method.variants]
    return (value,) if isinstance(value, str) else tuple(value)


def training_set(
    cfg: SweepConfig, n_images: int, n_pixels: int, aligned: bool, r: Resolved, given, asked
) -> TrainingSet:
    return TrainingSet(
        n_images=n_images,
        n_pixels=n_pixels,
        aligned=aligned,
        removed_pcs=cfg.removed_pcs,
        given=_given_in(given, r.group),
        asked=_given_in(asked, r.group),
    )


def trim_removed(
    cfg: SweepConfig, resolved: tuple[Resolved, ...], sets: dict[str, TrainingSet], given, log: Log
) -> SweepConfig:
    """The removed counts the training set serves: counts named on the command line are
    refused when it cannot (``check_training_set``), defaults and a preset's are cut to what
    it can (one note)."""
    sweeping = [r for r in resolved if "removed_pcs" in r.method.sweeps]
    if not sweeping or "removed_pcs" in given:
        return cfg
    some = next(iter(sets.values()))
    most, why = (
        some.pca_limit - 1,
        f"PCA of {some.n_images} training images has {some.pca_limit} components",
    )
    for r in (r for r in sweeping if r.method.most_removed is not None):
        for c in r.combinations:
            limit, reason = r.method.most_removed(c.settings, sets[r.name])
            most, why = min(most, limit), why if reason in why else why + reason
    kept = tuple(k for k in cfg.removed_pcs if k <= most)
    dropped = [k for k in cfg.removed_pcs if k > most]
    if dropped and kept:
        log(f"note: removed_pcs {dropped} dropped: {why} (set removed_pcs to choose)")
        return dataclasses.replace(cfg, removed_pcs=kept)
    return cfg


def check_training_set(
    resolved: tuple[Resolved, ...], sets: dict[str, TrainingSet], log: Log
) -> tuple[Resolved, ...]:
    """Each method's settings fitted to the training set by its own ``check`` (notes for
    what it changes, UserError for what it cannot serve); removed counts beyond the PCA of
    the training set are refused for every method that takes them."""
    out = []
    for r in resolved:
        ts = sets[r.name]
        if "removed_pcs" in r.method.sweeps and max(ts.removed_pcs) >= ts.pca_limit:
            raise UserError(
                f"removed_pcs={list(ts.removed_pcs)} leaves no component: PCA of "
                f"{ts.n_images} training images has {ts.pca_limit} components, so use "
                f"counts below {ts.pca_limit}"
            )
        if r.method.check is not None:
            checked = [r.method.check(c.settings, ts, log) for c in r.combinations]
            r = r._replace(
                combinations=tuple(
                    c._replace(settings=s, values={**c.values, **axes.as_dict(s)})
                    for c, s in zip(r.combinations, checked, strict=True)
                )
            )
        out.append(r)
    return tuple(out)


def fits(r: Resolved, cfg: SweepConfig) -> list[Fit]:
    """The fits of one method in each pair, in the order they run."""
    method, served_names = r.method, set(r.method.serves)
    counts = cfg.removed_pcs if "removed_pcs" in method.sweeps else None
    fit_counts = (None,) if counts is None or "removed_pcs" in served_names else counts
    seeds = cfg.fit_seeds if method.random else (cfg.seed,)
    groups: dict[str, list[Combination]] = {}
    for c in r.combinations:  # combinations that differ only in served settings share a fit
        key = repr(sorted((n, v) for n, v in c.values.items() if n not in served_names))
        groups.setdefault(key, []).append(c)
    out = []
    for group in groups.values():
        first = group[0]
        fit_swept = tuple((n, v) for n, v in first.swept if n not in served_names)
        for objective in _variants(r, first):
            for k in fit_counts:
                for seed in seeds:
                    out.append(_fit(r, group, fit_swept, objective, k, counts, seed, cfg.seed))
    return out


def _fit(r, group, fit_swept, objective, k, counts, seed, data_seed) -> Fit:
    method, served_names = r.method, set(r.method.serves)
    first = group[0]
    values = {n: v for n, v in first.values.items() if n not in served_names}
    if method.variants:
        values[method.variants] = objective
    if k is not None:
        values["removed_pcs"] = k
    cell_counts = counts if k is None and counts is not None else (k if k is not None else 0,)
    seed_named = seed if seed != data_seed else None
    count_named = "" if counts is None else "_k{:03d}"
    served = tuple(
        Served(
            values={
                **{n: c.values[n] for n in served_names if n in c.values},
                **({"removed_pcs": count} if "removed_pcs" in served_names else {}),
            },
            setting=c.label,
            removed_pcs=count,
            run=model_label(r.name, objective, c.label, seed_named) + count_named.format(count),
        )
        for c in group
        for count in cell_counts
    )
    folder = model_label(r.name, objective, axes.label(fit_swept), seed_named)
    if k is not None:
        folder += f"_k{k:03d}"
    return Fit(
        method=r,
        settings=first.settings,
        values=values,
        objective=objective,
        folder=folder,
        seed=seed,
        served=served,
    )


def settings_identities(config: dict) -> dict[str, dict]:
    """Per method of a config as config.yaml holds it, what of its settings decides its
    cells (``settings.identity``): a logdir may gain methods and axis values, not change
    the others."""
    out = {}
    for entry in config.get("methods", []):
        info = info_of(entry)
        if info.plugin:
            given = config.get("plugin", {}).get(info.name, {})
        else:
            given = config.get(info.name, {})
        try:
            method = load(info)
        except UserError:  # a user's method that no longer imports: its settings as given
            method = None
        schema, variants = (method.settings, method.variants) if method else (None, "")
        out[group_of(info)] = axes.identity(schema, given, variants)
    return out
