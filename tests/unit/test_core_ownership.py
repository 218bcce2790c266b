"""A core object owns its state: the processes around it give it what it needs when they build it.

The node runtime (`autopower.node`) and the coordinator (`autopower.basestation`'s deciding,
placing, operating and takeover) are driven by shells: the agent, the base station's process,
the CLI, the recorder and the simulator. A shell that assigns an attribute into a core object
after building it (a callback, a store, a clock) hides one of the core's ways out from whoever
reads the core's constructor (`autopower.node.ports`). This test fails on any such assignment in
the product's code outside the core's own classes.
"""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2] / "autopower"
NODE_CORE = sorted((ROOT / "node").glob("*.py"))
COORDINATOR_CORE = [ROOT / "basestation" / f"{name}.py"
                    for name in ("coordinator", "faults", "deciding", "prediction", "placing", "runs", "publishing",
                                 "operating", "takeover", "listening")]
CORE_CLASSES = {"TeamListening", "NodeRuntime", "Frames", "Hosting", "Acknowledging", "Components", "Sinks", "PlanView", "Resuming", "Production", "Sight", "Metering", "ArrivalRelay", "Flows", "Holds", "Sources",
                "Coordinator", "TeamFaults", "Deciding", "AheadQuestion", "Prediction", "Placement", "Generations",
                "ChainRuns", "PlanPublisher", "OperatorControl", "Takeover"}
# the packages that build and drive core objects (the layers above `node`: test_layering.py)
SHELLS = ("agent", "basestation", "recording", "deploy", "launch", "teamsim", "cli")


def core_attributes() -> set[str]:
    """Every attribute a core class assigns on ``self``."""
    names = set()
    for path in (*NODE_CORE, *COORDINATOR_CORE):
        for cls in ast.parse(path.read_text()).body:
            if isinstance(cls, ast.ClassDef) and cls.name in CORE_CLASSES:
                for node in ast.walk(cls):
                    if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store) \
                            and isinstance(node.value, ast.Name) and node.value.id == "self":
                        names.add(node.attr)
    return names


def assignments_from_outside(path: Path, names: set[str]) -> list[str]:
    """``x.attr = ...`` (also augmented, annotated, in a tuple) with ``x`` not ``self`` and
    ``attr`` one of ``names``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        targets = node.targets if isinstance(node, ast.Assign) else \
            [node.target] if isinstance(node, (ast.AugAssign, ast.AnnAssign)) else []
        for target in targets:
            for part in ast.walk(target):
                if isinstance(part, ast.Attribute) and isinstance(part.ctx, ast.Store) and part.attr in names \
                        and not (isinstance(part.value, ast.Name) and part.value.id == "self"):
                    found.append(f"{path}:{node.lineno}: {ast.unparse(part)} = ...")
    return found


def test_the_core_attributes_are_known():
    names = core_attributes()
    # the ways out a shell used to assign, now constructor arguments (`NodePorts`, `NodeStores`)
    assert {"send_to", "_notify_work", "resume_from", "store", "held"} <= names
    assert {"incarnation", "placement"} <= names


def test_no_shell_assigns_into_a_core_object():
    names = core_attributes()
    core = {p.resolve() for p in (*NODE_CORE, *COORDINATOR_CORE)}
    found = []
    for package in SHELLS:
        for path in sorted((ROOT / package).rglob("*.py")):
            if path.resolve() not in core:
                found += assignments_from_outside(path, names)
    assert not found, "assigned into a core object from outside (give it to its constructor):\n" + "\n".join(found)


def test_the_check_sees_an_assignment_from_outside(tmp_path):
    shell = tmp_path / "shell.py"
    shell.write_text("def wire(rt, relayer):\n    rt.send_to = relayer.send\n    a.b, rt.stage_workers = 1, 2\n"
                     "    self.send_to = relayer.send\n")
    assert [line.split(": ", 1)[1] for line in assignments_from_outside(shell, core_attributes())] == [
        "rt.send_to = ...", "rt.stage_workers = ..."]
