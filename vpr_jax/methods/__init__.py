"""The methods: one module each (``raw``, ``pca``, ``diff_pca``, ``ica``, ``lda``, ``fae``,
``cae``), each a ``Method`` of the one contract a user's ``module:name`` has too
(``contract``): ``fit`` and a pure ``encode``, with declarations the runner reads instead of
checking names. ``vpr_jax.method_table`` lists them; ``settings`` turns what a sweep gives
into each fit's settings; ``descriptors`` holds what the runner makes of a fit. Methods make
descriptors, never matches: matching and metrics are the runner's (``experiments``), as in
VPR_Tutorial's dataset -> features -> matching -> evaluation.
"""
