"""The documentation keeps up with the code: every config key is in docs/config.md (and
nothing else is), README stays a short front door, and relative links resolve."""

import dataclasses
import re
from pathlib import Path

from vpr_jax.config import SweepConfig

REPO = Path(__file__).resolve().parent.parent
CONFIG_DOC = REPO / "docs" / "config.md"
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def config_keys(obj=None, prefix=""):
    """Dotted names of every leaf field, e.g. ``seed``, ``data.root`` and each built-in
    method's settings, ``ica.n_components`` (its ``Settings``). Nesting is read off the
    default values: with ``from __future__ import annotations`` field.type is a string."""
    from experiments.resolve import load
    from vpr_jax.method_table import METHODS

    obj = SweepConfig() if obj is None else obj
    keys = set()
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if not prefix and f.name in METHODS:
            settings = load(METHODS[f.name]).settings
            if settings is not None:
                keys |= config_keys(settings(), f"{f.name}.")
        elif dataclasses.is_dataclass(value):
            keys |= config_keys(value, f"{prefix}{f.name}.")
        else:
            keys.add(prefix + f.name)
    return keys


def documented_keys():
    """Backticked names in the first column of docs/config.md's table rows."""
    keys = set()
    for line in CONFIG_DOC.read_text().splitlines():
        if line.startswith("|") and not line.startswith("|---"):
            first_cell = line.split("|")[1]
            keys |= set(re.findall(r"`([^`]+)`", first_cell))
    return keys


def test_every_config_field_is_documented():
    text = CONFIG_DOC.read_text()
    missing = sorted(k for k in config_keys() if f"`{k}`" not in text)
    assert not missing, f"docs/config.md lacks {missing}"


def test_documented_keys_exist():
    unknown = sorted(documented_keys() - config_keys())
    assert not unknown, f"docs/config.md lists keys that are no config field: {unknown}"


def test_readme_is_short():
    size = len((REPO / "README.md").read_bytes())  # as `wc -c` counts
    assert size < 16_000, f"README.md has {size} bytes (limit 16,000): move detail to docs/"


def test_relative_links_resolve():
    broken = []
    for page in PAGES:
        text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)  # code blocks
        text = re.sub(r"`[^`]*`", "", text)  # inline code
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            path = target.split("#", 1)[0]
            if path and not target.startswith(("http://", "https://", "mailto:")):
                if not (page.parent / path).exists():
                    broken.append(f"{page.relative_to(REPO)}: {target}")
    assert not broken, f"links to missing files: {broken}"


def test_the_refusal_catalogue_lists_every_bad_input_case():
    from tests import test_bad_input

    catalogue = (REPO / "docs" / "refusals.md").read_text()
    cases = [*test_bad_input.DATA_CASES, *test_bad_input.CONFIG_CASES, *test_bad_input.LOGDIR_CASES]
    missing = [case for case in cases if f"| {case} |" not in catalogue]
    assert not missing, f"docs/refusals.md lacks {missing}"
    for module, name in re.findall(r"`(test_\w+\.py)::(\w+)", catalogue):
        assert f"def {name}(" in (REPO / "tests" / module).read_text(), f"{module}::{name}"


def test_the_worked_example_of_your_own_method_runs(tmp_path, monkeypatch):
    """docs/methods.md's example module, as printed there, fits and encodes (the sweep's own
    handling of such a method is tests/test_plugins.py's)."""
    import numpy as np

    text = (REPO / "docs" / "methods.md").read_text()
    section = text.split("### A worked example", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    (tmp_path / "edges.py").write_text(code)
    monkeypatch.syspath_prepend(str(tmp_path))
    from experiments.resolve import load
    from vpr_jax.method_table import info_of

    edges = load(info_of("edges:edges"))
    rng = np.random.default_rng(0)
    train = rng.random((40, 32, 64), dtype=np.float32)
    state = edges.fit(train, None, None, n_components=16)
    out = edges.encode(state, train[:5])
    assert out.shape == (5, 16) and np.isfinite(np.asarray(out)).all()
    assert edges.axes(None) == {"skip": "served"}  # one fit serves every skip
    shifted = edges.encode(state, train[:5], skip=5)
    np.testing.assert_allclose(shifted[:, :13], out[:, 3:], rtol=1e-5, atol=1e-5)
    assert "edges:edges" in text  # the command names it as the example defines it
