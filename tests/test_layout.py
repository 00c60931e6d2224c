"""The package's import graph: no cycles, and production code never imports
the numpy references (mccnn_cl.reference is the tests' oracle).

The graph is read from the source (every ``import`` statement, those inside
functions too, as a lazy import is still a dependency): an edge goes to the
module named, or to ``package.name`` when ``from package import name`` names
a submodule.  Importing a submodule also runs its package's ``__init__``;
that implicit edge is not counted (an ``__init__`` re-exporting its
submodules would otherwise close a loop with every child that imports a
sibling).
"""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "mccnn_cl"


def _modules() -> dict:
    """module name -> (path, is_package) for every .py file of the package."""
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        is_pkg = parts[-1] == "__init__"
        if is_pkg:
            parts = parts[:-1]
        out[".".join(parts)] = (path, is_pkg)
    return out


def import_graph() -> dict:
    """module -> set of package modules it imports (see the module docstring)."""
    mods = _modules()
    graph = {}
    for name, (path, is_pkg) in mods.items():
        edges = set()
        base = name.split(".") if is_pkg else name.split(".")[:-1]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    stem = base[:len(base) - node.level + 1]
                    src = ".".join(stem + ([node.module] if node.module else []))
                else:
                    src = node.module or ""
                targets = [f"{src}.{a.name}" if f"{src}.{a.name}" in mods else src for a in node.names]
            else:
                continue
            for t in targets:
                while t and t not in mods:  # "import a.b.c" of a name inside a module
                    t = t.rpartition(".")[0]
                if t and t != name:
                    edges.add(t)
        graph[name] = edges
    return graph


def cycles(graph: dict) -> list:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_graph_sees_the_package():
    g = import_graph()
    assert "mccnn_cl.pipeline" in g and "mccnn_cl.costs.registry" in g["mccnn_cl.pipeline"]
    assert "mccnn_cl.opencl.context" in g["mccnn_cl.stages.sgm"]


def test_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycles():
    found = cycles(import_graph())
    assert not found, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in found)


def test_production_code_does_not_import_the_references():
    g = import_graph()
    bad = sorted(f"{m} imports {t}" for m, ts in g.items() if not m.startswith("mccnn_cl.reference")
                 for t in ts if t == "mccnn_cl.reference" or t.startswith("mccnn_cl.reference."))
    assert not bad, "\n".join(bad)
