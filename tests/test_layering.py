"""The packages stay layered (issue 40): iarcs_env <- rewards <- agents <- experiments, each importing only those
below it, and no two modules import each other, directly or round a loop. Read from the source (imports inside
functions count; ``if TYPE_CHECKING:`` imports, which never run, do not)."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LAYERS = ["iarcs_env", "rewards", "agents", "experiments"]


def modules() -> dict[str, Path]:
    out = {}
    for package in LAYERS:
        for path in (REPO / package).rglob("*.py"):
            name = ".".join(path.relative_to(REPO).with_suffix("").parts)
            out[name.removesuffix(".__init__")] = path
    return out


def imports(name: str, path: Path, known: dict[str, Path]) -> set[str]:
    """The project modules ``name`` imports (a package's submodules named in ``from package import x`` too)."""
    tree = ast.parse(path.read_text())
    skip = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
            for child in node.body for n in ast.walk(child)}
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(tree):
        if id(node) in skip or not isinstance(node, (ast.Import, ast.ImportFrom)):
            continue
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        else:
            base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
            prefix = ".".join(base + ([node.module] if node.module else []))
            targets = [f"{prefix}.{a.name}" if f"{prefix}.{a.name}" in known else prefix for a in node.names]
        for target in targets:
            while target and target not in known and "." in target:
                target = target.rsplit(".", 1)[0]
            if target in known and target != name:
                found.add(target)
    return found


def graph() -> dict[str, set[str]]:
    known = modules()
    return {name: imports(name, path, known) for name, path in known.items()}


def test_no_package_imports_a_layer_above_it():
    rank = {package: k for k, package in enumerate(LAYERS)}
    upward = [(a, b) for a, deps in graph().items() for b in deps if rank[b.split(".")[0]] > rank[a.split(".")[0]]]
    assert not upward, upward


def test_no_import_cycles():
    edges = graph()
    cycles, state = [], {}

    def visit(node, path):
        state[node] = "open"
        for dep in sorted(edges[node]):
            if state.get(dep) == "open":
                cycles.append(path[path.index(dep):] + [dep])
            elif dep not in state:
                visit(dep, path + [dep])
        state[node] = "done"

    for node in sorted(edges):
        if node not in state:
            visit(node, [node])
    # a package's __init__ importing its own submodules is how packages export; not a cycle of the design
    cycles = [c for c in cycles if not any(a.startswith(b + ".") or b.startswith(a + ".") for a, b in zip(c, c[1:]))]
    assert not cycles, cycles


def test_the_checker_sees_cycles_and_upward_imports(tmp_path, monkeypatch):
    """The checker itself: a loop and an upward import planted in a copy of the layout are found."""
    for package in LAYERS:
        (tmp_path / package).mkdir()
        (tmp_path / package / "__init__.py").write_text("")
    (tmp_path / "agents" / "a.py").write_text("from . import b\n")
    (tmp_path / "agents" / "b.py").write_text("def f():\n    from agents import a\n")
    (tmp_path / "iarcs_env" / "env.py").write_text("import rewards.composite\n")
    (tmp_path / "rewards" / "composite.py").write_text("")
    monkeypatch.setattr(__import__(__name__), "REPO", tmp_path)
    edges = graph()
    assert edges["agents.a"] == {"agents.b"} and edges["agents.b"] == {"agents.a"}
    assert edges["iarcs_env.env"] == {"rewards.composite"}
