"""Dependency direction: core <- chains <- {agent, basestation} <- deploy. Nothing imports upward."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2] / "autopower"
LAYERS = {"core": 0, "chains": 1, "agent": 2, "basestation": 2, "deploy": 3}


def layer_of(module: str) -> str:
    parts = module.split(".")
    if parts[0] != "autopower" or len(parts) == 1:
        return "core"
    return parts[1] if parts[1] in LAYERS else "core"


def test_nothing_imports_upward():
    wrong = []
    for path in ROOT.rglob("*.py"):
        module = ".".join(path.relative_to(ROOT.parent).with_suffix("").parts)
        here = layer_of(module)
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            for name in names:
                if name.startswith("autopower"):
                    there = layer_of(name)
                    if LAYERS[there] > LAYERS[here] or (LAYERS[there] == LAYERS[here] and there != here):
                        wrong.append(f"{module} ({here}) imports {name} ({there})")
    assert not wrong, "\n".join(wrong)
