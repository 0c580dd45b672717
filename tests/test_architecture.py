"""The code's shape: no import cycle, stages that import only earlier stages, short
functions, records built by name, one formatter."""

import ast
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from tests.conftest import REPO, run_process


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


# The stages of the data flow, in order. A module of a stage imports its own stage, earlier
# stages and the foundation (the modules at vpr_jax's root, which import no stage); the
# runner (experiments/) and the package's front door (vpr_jax/__init__.py) may import any.
STAGES = ("data", "encoders", "methods", "evaluation", "outputs")


def _stage(module: str) -> int | None:
    """The stage index of a vpr_jax module, None for the foundation and the runner."""
    parts = module.split(".")
    if parts[0] == "vpr_jax" and len(parts) > 1 and parts[1] in STAGES:
        return STAGES.index(parts[1])
    return None


def test_no_stage_imports_a_later_stage_and_the_foundation_imports_none():
    graph = import_graph()
    assert {"data", "encoders", "methods", "evaluation", "outputs"} == {
        m.split(".")[1] for m in graph if _stage(m) is not None
    }  # every stage is a folder the graph sees
    backwards = [
        f"{m} -> {dep}"
        for m, deps in graph.items()
        if _stage(m) is not None
        for dep in deps
        if _stage(dep) is not None and _stage(dep) > _stage(m)
    ]
    assert not backwards, f"a stage imports a later one: {backwards}"
    foundation = [m for m in graph if m.startswith("vpr_jax.") and _stage(m) is None]
    assert {"vpr_jax.config", "vpr_jax.sharding", "vpr_jax.files"} <= set(foundation)
    reaching = [f"{m} -> {dep}" for m in foundation for dep in graph[m] if _stage(dep) is not None]
    assert not reaching, f"the foundation imports a stage: {reaching}"


def test_the_encoders_load_no_method():
    """encoders/ is the math and its files; which method a saved folder is, and loading its
    object, belong to methods/ (``vpr_jax.methods.loading``)."""
    found = [
        str(p.relative_to(REPO))
        for p in REPO.glob("vpr_jax/encoders/*.py")
        if "load_object" in p.read_text() or "method_table" in p.read_text()
    ]
    assert not found, f"encoders/ loading methods: {found}"


def test_methods_make_descriptors_and_never_match():
    modules = _modules()
    graph = import_graph()
    package = [m for m in modules if m == "vpr_jax.methods" or m.startswith("vpr_jax.methods.")]
    assert len(package) > 1
    for module in package:
        assert not {"experiments.cells"} & graph[module]
        names = {n.id for n in ast.walk(modules[module]) if isinstance(n, ast.Name)}
        assert not {"top_k_matches", "sequence_top_k_cosine", "evaluate_top_k"} & names, module


def _ruff(*args: str) -> subprocess.CompletedProcess:
    return run_process([sys.executable, "-m", "ruff", *args], timeout=60)


PROJECT_FOLDERS = ("vpr_jax", "experiments", "tests", "benchmarks")


def project_python_files(repo: Path = REPO) -> list[str]:
    """The project's own Python files, relative to ``repo``: the ones git tracks (that are
    still there), so a folder of a user's own in the clone (their methods, untracked) is
    never the project's to lay out. Outside a git checkout: those of the project's folders
    and its root."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--", "*.py"], cwd=repo, capture_output=True, check=False
    )
    if listed.returncode == 0:
        names = [name for name in listed.stdout.decode().split("\0") if name]
    else:
        paths = [*repo.glob("*.py")]
        paths += [p for folder in PROJECT_FOLDERS for p in repo.glob(f"{folder}/**/*.py")]
        names = [p.relative_to(repo).as_posix() for p in paths]
    return sorted(name for name in names if (repo / name).is_file())


def test_ruff_owns_the_layout_and_the_lint():
    """One formatter lays out every file of the project (``ruff format``); ``ruff check``
    finds nothing in them."""
    files = project_python_files()
    assert "vpr_jax/__init__.py" in files and "tests/test_architecture.py" in files
    fmt = _ruff("format", "--check", *files)
    assert fmt.returncode == 0, f"run `ruff format .`:\n{fmt.stdout}{fmt.stderr}"
    lint = _ruff("check", *files)
    assert lint.returncode == 0, f"run `ruff check .`:\n{lint.stdout}{lint.stderr}"


def test_a_user_s_untracked_module_in_the_clone_is_not_the_project_s_to_lay_out():
    """A folder of a user's own in the clone (docs/methods.md puts it outside, but one may
    not), holding a badly laid out module git does not track, is left out of the files the
    layout and lint test checks."""
    folder = Path(tempfile.mkdtemp(prefix="user_methods_", dir=REPO))
    try:
        (folder / "mine.py").write_text("import os,sys\ndef  f( x ):\n  return x\n")
        files = project_python_files()
        assert not [name for name in files if name.startswith(folder.name)]
        assert "vpr_jax/methods/loading.py" in files  # the project's own stay in
    finally:
        shutil.rmtree(folder)


MAX_FUNCTION_LINES = 60


def test_no_function_is_longer_than_a_reader_can_hold():
    """No function of vpr_jax/ or experiments/ over 60 lines (its ``def`` to its last line;
    a nested function counts on its own and inside its parent)."""
    long = [
        f"{name}:{node.lineno} {node.name} ({node.end_lineno - node.lineno + 1} lines)"
        for name, tree in _modules().items()
        for node in ast.walk(tree)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES
    ]
    assert not long, f"split into named steps: {long}"


def _records(trees) -> dict[str, list[str]]:
    """NamedTuple and dataclass names -> their fields, of every module in ``trees``."""
    out = {}
    for tree in trees:
        for node in ast.walk(tree):
            if not isinstance(node, ast.ClassDef):
                continue
            kinds = [ast.unparse(b) for b in node.bases + node.decorator_list]
            if any("NamedTuple" in k or "dataclass" in k for k in kinds):
                out[node.name] = [
                    s.target.id
                    for s in node.body
                    if isinstance(s, ast.AnnAssign) and isinstance(s.target, ast.Name)
                ]
    return out


def test_records_of_more_than_three_fields_are_built_by_name():
    """A record (NamedTuple, dataclass) of more than three fields is constructed with
    keywords wherever it is built, tests and benchmarks included (``_make`` of an iterable
    of every field stays allowed)."""
    paths = [*REPO.glob("vpr_jax/**/*.py"), *REPO.glob("experiments/**/*.py")]
    paths += [*REPO.glob("benchmarks/*.py"), *REPO.glob("tests/*.py")]
    trees = {p.relative_to(REPO): ast.parse(p.read_text()) for p in paths}
    wide = {name for name, fields in _records(trees.values()).items() if len(fields) > 3}
    assert {"Cell", "TrainState", "TrainResult", "Descriptors"} <= wide  # the checker sees them
    positional = [
        f"{path}:{node.lineno} {ast.unparse(node.func)}"
        for path, tree in trees.items()
        for node in ast.walk(tree)
        if isinstance(node, ast.Call)
        and ast.unparse(node.func).split(".")[-1] in wide
        and node.args
    ]
    assert not positional, f"build these with keywords: {positional}"


def _setting_values(path: Path) -> set[str]:
    """Names a module may use as a setting's values although a method has the name: the
    auto-encoders' starts are named after the linear method they start from
    (``fae.init=pca``, ``lda``), and no method is looked up by them."""
    if path.relative_to(REPO).as_posix() == "vpr_jax/methods/autoencoder.py":
        from vpr_jax.methods.autoencoder import INITS

        return set(INITS)
    return set()


def test_a_method_is_fit_encode_and_at_most_six_declarations():
    """The contract stays small enough to hold in one's head (optax's transformation is two
    functions): a ninth field of ``Method`` fails here; each is documented in
    docs/methods.md's table of declarations."""
    from vpr_jax.methods.contract import Method

    assert Method._fields[:2] == ("fit", "encode")
    assert len(Method._fields) <= 8, Method._fields
    table = (REPO / "docs" / "methods.md").read_text().split("## Your own method", 1)[1]
    missing = [f for f in Method._fields[2:] if f"| `{f} =" not in table]
    assert not missing, f"docs/methods.md's table of declarations lacks {missing}"


def test_only_the_method_table_lists_the_methods():
    """Adding a method is one module and one line in vpr_jax/method_table.py: no other module
    of vpr_jax/, experiments/ or benchmarks/ keeps a list, tuple, set or dict of two or more
    method names."""
    from vpr_jax.method_table import NAMES

    paths = [*REPO.glob("vpr_jax/**/*.py"), *REPO.glob("experiments/**/*.py")]
    paths += [*REPO.glob("benchmarks/*.py")]
    lists = []
    for path in paths:
        if path.name == "method_table.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            items = getattr(node, "elts", None) or getattr(node, "keys", None) or []
            if isinstance(node, ast.List | ast.Tuple | ast.Set | ast.Dict):
                names = {i.value for i in items if isinstance(i, ast.Constant)} & set(NAMES)
                names -= _setting_values(path)
                if len(names) >= 2:
                    lists.append(f"{path.relative_to(REPO)}:{node.lineno} {sorted(names)}")
    assert not lists, f"use vpr_jax.method_table instead: {lists}"


def _name_lookups(tree: ast.Module, names: set[str]) -> list[tuple[int, str]]:
    """(line, name) of every method name used as a string to decide something: compared
    (``==``, ``in``, also inside a tuple or list compared with), a subscript (``d["pca"]``),
    a dict key, or the key of ``.get``, ``getattr``, ``hasattr`` or ``.index``."""

    def constants(node) -> list[str]:
        if isinstance(node, ast.Constant) and node.value in names:
            return [node.value]
        if isinstance(node, ast.Tuple | ast.List | ast.Set):
            return [v for item in node.elts for v in constants(item)]
        return []

    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            used = [v for side in (node.left, *node.comparators) for v in constants(side)]
        elif isinstance(node, ast.Subscript):
            used = constants(node.slice)
        elif isinstance(node, ast.Dict):
            used = [v for key in node.keys if key is not None for v in constants(key)]
        elif isinstance(node, ast.Call):
            func = ast.unparse(node.func)
            looks_up = func in ("getattr", "hasattr") or func.endswith((".get", ".index"))
            used = [v for a in node.args for v in constants(a)] if looks_up else []
        else:
            used = []
        found += [(node.lineno, v) for v in used]
    return found


def test_no_module_decides_by_a_method_s_name():
    """The runner asks a method's declarations, never its name: outside the method table
    and the method's own module (``vpr_jax/methods/<name>.py``), no module of vpr_jax/,
    experiments/ or benchmarks/ compares a method name as a string, or looks it up by one
    (a dict key, a subscript, ``getattr``)."""
    from vpr_jax.method_table import NAMES

    paths = [*REPO.glob("vpr_jax/**/*.py"), *REPO.glob("experiments/**/*.py")]
    paths += [*REPO.glob("benchmarks/*.py")]
    found = []
    for path in paths:
        if path.name == "method_table.py":
            continue
        others = set(NAMES) - {path.stem} if path.parent.name == "methods" else set(NAMES)
        others -= _setting_values(path)
        found += [
            f"{path.relative_to(REPO)}:{line} {name!r}"
            for line, name in _name_lookups(ast.parse(path.read_text()), others)
        ]
    assert not found, f"declare it on the method instead (vpr_jax.methods.contract): {found}"


def test_the_name_check_sees_what_it_forbids():
    """Each form the check forbids, written once, is caught; a name in a message is not."""
    code = """
if method == "pca": pass
if "lda" in cfg.methods: pass
if m in ("ica", "x"): pass
x = table["fae"]
y = {"cae": 1}
z = getattr(cfg, "ica")
w = rows.get("diff_pca")
print(f"pca says {method}", "lda")
"""
    found = _name_lookups(ast.parse(code), {"pca", "lda", "ica", "fae", "cae", "diff_pca"})
    assert sorted(name for _, name in found) == [
        "cae",
        "diff_pca",
        "fae",
        "ica",
        "ica",
        "lda",
        "pca",
    ]
