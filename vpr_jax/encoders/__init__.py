"""Fitting what turns images into descriptors: PCA, ICA, diff_pca and LDA fits, the Flax
auto-encoders, their training loop and its orbax checkpoints. Each fit returns a pytree of
arrays; each encoder is a pure ``encode(params, images)``."""
