"""The code's shape: no module of vpr_jax/ or experiments/ imports itself back in a cycle."""

import ast
import subprocess
import sys

from tests.conftest import REPO


def _modules() -> dict[str, ast.Module]:
    out = {}
    for path in [*REPO.glob("vpr_jax/**/*.py"), *REPO.glob("experiments/**/*.py")]:
        name = ".".join(path.relative_to(REPO).with_suffix("").parts)
        out[name.removesuffix(".__init__")] = ast.parse(path.read_text())
    return out


def import_graph() -> dict[str, set[str]]:
    """Module -> the modules of ours it imports (anywhere in it, lazy imports included).
    ``from a import b`` counts as importing ``a.b`` where that is a module, else ``a``; a
    package imported only as the parent of a module does not count."""
    modules = _modules()
    graph = {}
    for name, tree in modules.items():
        found = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                found |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                found |= {
                    f"{node.module}.{a.name}"
                    if f"{node.module}.{a.name}" in modules
                    else node.module
                    for a in node.names
                }
        graph[name] = {m for m in found if m in modules and m != name}
    return graph


def _cycle_from(start: str, graph: dict[str, set[str]]) -> list[str] | None:
    stack = [(start, [start])]
    seen = set()
    while stack:
        node, path = stack.pop()
        for nxt in graph[node]:
            if nxt == start:
                return [*path, start]
            if nxt not in seen:
                seen.add(nxt)
                stack.append((nxt, [*path, nxt]))
    return None


def test_no_import_cycles():
    graph = import_graph()
    assert "experiments.run" in graph["experiments.sweep"]  # the graph sees lazy imports
    cycles = [c for m in sorted(graph) if (c := _cycle_from(m, graph))]
    assert not cycles, " -> ".join(cycles[0])


def test_methods_make_descriptors_and_never_match():
    graph = import_graph()
    assert not {"vpr_jax.sequence", "experiments.cells"} & graph["vpr_jax.methods"]
    tree = _modules()["vpr_jax.methods"]
    names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    assert not {"top_k_matches", "sequence_top_k_cosine", "evaluate_top_k"} & names


def _ruff(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "ruff", *args], cwd=REPO, capture_output=True, text=True, timeout=60
    )


def test_ruff_owns_the_layout_and_the_lint():
    """One formatter lays out every file (``ruff format``); ``ruff check`` finds nothing."""
    fmt = _ruff("format", "--check", ".")
    assert fmt.returncode == 0, f"run `ruff format .`:\n{fmt.stdout}{fmt.stderr}"
    lint = _ruff("check", ".")
    assert lint.returncode == 0, f"run `ruff check .`:\n{lint.stdout}{lint.stderr}"
