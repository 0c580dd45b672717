"""One season pair through one method: fit on the training images, encode the database and
the queries. What comes out is ``Descriptors``; matching, metrics and files are the runner's
(``experiments/cells.py``), as in VPR_Tutorial's dataset -> features -> matching ->
evaluation.

Which methods exist, and what each needs, is ``vpr_jax.method_table``; each row names its
``describe(pair, cfg, ctx)`` here: ``linear.py`` (raw, pca, diff_pca, lda, ica),
``autoencoders.py`` (fae, cae), ``plugin.py`` (a user's ``module:name``).

Methods with the removed-PC axis (pca, diff_pca, ica) serve several counts: PCA's
coefficients and diff_pca's suffix descriptors serve every count at once (cosine on the
suffix ``[k:]`` is the removal of the first k components, one similarity pass for all), ICA
fits once per count and yields each as soon as it is done. diff_pca and lda learn from the
alignment of the training places (``aligned_train``). The auto-encoders checkpoint their
training and report it through the ``MethodContext`` the runner passes in; they select
their epochs by the validation places' recall@1, which the runner computes for them
(``MethodContext.validate``): methods make descriptors, never matches.
"""

from __future__ import annotations

from vpr_jax.data.pair import PairData
from vpr_jax.method_table import model_name
from vpr_jax.methods.autoencoders import autoencoder_spec
from vpr_jax.methods.descriptors import Descriptors, MethodContext, PCAFit, degenerate_warning
from vpr_jax.methods.linear import fit_pair_pca, pca_components_needed, uses_pca_fit

__all__ = [
    "Descriptors",
    "MethodContext",
    "PCAFit",
    "PairData",
    "autoencoder_spec",
    "degenerate_warning",
    "fit_pair_pca",
    "model_name",
    "pca_components_needed",
    "uses_pca_fit",
]
