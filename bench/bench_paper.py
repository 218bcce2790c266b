"""The paper's results reproduced by the product itself: Fig. 7, Fig. 8, physical accounting, variants and DVFS.

    .venv/bin/python bench/bench_paper.py [--json-out PATH]

Every figure comes from the installed command line, as a user gets it (`autopower analyze
SCENARIO --json`, `autopower plan SCENARIO --json`), each beside its baseline:
- Fig. 7's sixteen rows against the lifetimes the paper prints (the independent baseline);
- Fig. 8 (r1 starts with 32 kJ; the paper prints no table): the optimum of each topology and
  media pair against keeping every component local in that configuration;
- physical accounting (each message charged as sent) against the paper's accounting, row by row
  and for the optimum of each configuration;
- the control plane charged (statuses, keep-alives) against the paper's optimum of each configuration;
- quality variants and DVFS levels, and the team map (a DAG), against the paper's mission's
  optimum under the same accounting. Not a timed test: a few seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import results

AUTOPOWER = str(Path(sys.executable).parent / "autopower")
WHAT = "The paper's results reproduced by the product itself: Fig. 7, Fig. 8, physical accounting, variants and DVFS."


def cli(*args: str) -> dict:
    out = subprocess.run([AUTOPOWER, *args, "--json"], capture_output=True, text=True, timeout=600,
                         env={**os.environ, "RERUN_ANALYTICS": "0"})
    if out.returncode != 0:
        raise SystemExit(f"autopower {' '.join(args)} failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout)


def placement(allocation: dict[str, str], local: dict[str, str], base: str) -> str:
    """'all on the laptop', 'all local', or each stage's host."""
    if allocation and all(h == base for h in allocation.values()):
        return f"all on the {base}"
    if allocation and all(local.get(s) == h for s, h in allocation.items()):
        return "all local"
    return ", ".join(f"{s} {h}" for s, h in allocation.items())


def config(row: dict) -> str:
    return f"{row['topology']}, {row['laptop_robot_medium']} / {row['robot_robot_medium']}"


def by_label(rows: list[dict], label: str) -> dict[tuple, dict]:
    return {(r["topology"], r["laptop_robot_medium"], r["robot_robot_medium"]): r for r in rows if r["label"] == label}


def paper_rows(rows: list[dict]) -> list[dict]:
    out = [r for r in rows if r["label"].startswith("paper-row-")]
    return sorted(out, key=lambda r: int(r["label"].rsplit("-", 1)[1]))


def measure() -> tuple[list[dict], dict]:
    from autopower.model.loading import load_scenario

    fig7 = load_scenario("paper-fig7")
    local = {c.stages[0].name: c.source for c in fig7.chains}
    base = fig7.basestation
    figures: list[dict] = []
    groups: dict[str, dict] = {}

    g = "Fig. 7: the paper's sixteen rows"
    groups[g] = {"what": "`autopower analyze paper-fig7 --json`, paper accounting, each row against the lifetime "
                         "the paper prints for it.",
                 "value": "AutoPower", "baseline_value": "the paper's Fig. 7",
                 "detail": "placement"}
    paper7 = cli("analyze", "paper-fig7")
    for r in paper_rows(paper7["rows"]):
        n = r["label"].rsplit("-", 1)[1]
        figures.append(results.figure(f"row {n}: {config(r)}", r["lifetime_s"], "s", "the paper's Fig. 7",
                                      r["paper_lifetime_s"], note="the lifetime the paper prints for this row",
                                      group=g, detail=placement(r["allocation"], local, base)))

    g = "Fig. 8: r1 starts with 32 kJ, the optimum of each configuration"
    groups[g] = {"what": "`autopower analyze paper-fig8 --json` (the paper prints no table): the optimum of each "
                         "topology and media pair against every component local in that configuration.",
                 "value": "optimum", "baseline_value": "all local", "detail": "the optimum's placement"}
    fig8 = cli("analyze", "paper-fig8")
    allocal = by_label(fig8["rows"], "all-local")
    for key, r in by_label(fig8["rows"], "optimal").items():
        figures.append(results.figure(config(r), r["lifetime_s"], "s", "all local", allocal[key]["lifetime_s"],
                                      note="every component on its own robot, same configuration, same run",
                                      group=g, detail=placement(r["allocation"], local, base)))

    phys7 = cli("analyze", "paper-fig7", "--accounting", "physical")
    g = "Physical accounting: the sixteen rows"
    groups[g] = {"what": "`autopower analyze paper-fig7 --accounting physical --json`: each message charged as sent "
                         "(four 230 KB images a second, one scan every two seconds), against the paper's "
                         "accounting of the same row (one message a second per flow), same run.",
                 "value": "physical accounting", "baseline_value": "paper accounting", "detail": "placement"}
    paper_by_label = {r["label"]: r for r in paper7["rows"]}
    for r in paper_rows(phys7["rows"]):
        n = r["label"].rsplit("-", 1)[1]
        figures.append(results.figure(f"row {n}: {config(r)}", r["lifetime_s"], "s", "paper accounting",
                                      paper_by_label[r["label"]]["lifetime_s"],
                                      note="the same row under the paper's accounting, same run", group=g,
                                      detail=placement(r["allocation"], local, base)))
    g = "Physical accounting: the optimum of each configuration"
    groups[g] = {"what": "The optimum under physical accounting against the optimum under the paper's, per "
                         "topology and media pair.",
                 "value": "physical optimum", "baseline_value": "paper-accounting optimum",
                 "detail": "the physical optimum's placement"}
    paper_opt = by_label(paper7["rows"], "optimal")
    for key, r in by_label(phys7["rows"], "optimal").items():
        figures.append(results.figure(config(r), r["lifetime_s"], "s", "paper-accounting optimum",
                                      paper_opt[key]["lifetime_s"], note="the optimum under the paper's accounting",
                                      group=g, detail=placement(r["allocation"], local, base)))

    g = "The control plane charged: the optimum of each configuration"
    groups[g] = {"what": "`autopower analyze paper-fig7 --control-plane --json`: the team's own statuses, keep-alives "
                         "and their acknowledgements charged on every link (docs/concepts/energy-model.md, the "
                         "control plane), against the paper's optimum of the same configuration, which leaves them "
                         "out; same run.",
                 "value": "with the control plane", "baseline_value": "without (the paper)",
                 "detail": "the optimum's placement with it"}
    charged = cli("analyze", "paper-fig7", "--control-plane")
    for key, r in by_label(charged["rows"], "optimal").items():
        figures.append(results.figure(config(r), r["lifetime_s"], "s", "without (the paper)",
                                      paper_opt[key]["lifetime_s"],
                                      note="the same configuration's optimum with statuses and keep-alives free",
                                      group=g, detail=placement(r["allocation"], local, base)))

    g = "Quality variants and DVFS"
    groups[g] = {"what": "`autopower plan SCENARIO --accounting A --json` against the paper's mission's optimum "
                         "under the same accounting (`autopower plan paper-fig7`), same run.",
                 "value": "lifetime", "baseline_value": "paper-fig7 optimum",
                 "detail": "quality; what runs"}
    optimum = {a: cli("plan", "paper-fig7", "--accounting", a) for a in ("paper", "physical")}
    for scenario in ("paper-pxa255-dvfs", "paper-variants", "paper-variants-dvfs"):
        for accounting in ("paper", "physical"):
            p = cli("plan", scenario, "--accounting", accounting)
            what = placement(p["allocation"], local, base)
            variants = sorted(set((p.get("variants") or {}).values()))
            levels = sorted(set((p.get("levels") or {}).values()))
            detail = "; ".join(x for x in (
                f"quality {p['quality']:.2f}" if p.get("quality") is not None else "",
                what, "variants " + ", ".join(variants) if variants else "",
                "levels " + ", ".join(levels) if levels else "") if x)
            figures.append(results.figure(f"{scenario}, {accounting}", p["lifetime_s"], "s",
                                          "paper-fig7 optimum", optimum[accounting]["lifetime_s"],
                                          note="the paper's mission without variants or levels, its best static plan",
                                          group=g, detail=detail))

    g = "The team map (a DAG): the optimum of each topology"
    groups[g] = {"what": "`autopower analyze paper-teammap --json`: the paper's mission plus a TeamMap stage "
                         "merging the three localisations, against the mission without it, per topology "
                         "(802.11a everywhere).",
                 "value": "with the team map", "baseline_value": "paper-fig7",
                 "detail": "the team map's host"}
    for accounting in ("paper", "physical"):
        tm = cli("analyze", "paper-teammap", "--accounting", accounting)
        f7 = paper7 if accounting == "paper" else phys7
        f7_opt = by_label(f7["rows"], "optimal")
        for key, r in by_label(tm["rows"], "optimal").items():
            if key[1:] != ("802.11a", "802.11a"):
                continue
            figures.append(results.figure(f"{r['topology']}, {accounting} accounting", r["lifetime_s"], "s",
                                          "paper-fig7", f7_opt[key]["lifetime_s"],
                                          note="the same configuration's optimum without the team map", group=g,
                                          detail=r["allocation"].get("TeamMap", "")))
    return figures, groups


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    results.add_json_out(parser)
    args = parser.parse_args()
    figures, groups = measure()
    group = None
    for f in figures:
        if f.get("group") != group:
            group = f.get("group")
            print(f"\n== {group} ==")
            print(f"{'':44} {groups[group].get('value', 'value'):>22} {groups[group].get('baseline_value', ''):>28} "
                  f"{'ratio':>8}  {groups[group].get('detail', '')}")
        r = f"{f['ratio']:.4f}" if f["ratio"] is not None else "-"
        base = f"{f['baseline_value']:.1f}" if f["baseline_value"] is not None else "-"
        value = f"{f['value']:.1f}" if f["value"] is not None else "infeasible"
        print(f"{f['name']:44} {value:>22} {base:>28} {r:>8}  {f.get('detail', '')}")
    results.write_result("paper", {}, figures, args.json_out, what=WHAT, groups=groups)


if __name__ == "__main__":
    main()
