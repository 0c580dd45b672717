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
from vpr_jax.data.precomputed import OutsideSide
from vpr_jax.methods.descriptors import Descriptors, Part, degenerate_warning


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
        parts=(Part(setting="", removed_pcs=0, run=name),),
        starts=(0,),
        db=db,
        query=query,
        val_db=db if held_out else None,
        val_query=sides["queries"].of(pair.names.val_query) if held_out else None,
        fit_seconds=math.nan,
        encode_ms_per_image=math.nan,
        basis=(None,),
        warning=degenerate_warning(db, query),
    )
