"""Descriptors computed elsewhere as one more row of a benchmark sweep
(``precomputed.<name>.database=PATH``, ``precomputed.<name>.queries=PATH``;
``vpr_jax.data.precomputed`` reads and checks the files).

Nothing is fitted or encoded here: fit and encoding times are NaN (unknown: they were spent
elsewhere), and no encoder is saved. The validation queries are the benchmark's own held-out
queries when it trains on its database; a benchmark that learns from an aligned route
(``data.train_source``) validates on that route's places, which outside descriptors do not
cover, so their validation scores are NaN (one cell: nothing is chosen on them).
"""

from __future__ import annotations

import math

from vpr_jax.data.pair import PairData
from vpr_jax.data.precomputed import OutsideSide, setting_key
from vpr_jax.errors import UserError
from vpr_jax.methods.descriptors import Descriptors, Part, degenerate, degenerate_warning


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


def precomputed_descriptors(
    name: str, sides: dict[str, OutsideSide], pair: PairData, seed: int
) -> Descriptors:
    """The pair's database, queries and (benchmark-held-out) validation queries of the set
    ``name``, picked by image name from what the plan read."""
    db, query = sides["database"].of(pair.names.db), sides["queries"].of(pair.names.query)
    held_out = not pair.aligned_training  # validation queries are the benchmark's own
    return Descriptors(
        method=name,
        objective="",
        seed=seed,
        parts=(Part(settings={}, setting="", run=name),),
        starts=(0,),
        db=db,
        query=query,
        val_db=db if held_out else None,
        val_query=sides["queries"].of(pair.names.val_query) if held_out else None,
        fit_seconds=math.nan,
        encode_ms_per_image=math.nan,
        basis=(None,),
        warning=_zero_warning(sides, pair) or degenerate_warning(db, query),
    )


def _zero_warning(sides: dict[str, OutsideSide], pair: PairData) -> str | None:
    """One line naming the pair's images whose outside descriptor is zero (their cosine to
    every image is 0: their matches are arbitrary), or None."""
    found = []
    for side, names in (("database", pair.names.db), ("queries", pair.names.query)):
        zero = sorted(set(sides[side].zero) & {str(n) for n in names})
        if zero:
            more = f" and {len(zero) - 3:,} more" if len(zero) > 3 else ""
            found.append(f"{len(zero):,} {side} rows ({', '.join(zero[:3])}{more})")
    if not found:
        return None
    return (
        f"zero descriptors: {' and '.join(found)}; cosine scores them 0 against every "
        "image, so their matches are arbitrary: recompute those descriptors"
    )
