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
from collections.abc import Iterator

from vpr_jax.config import SweepConfig
from vpr_jax.data.pair import PairData
from vpr_jax.method_table import MethodInfo
from vpr_jax.methods.descriptors import Descriptors, MethodContext, degenerate_warning


def describe_precomputed(
    info: MethodInfo, pair: PairData, cfg: SweepConfig, ctx: MethodContext
) -> Iterator[Descriptors]:
    """The pair's database, queries and (benchmark-held-out) validation queries, picked by
    image name from the set the plan read (``ctx.outside``)."""
    sides = ctx.outside[info.name]
    db, query = sides["database"].of(pair.names.db), sides["queries"].of(pair.names.query)
    held_out = not pair.aligned_training  # validation queries are the benchmark's own
    yield Descriptors(
        method=info.name,
        removed_pcs=(0,),
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
