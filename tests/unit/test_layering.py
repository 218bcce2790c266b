"""The package layout is the architecture: imports go down the layers, never up, never in a circle.

    errors  <-  model | protocol | chains  <-  planner | runtime  <-  policies  <-  simulation | node
            <-  agent | basestation | recording | deploy  <-  launch | teamsim  <-  cli

Packages on one level are peers and do not import each other. Every import counts, including the
ones inside functions: a lazy import hides a cycle from Python, not from a reader.
"""

import ast
from pathlib import Path

import networkx as nx

ROOT = Path(__file__).resolve().parents[2] / "autopower"
LEVELS = {
    "errors": 0,
    "model": 1, "protocol": 1, "chains": 1, "scenarios": 1,
    "planner": 2, "runtime": 2,
    "policies": 3,
    "simulation": 4, "node": 4,
    "agent": 5, "basestation": 5, "recording": 5, "deploy": 5,
    "launch": 6, "teamsim": 6,
    "cli": 7,
}
PUBLIC_API = "autopower"  # the package's __init__: re-exports, may import any layer


def package_of(module: str) -> str:
    parts = module.split(".")
    return PUBLIC_API if len(parts) == 1 else parts[1]


def modules() -> dict[str, Path]:
    found = {}
    for path in ROOT.rglob("*.py"):
        parts = path.relative_to(ROOT.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        found[name] = path
    return found


def imports_of(path: Path, module: str, known: set[str]) -> set[str]:
    """Every autopower module this one imports (`from a.b import c` counts a.b.c when it is a module)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            submodules = {f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in known}
            out |= submodules or {base}
    return {name for name in out if name.startswith("autopower")}


def graph() -> nx.DiGraph:
    found = modules()
    g = nx.DiGraph()
    for module, path in found.items():
        g.add_node(module)
        for target in imports_of(path, module, set(found)):
            if target != module and target in found:
                g.add_edge(module, target)
    return g


def test_every_package_has_a_level():
    packages = {package_of(m) for m in modules()} - {PUBLIC_API}
    assert packages <= set(LEVELS), f"give these packages a level: {sorted(packages - set(LEVELS))}"


def test_nothing_imports_upward_or_sideways():
    wrong = []
    for here, there in graph().edges:
        a, b = package_of(here), package_of(there)
        if a == PUBLIC_API or a == b:
            continue
        if b == PUBLIC_API:
            wrong.append(f"{here} imports the public API package {there}; import the module itself")
        elif LEVELS[b] >= LEVELS[a]:
            wrong.append(f"{here} ({a}, level {LEVELS[a]}) imports {there} ({b}, level {LEVELS[b]})")
    assert not wrong, "\n".join(sorted(wrong))


def test_no_import_cycles():
    g = graph()
    # a package's __init__ re-exporting its own modules is not a cycle of design
    g.remove_edges_from([(a, b) for a, b in list(g.edges) if b.startswith(a + ".") and modules()[a].name == "__init__.py"])
    cycles = list(nx.simple_cycles(g))
    assert not cycles, "import cycles:\n" + "\n".join(" -> ".join(c + [c[0]]) for c in cycles)


def test_each_package_says_what_it_owns_and_may_import():
    missing = []
    for init in ROOT.glob("*/__init__.py"):
        doc = ast.get_docstring(ast.parse(init.read_text())) or ""
        if init.parent.name != "scenarios" and ("May import" not in doc and "may import" not in doc):
            missing.append(init.parent.name)
    assert not missing, f"these packages' __init__ docstrings do not say what they may import: {missing}"


def test_the_checker_catches_an_upward_import(tmp_path):
    """The rule above must be able to fail: an upward edge and a cycle are reported."""
    g = nx.DiGraph([("autopower.model.x", "autopower.cli.main"), ("autopower.cli.main", "autopower.model.x")])
    upward = [(a, b) for a, b in g.edges if LEVELS[package_of(b)] >= LEVELS[package_of(a)]]
    assert upward == [("autopower.model.x", "autopower.cli.main")]
    assert list(nx.simple_cycles(g))
