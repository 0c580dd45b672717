"""Descriptors computed elsewhere as one more row of a benchmark sweep
(``precomputed.<name>.database=PATH``, ``precomputed.<name>.queries=PATH``;
``vpr_jax.data.precomputed`` reads and checks the files).

A set is a method like any other (``method``), one per set, run by the same path: its fit
reads nothing new (the plan read and checked the files, ``checked_sides``) and keeps the
pair's rows, its encode looks each image's row up, its fit time is NaN (spent elsewhere).
The validation queries are the benchmark's own held-out queries when it trains on its
database; a benchmark that learns from an aligned route (``data.train_source``) validates on
that route's places, which outside descriptors do not cover, so their validation scores are
NaN (one cell: nothing is chosen on them).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from vpr_jax.data.pair import PairData
from vpr_jax.data.precomputed import OutsideSide, setting_key
from vpr_jax.errors import UserError
from vpr_jax.methods.contract import Method, Report
from vpr_jax.methods.descriptors import degenerate
from vpr_jax.precision import f32_matmul


def checked_sides(
    name: str, files: dict[str, str], sides: dict[str, OutsideSide]
) -> dict[str, OutsideSide]:
    """Set ``name``'s sides (``files``: side -> path) with the names of their zero rows;
    UserError for a side whose rows are all zero, or all point the same way (constant
    descriptors): cosine matching cannot tell its images apart (``degenerate``)."""
    out = {}
    for side, rows in sides.items():
        where = f"{setting_key(name, side)}={files[side]}"
        found = degenerate(rows.rows)
        if found.zero.all():
            raise UserError(f"{where}: every row is zero: recompute the descriptors")
        if found.one_way:
            raise UserError(
                f"{where}: every nonzero row points the same way (constant descriptors), so "
                "cosine matching cannot tell the images apart: recompute the descriptors"
            )
        zero = [n for n, i in rows.row_of.items() if found.zero[i]]
        out[side] = rows._replace(zero=tuple(zero))
    return out


class Outside(NamedTuple):
    """What the method of a set of outside descriptors takes from the runner (resource
    ``outside``): the set's rows as the plan read them, and the pair whose images it
    describes."""

    sides: dict[str, OutsideSide]  # "database", "queries" -> the set's rows by image name
    pair: PairData


FINGERPRINT = 16  # values per image the rows are looked up by


def fit(train, aligned, key, *, outside: Outside, database: str = "", queries: str = ""):
    """Nothing is learnt: the state holds the set's rows for the pair's images (the
    database, the queries and, where the benchmark holds them out, its validation queries)
    and a fingerprint of each image to look its row up by (a fixed random projection of
    its pixels: distinct images, distinct fingerprints)."""
    pair, sides = outside.pair, outside.sides
    held_out = not pair.aligned_training  # validation queries are the benchmark's own
    parts = [(pair.db, sides["database"].of(pair.names.db))]
    parts.append((pair.query, sides["queries"].of(pair.names.query)))
    if held_out:
        parts.append((pair.val_query, sides["queries"].of(pair.names.val_query)))
    images = np.concatenate([np.reshape(i, (len(i), -1)) for i, _ in parts])
    projection = jax.random.normal(jax.random.key(0), (images.shape[1], FINGERPRINT))
    return {
        "projection": projection,
        "fingerprints": f32_matmul(jnp.asarray(images, jnp.float32), projection),
        "rows": jnp.asarray(np.concatenate([r for _, r in parts]), jnp.float32),
        "covers_validation": jnp.bool_(held_out),
    }


MATCH_TOLERANCE = 1e-6  # squared fingerprint distance, relative: rounding, not another image


@jax.jit
def encode(state: dict, images: Float[Array, "n h w"]) -> Float[Array, "n d"]:
    """Each image's row: the one whose image has its fingerprint; NaN for an image the set
    does not describe (the runner refuses NaN descriptors, and a saved set used on other
    images says so rather than answer with another image's row)."""
    fingerprints = f32_matmul(jnp.reshape(images, (images.shape[0], -1)), state["projection"])
    table = state["fingerprints"]
    norms = jnp.sum(fingerprints**2, axis=1, keepdims=True)
    distances = norms - 2 * f32_matmul(fingerprints, table.T) + jnp.sum(table**2, axis=1)
    nearest = jnp.argmin(distances, axis=1)
    found = jnp.min(distances, axis=1) <= MATCH_TOLERANCE * (norms[:, 0] + 1.0)
    return jnp.where(found[:, None], state["rows"][nearest], jnp.nan)


def _report(state: dict, settings: dict) -> Report:
    """Their cost was paid elsewhere (NaN); a benchmark that trains on an aligned route
    validates on its places, which outside descriptors do not describe."""
    return Report(fit_seconds=math.nan, validation=bool(state["covers_validation"]))


method = Method(fit=fit, encode=encode, needs=("outside",), random=False, report=_report)


def zero_warning(sides: dict[str, OutsideSide], names: dict[str, np.ndarray]) -> str | None:
    """One line naming the images (``names``: side -> the benchmark's) whose outside
    descriptor is zero (their cosine to every image is 0: their matches are arbitrary), or
    None."""
    found = []
    for side, side_names in names.items():
        zero = sorted(set(sides[side].zero) & {str(n) for n in side_names})
        if zero:
            more = f" and {len(zero) - 3:,} more" if len(zero) > 3 else ""
            found.append(f"{len(zero):,} {side} rows ({', '.join(zero[:3])}{more})")
    if not found:
        return None
    return (
        f"zero descriptors: {' and '.join(found)}; cosine scores them 0 against every "
        "image, so their matches are arbitrary: recompute those descriptors"
    )
