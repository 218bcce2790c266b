"""Run the benches and write the documentation's tables from their JSON: `./run bench --report`.

    ./run bench --report [--long] [--only NAME ...] [--render-only] [--list]

Each bench in the list below runs in turn (never two at once: they measure the machine), writes
its figures to docs/generated/bench/NAME.json (`bench/results.py`), and then the two pages'
tables are written from whatever JSON is there:

- docs/generated/results-figures.md: the paper's results from the product itself, the planner
  and the policies;
- docs/generated/performance-figures.md: one table per bench, each figure beside its baseline.

The default set finishes in about a quarter of an hour on a 2-core machine; ``--long`` adds the
benches that run the whole mission, random faults, live policies and floods. A bench that is not
run keeps its last JSON, and its table keeps that run's date and machine. A bench that fails
keeps its last JSON too (the command then exits 1, after rendering). The pages are overwritten
every time: how a figure moved is in git's history of these files.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GENERATED = ROOT / "docs" / "generated"
JSON_DIR = GENERATED / "bench"
PAGES = {"results": "results-figures.md", "performance": "performance-figures.md"}
REQUIRED = ("bench", "date_utc", "machine", "figures")
FIGURE_KEYS = ("name", "value", "unit", "baseline", "baseline_value", "ratio")


@dataclass(frozen=True)
class Bench:
    name: str  # the JSON's name, and --only's
    script: str
    args: tuple[str, ...]
    title: str
    page: str  # "results" or "performance"
    minutes: float  # what it takes on a quiet 2-core machine (an estimate)
    long: bool = False
    other_page: tuple[str, ...] = field(default=())  # groups shown on the other page


# The workloads are the hardest realistic ones that fit: every robot loaded, the relay topology
# where a bench can choose, the paper's whole mission where it runs a team.
BENCHES = (
    Bench("paper", "bench/bench_paper.py", (), "The paper's results, reproduced", "results", 0.3),
    Bench("planner", "bench/bench_planner.py", ("--big",), "Planner: MILP against greedy", "results", 1.0),
    Bench("policies", "bench/bench_policies.py", (), "Policies: simulated lifetimes", "results", 0.5,
          other_page=("Simulator speed",)),
    Bench("components", "bench/bench_components.py", ("200",), "Components on this machine", "performance", 0.1),
    Bench("codec", "bench/bench_codec.py", (), "Strict codec", "performance", 0.1),
    Bench("custody", "bench/bench_custody.py", (), "Custody", "performance", 0.2),
    Bench("hot_path", "bench/bench_hot_path.py", ("--virtual-s", "300"), "Hot path", "performance", 0.3),
    Bench("recording", "bench/bench_recording.py", (), "Recording", "performance", 0.5),
    Bench("stage_worker_cpu", "bench/bench_stage_worker_cpu.py", (), "Stage workers", "performance", 0.1),
    Bench("loading", "bench/bench_loading.py", ("250", "2000"), "Scenario loading", "performance", 0.2),
    Bench("overload", "bench/bench_overload.py", (), "An overloaded receiver", "performance", 0.5),
    Bench("relay", "bench/bench_relay.py", ("400",), "One relay hop", "performance", 0.5),
    Bench("runtime", "bench/bench_runtime.py", ("overhead", "migration"), "Runtime", "performance", 0.5),
    Bench("security", "bench/bench_security.py", (), "Security", "performance", 0.3),
    Bench("sim", "bench/bench_sim.py", ("--seeds", "4", "--jobs", "2"), "The simulated team", "performance", 1.0),
    Bench("sim_fleet", "bench/bench_sim_fleet.py", ("--robots", "3,10,30,100"), "The simulated team at fleet size",
          "performance", 6.0),
    Bench("detector", "bench/bench_detector.py", (), "Failure detection on lossy links", "performance", 7.0),
    Bench("lossy_links", "bench/bench_lossy_links.py", ("--frames", "40"), "Throughput under loss", "performance",
          2.5),
    Bench("faults", "bench/bench_faults.py", ("--cuts", "20"), "Faults", "performance", 2.5),
    Bench("idle", "bench/bench_idle.py", ("--seconds", "20"), "At rest", "performance", 1.4),
    Bench("control_plane", "bench/bench_control_plane.py", ("--seconds", "20"),
          "The runtime's own cost: control-plane bytes and CPU", "performance", 1.2),
    Bench("zenoh_floor", "bench/bench_zenoh_floor.py", ("--seconds", "10", "--team"), "Zenoh's floor",
          "performance", 1.5),
    Bench("live_speed", "bench/bench_live_speed.py", ("--speeds", "55,100", "--seconds", "15"), "Live speed",
          "performance", 2.3),
    # --long
    Bench("live_policies", "bench/bench_live_policies.py", ("--topology", "relay", "--energy-scale", "0.01"),
          "Policies, live", "results", 2.0, long=True),
    Bench("detector_testbed", "bench/bench_detector_testbed.py", ("--minutes", "10"),
          "Failure detection on lossy links, in the testbed", "performance", 36.0, long=True),
    Bench("detector_testbed_quic", "bench/bench_detector_testbed.py", ("--minutes", "10", "--transport", "quic"),
          "Failure detection on lossy links, in the testbed, over QUIC", "performance", 36.0, long=True),
    Bench("random_faults", "bench/bench_random_faults.py", ("--seed", "1", "--faults", "20"), "Random faults",
          "performance", 2.5, long=True),
    Bench("flood", "bench/bench_flood.py", ("--messages", "4000", "16000"), "A flood of garbage", "performance",
          2.0, long=True),
    Bench("whole_mission", "bench/bench_whole_mission.py", ("--speed", "55", "--control-plane"), "The whole mission live",
          "performance", 15.0, long=True),
    Bench("fleet", "bench/bench_fleet.py", ("--robots", "3,10,20,30,50", "--seconds", "30"), "Live fleets",
          "performance", 5.0, long=True),
)
BY_NAME = {b.name: b for b in BENCHES}


class ReportError(Exception):
    pass


# -------------------------------------------------------------------------------------------------
# reading
# -------------------------------------------------------------------------------------------------


def load_result(path: Path) -> dict | None:
    """A bench's JSON, checked; None when the bench never wrote one. Raises ReportError naming the file."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ReportError(f"{path}: not readable JSON ({exc})") from exc
    if not isinstance(doc, dict):
        raise ReportError(f"{path}: a bench result is a JSON object, not {type(doc).__name__}")
    missing = [k for k in REQUIRED if k not in doc]
    if missing:
        raise ReportError(f"{path}: missing {', '.join(missing)}")
    if not isinstance(doc["figures"], list) or not isinstance(doc["machine"], dict):
        raise ReportError(f"{path}: 'figures' must be a list and 'machine' an object")
    for i, f in enumerate(doc["figures"]):
        if not isinstance(f, dict) or any(k not in f for k in FIGURE_KEYS):
            keys = ", ".join(k for k in FIGURE_KEYS if not isinstance(f, dict) or k not in f)
            raise ReportError(f"{path}: figure {i} lacks {keys}")
    return doc


# -------------------------------------------------------------------------------------------------
# writing
# -------------------------------------------------------------------------------------------------


def number(x, unit: str = "") -> str:
    if x is None:
        return "–"
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        text = str(x)
    elif isinstance(x, float) and not math.isfinite(x):
        return "–"
    elif isinstance(x, int):
        text = f"{x:,}"
    else:
        a = abs(x)
        text = (f"{x:,.1f}" if a >= 100 else f"{x:.2f}" if a >= 10 else f"{x:.3f}" if a >= 0.1
                else "0" if a == 0 else f"{x:.3g}")
    return f"{text} {unit}".strip() if unit else text


def ratio_text(r) -> str:
    if r is None or not isinstance(r, (int, float)) or isinstance(r, bool) or not math.isfinite(r):
        return "–"
    a = abs(r)
    if a == 0:
        return "0"
    return f"{r:,.0f}" if a >= 100 else f"{r:.1f}" if a >= 10 else f"{r:.4f}" if a >= 0.01 else f"{r:.2e}"


def cell(text) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def machine_line(doc: dict) -> str:
    m = doc.get("machine") or {}
    try:
        when = datetime.strptime(doc["date_utc"], "%Y-%m-%dT%H:%M:%SZ").strftime("%Y-%m-%d %H:%M UTC")
    except (TypeError, ValueError):
        when = f"{doc.get('date_utc')} UTC"
    cores = m.get("cores")
    parts = [m.get("cpu") or "unknown CPU"]
    text = f"{parts[0]}, {cores} cores" if cores else parts[0]
    text += f"; Python {m.get('python', '?')}; {m.get('os', '?')}, {m.get('kernel', '?')}"
    command = shlex.join(doc.get("command") or []) or "?"
    took = doc.get("duration_s")
    return (f"Measured {when} on {text}. Command: `{command}`"
            + (f" ({took:.0f} s)." if isinstance(took, (int, float)) else "."))


def groups_of(doc: dict) -> list[tuple[str, list[dict]]]:
    order: dict[str, list[dict]] = {}
    for f in doc["figures"]:
        order.setdefault(f.get("group") or "", []).append(f)
    return list(order.items())


def table(figures: list[dict], headers: dict) -> list[str]:
    """figure | value | baseline | baseline value | ratio [| more baselines and ratios] [| detail].

    A group whose headers name its baseline (``baseline_value``) and that has one baseline leaves
    out the baseline column: its header says it. More baselines (a figure's ``also``) are columns
    of their own, headed by ``also`` (one header per extra baseline) or by the baseline's name.
    """
    detail = any(f.get("detail") for f in figures)
    named = "baseline_value" in headers and len({f["baseline"] for f in figures}) == 1
    more = max((len(f.get("also") or ()) for f in figures), default=0)
    also_heads = list(headers.get("also") or [])
    head = [headers.get("name", "figure"), headers.get("value", "value")]
    head += [] if named else [headers.get("baseline", "baseline")]
    head += [headers.get("baseline_value", "baseline value"), headers.get("ratio", "ratio")]
    for i in range(more):
        name = also_heads[i] if i < len(also_heads) else next(
            (f["also"][i]["baseline"] for f in figures if len(f.get("also") or ()) > i), "baseline")
        ratio_heads = list(headers.get("also_ratio") or [])
        head += [name, ratio_heads[i] if i < len(ratio_heads) else "ratio"]
    if detail:
        head.append(headers.get("detail", "detail"))
    lines = ["| " + " | ".join(cell(h) for h in head) + " |", "|" + "---|" * len(head)]
    for f in figures:
        unit = f.get("unit", "")
        row = [f["name"], number(f["value"], unit)]
        row += [] if named else [f["baseline"]]
        row += [number(f["baseline_value"], f.get("baseline_unit", unit)), ratio_text(f["ratio"])]
        also = list(f.get("also") or ())
        for i in range(more):
            row += ([number(also[i].get("baseline_value"), unit), ratio_text(also[i].get("ratio"))]
                    if i < len(also) else ["–", "–"])
        if detail:
            row.append(f.get("detail") or "")
        lines.append("| " + " | ".join(cell(c) for c in row) + " |")
    notes: dict[str, str] = {}
    for f in figures:
        for b in [f, *(f.get("also") or ())]:
            if b.get("baseline_note"):
                notes.setdefault(b["baseline"], b["baseline_note"])
    if notes:
        lines += ["", "Baselines: " + "; ".join(f"*{cell(b)}*: {cell(n)}" for b, n in notes.items()) + "."]
    return lines


def section(bench: Bench, doc: dict | None, page: str) -> list[str]:
    """The Markdown of one bench on one page: its heading, what it measures, its run, its tables."""
    out = [f"### {bench.title}", ""]
    if doc is None:
        return out + [f"_Not run yet: `./run bench --report --only {bench.name}`"
                      + (" (a `--long` bench)" if bench.long else "") + "._", ""]
    shown = [(g, fs) for g, fs in groups_of(doc) if (bench.page == page) != (g in bench.other_page)]
    if not shown:
        return []
    if doc.get("what"):
        out += [doc["what"], ""]
    out += [machine_line(doc), ""]
    headers = doc.get("groups") or {}
    for name, figures in shown:
        meta = headers.get(name) or {}
        if name:
            out += [f"#### {name}", ""]
            if meta.get("what"):
                out += [meta["what"], ""]
        if figures:
            out += table(figures, meta) + [""]
    return out


def render_page(page: str, json_dir: Path = JSON_DIR, benches=BENCHES) -> str:
    """One page's Markdown: each bench of the page, then the groups other benches show here."""
    lines = []
    for bench in [b for b in benches if b.page == page] + [b for b in benches if b.page != page and b.other_page]:
        doc = load_result(Path(json_dir) / f"{bench.name}.json")
        if bench.page != page and doc is None:
            continue
        lines += section(bench, doc, page)
    while lines and lines[-1] == "":
        lines.pop()
    return "\n".join(lines) + "\n"


def render(json_dir: Path = JSON_DIR, out_dir: Path = GENERATED, benches=BENCHES) -> list[Path]:
    """Write both pages (every JSON is read first: a bad file changes neither page)."""
    texts = {page: render_page(page, json_dir, benches) for page in PAGES}
    written = []
    for page, text in texts.items():
        path = Path(out_dir) / PAGES[page]
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        written.append(path)
    return written


# -------------------------------------------------------------------------------------------------
# running
# -------------------------------------------------------------------------------------------------


def run_bench(bench: Bench, json_dir: Path) -> tuple[bool, float]:
    """Run one bench (its output goes to the terminal); its JSON replaces the last only if it succeeded."""
    json_dir.mkdir(parents=True, exist_ok=True)
    final = json_dir / f"{bench.name}.json"
    fresh = json_dir / f"{bench.name}.json.new"
    fresh.unlink(missing_ok=True)
    cmd = [sys.executable, bench.script, *bench.args, "--json-out", str(fresh)]
    print(f"\n===== {bench.name}: {' '.join([bench.script, *bench.args])} (about {bench.minutes:g} min)", flush=True)
    started = time.monotonic()
    try:
        done = subprocess.run(cmd, cwd=ROOT, env={**os.environ, "RERUN_ANALYTICS": "0"},
                              timeout=max(600.0, bench.minutes * 60 * 4))
        ok = done.returncode == 0
        why = f"exit status {done.returncode}"
    except subprocess.TimeoutExpired:
        ok, why = False, "timed out"
    took = time.monotonic() - started
    if ok:
        try:
            if load_result(fresh) is None:
                ok, why = False, "it wrote no JSON"
        except ReportError as exc:
            ok, why = False, str(exc)
    if ok:
        fresh.replace(final)
    else:
        fresh.unlink(missing_ok=True)
        print(f"===== {bench.name} FAILED ({why}); its last JSON is kept", flush=True)
    return ok, took


def selected(args) -> list[Bench]:
    if args.only:
        unknown = [n for n in args.only if n not in BY_NAME]
        if unknown:
            raise SystemExit(f"unknown bench {', '.join(unknown)}; known: {', '.join(BY_NAME)}")
        return [BY_NAME[n] for n in args.only]
    return [b for b in BENCHES if args.long or not b.long]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="./run bench --report", description=__doc__.splitlines()[0])
    ap.add_argument("--long", action="store_true", help="also run the long benches (whole mission, random faults, "
                                                        "live policies, flood)")
    ap.add_argument("--only", nargs="+", metavar="NAME", help="run only these benches (then render everything)")
    ap.add_argument("--render-only", action="store_true", help="run nothing: write the pages from the JSON there is")
    ap.add_argument("--list", action="store_true", help="print the benches, their arguments and their time")
    ap.add_argument("--json-dir", type=Path, default=JSON_DIR, help=argparse.SUPPRESS)
    ap.add_argument("--out-dir", type=Path, default=GENERATED, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.list:
        for long in (False, True):
            chosen = [b for b in BENCHES if b.long == long]
            print(f"{'--long' if long else 'default'} set, about {sum(b.minutes for b in chosen):.0f} min:")
            for b in chosen:
                print(f"  {b.name:17} ~{b.minutes:4.1f} min  {' '.join([b.script, *b.args])}")
        return 0
    failed = []
    if not args.render_only:
        benches = selected(args)
        print(f"running {len(benches)} benches one after the other, about "
              f"{sum(b.minutes for b in benches):.0f} min: {', '.join(b.name for b in benches)}", flush=True)
        times = {}
        for bench in benches:
            ok, times[bench.name] = run_bench(bench, args.json_dir)
            if not ok:
                failed.append(bench.name)
        print("\n" + "\n".join(f"  {n:17} {t / 60:5.1f} min{'  FAILED' if n in failed else ''}"
                               for n, t in times.items()))
    try:
        for path in render(args.json_dir, args.out_dir):
            print(f"wrote {path.relative_to(ROOT) if path.is_relative_to(ROOT) else path}")
    except ReportError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if failed:
        print(f"failed: {', '.join(failed)} (their last JSON, if any, is what the pages show)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
