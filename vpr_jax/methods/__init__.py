"""One season pair through one method: fit on the training images, encode the database and
the queries. What comes out is ``Descriptors``; matching, metrics and files are the runner's
(``experiments/cells.py``), as in VPR_Tutorial's dataset -> features -> matching ->
evaluation.

Methods with the removed-PC axis (``config.SWEEPS_REMOVED_PCS``: pca, diff_pca, ica) serve
several counts: PCA's coefficients and diff_pca's suffix descriptors serve every count at
once (cosine on the suffix ``[k:]`` is the removal of the first k components, one
similarity pass for all), ICA fits once per count and yields each as soon as it is done.
diff_pca and lda learn from the alignment of the training places (``aligned_train``). The
auto-encoders checkpoint their training and report it through the ``MethodContext`` the
runner passes in.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from functools import partial

from vpr_jax.config import SweepConfig
from vpr_jax.data.pair import PairData
from vpr_jax.methods.autoencoders import autoencoder_spec, describe_autoencoder, model_name
from vpr_jax.methods.descriptors import Descriptors, MethodContext, PCAFit, degenerate_warning
from vpr_jax.methods.linear import (
    describe_diff_pca,
    describe_ica,
    describe_lda,
    describe_pca,
    describe_raw,
    fit_pair_pca,
    pca_components_needed,
)

__all__ = [
    "AUTOENCODERS",
    "METHODS",
    "USES_PCA_FIT",
    "Descriptors",
    "MethodContext",
    "PCAFit",
    "PairData",
    "autoencoder_spec",
    "degenerate_warning",
    "fit_pair_pca",
    "model_name",
    "pca_components_needed",
]


# A method maps (pair, config, context) to its descriptors, in any order, as they finish.
Method = Callable[[PairData, SweepConfig, MethodContext], Iterable[Descriptors]]
METHODS: dict[str, Method] = {
    "raw": describe_raw,
    "pca": describe_pca,
    "diff_pca": describe_diff_pca,
    "ica": describe_ica,
    "lda": describe_lda,
    "fae": partial(describe_autoencoder, "fae"),
    "cae": partial(describe_autoencoder, "cae"),
}
USES_PCA_FIT = frozenset({"pca", "ica", "lda"})  # their context carries the pair's PCA fit
AUTOENCODERS = frozenset({"fae", "cae"})  # trained, one model per objective
