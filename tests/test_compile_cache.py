"""Where the sweep keeps XLA's compiled programs (``vpr_jax.compile_cache``)."""

from __future__ import annotations

import contextlib

import jax
import pytest

from vpr_jax import compile_cache


@contextlib.contextmanager
def no_jax_cache_folder():
    """JAX without a cache folder of its own (the suite gives it one), restored after."""
    saved = jax.config.jax_compilation_cache_dir
    saved_time = jax.config.jax_persistent_cache_min_compile_time_secs
    jax.config.update("jax_compilation_cache_dir", None)
    try:
        yield
    finally:
        jax.config.update("jax_compilation_cache_dir", saved)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", saved_time)


@pytest.mark.timeout(60)
def test_programs_are_kept_in_a_folder_per_kind_of_cpu(tmp_path):
    with no_jax_cache_folder():
        used = compile_cache.use(str(tmp_path / "xla"))
        assert used == tmp_path / "xla" / compile_cache.machine_tag()
        assert used.is_dir()
        assert jax.config.jax_compilation_cache_dir == str(used)
        assert jax.config.jax_persistent_cache_min_compile_time_secs == 0.0
    assert compile_cache.machine_tag() == compile_cache.machine_tag()  # stable


@pytest.mark.timeout(60)
def test_off_or_unwritable_leaves_jax_uncached(tmp_path):
    blocker = tmp_path / "a file"
    blocker.write_text("")
    notes = []
    with no_jax_cache_folder():
        assert compile_cache.use(None, notes.append) is None
        assert compile_cache.use(str(blocker / "xla"), notes.append) is None
        assert jax.config.jax_compilation_cache_dir is None
    assert len(notes) == 1 and "compile_cache=" in notes[0] and "cannot be made" in notes[0]


@pytest.mark.timeout(60)
def test_a_folder_jax_has_already_wins(tmp_path):
    with no_jax_cache_folder():
        jax.config.update("jax_compilation_cache_dir", str(tmp_path / "mine"))
        assert compile_cache.use(str(tmp_path / "ours")) == tmp_path / "mine"
        assert not (tmp_path / "ours").exists()
