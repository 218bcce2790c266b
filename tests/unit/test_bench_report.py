"""`./run bench --report`'s rendering (bench/report.py) from bench JSON (bench/results.py), on fixtures."""

from __future__ import annotations

import importlib.util
import json
import re
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"_bench_{name}_under_test", BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is made
    spec.loader.exec_module(module)
    return module


report = _load("report")
results = _load("results")

BENCHES = (
    report.Bench("alpha", "bench/bench_alpha.py", ("--n", "3"), "Alpha", "performance", 0.1),
    report.Bench("beta", "bench/bench_beta.py", (), "Beta", "results", 0.1, other_page=("speed",)),
    report.Bench("gamma", "bench/bench_gamma.py", (), "Gamma", "performance", 0.1, long=True),
)
MACHINE_LINE = re.compile(r"^Measured \d{4}-\d\d-\d\d \d\d:\d\d UTC on .+, \d+ cores; Python [\d.]+; .+, .+\. "
                          r"Command: `.+`")


def write_fixtures(json_dir: Path) -> None:
    alpha = [results.figure("decode", 12.5, "us", "bare msgpack", 10.0, note="the same bytes, no check"),
             results.figure("lost outputs", 0, "outputs", "outputs received", 1200, group="delivery"),
             results.figure("no baseline value", 3.0, "ms", "idle", None)]
    results.write_result("alpha", {"n": 3}, alpha, json_dir / "alpha.json", what="Alpha measures decoding.")
    beta = [results.figure("row 1", 45715.2, "s", "the paper", 45715.2, group="Fig. 7", detail="all on the laptop"),
            results.figure("rebalance", 43008.9, "s", "static optimum", 41820.3, group="policies",
                           also=[("time-sharing bound", 43008.9, "the upper bound")]),
            results.figure("rebalance", 509.0, "h/s", "static", 2333.0, group="speed")]
    results.write_result("beta", {}, beta, json_dir / "beta.json", what="Beta reproduces the paper.",
                         groups={"Fig. 7": {"value": "AutoPower", "baseline_value": "the paper's Fig. 7"},
                                 "policies": {"also": ["time-sharing bound"], "also_ratio": ["/ bound"]}})
    # the two runs on different days: each table keeps its own
    doc = json.loads((json_dir / "beta.json").read_text())
    doc["date_utc"] = "2026-01-02T03:04:05Z"
    (json_dir / "beta.json").write_text(json.dumps(doc))


def sections(text: str) -> dict[str, str]:
    out = {}
    for part in re.split(r"^### ", text, flags=re.M)[1:]:
        title, _, body = part.partition("\n")
        out[title] = body
    return out


def table_rows(body: str) -> list[list[str]]:
    """Every table's rows (header included, separator left out), cells stripped."""
    rows = []
    for line in body.splitlines():
        if line.startswith("|") and not line.startswith("|---"):
            rows.append([c.strip() for c in re.split(r"(?<!\\)\|", line)[1:-1]])
    return rows


@pytest.fixture
def rendered(tmp_path):
    json_dir, out_dir = tmp_path / "bench", tmp_path / "generated"
    json_dir.mkdir()
    write_fixtures(json_dir)
    report.render(json_dir, out_dir, BENCHES)
    return {page: (out_dir / name).read_text() for page, name in report.PAGES.items()}


def test_every_table_says_the_machine_and_the_date_of_its_own_run(rendered):
    seen = 0
    for page, text in rendered.items():
        assert not text.startswith("---"), "no front matter: the pages include these files"
        for title, body in sections(text).items():
            if "|---" not in body:
                continue
            seen += 1
            lines = [line for line in body.splitlines() if MACHINE_LINE.match(line)]
            assert len(lines) == 1, (page, title, body)
            assert "AMD" in lines[0] or "cores" in lines[0]
    assert seen == 3  # alpha; beta on the results page and its "speed" group on the performance page
    beta = sections(rendered["results"])["Beta"]
    assert "Measured 2026-01-02 03:04 UTC" in beta
    assert "Measured 2026-01-02 03:04 UTC" not in sections(rendered["performance"])["Alpha"]


def test_every_figure_row_has_its_baseline_and_ratio(rendered):
    rows_seen = 0
    for text in rendered.values():
        for body in sections(text).values():
            for block in body.split("\n\n"):
                rows = table_rows(block)
                if not rows:
                    continue
                header, *data = rows
                assert "ratio" in header or "/ static" in header or any(h.startswith("/") for h in header)
                for row in data:
                    rows_seen += 1
                    assert len(row) == len(header), (header, row)
                    value_cols = [i for i, h in enumerate(header) if h == "ratio" or h.startswith("/ ")]
                    for i in value_cols:
                        assert row[i], (header, row)  # a ratio, or "–" when the baseline is 0 or unknown
                        assert row[i - 1], (header, row)  # the baseline value beside it
    assert rows_seen == 6
    perf = rendered["performance"]
    assert "| decode | 12.50 us | bare msgpack | 10.00 us | 1.2500 |" in perf
    assert "| lost outputs | 0 outputs | outputs received | 1,200 outputs | 0 |" in perf
    assert "| no baseline value | 3.000 ms | idle | – | – |" in perf
    assert "*bare msgpack*: the same bytes, no check" in perf
    res = rendered["results"]
    # a group whose header names its one baseline leaves the baseline column out
    assert "| figure | AutoPower | the paper's Fig. 7 | ratio | detail |" in res
    assert "| row 1 | 45,715.2 s | 45,715.2 s | 1.0000 | all on the laptop |" in res
    assert "| rebalance | 43,008.9 s | static optimum | 41,820.3 s | 1.0284 | 43,008.9 s | 1.0000 |" in res
    assert "| time-sharing bound | / bound |" in res
    # a group shown on the other page: there, not here
    assert "h/s" in perf and "h/s" not in res


def test_a_bench_never_run_is_reported_as_not_run(rendered):
    gamma = sections(rendered["performance"])["Gamma"]
    assert "Not run yet" in gamma and "--only gamma" in gamma and "--long" in gamma


def test_malformed_json_is_an_error_naming_the_file(tmp_path, capsys):
    json_dir, out_dir = tmp_path / "bench", tmp_path / "generated"
    json_dir.mkdir()
    write_fixtures(json_dir)
    report.render(json_dir, out_dir, BENCHES)
    before = {p.name: p.read_text() for p in out_dir.iterdir()}
    bad = json_dir / "alpha.json"
    bad.write_text('{"bench": "alpha", "figures": [')
    with pytest.raises(report.ReportError, match=re.escape(str(bad))):
        report.render(json_dir, out_dir, BENCHES)
    assert {p.name: p.read_text() for p in out_dir.iterdir()} == before  # neither page half-written
    bad.write_text(json.dumps({"bench": "alpha", "date_utc": "x", "machine": {}, "figures": [{"name": "a"}]}))
    with pytest.raises(report.ReportError, match=r"alpha\.json: figure 0 lacks value, unit, baseline"):
        report.load_result(bad)
    bad.write_text("[]")
    with pytest.raises(report.ReportError, match=r"alpha\.json"):
        report.load_result(bad)
    # the command says so and exits non-zero, without a traceback
    (json_dir / "codec.json").write_text("{not json")
    code = report.main(["--render-only", "--json-dir", str(json_dir), "--out-dir", str(out_dir)])
    assert code == 2
    assert f"error: {json_dir / 'codec.json'}: not readable JSON" in capsys.readouterr().err


def test_write_result_schema_and_json_out(tmp_path, monkeypatch):
    path = tmp_path / "x.json"
    doc = results.write_result("x", {"k": 1}, [results.figure("f", float("nan"), "s", "b", 2.0)], path, what="What.")
    on_disk = json.loads(path.read_text())
    assert on_disk == doc
    assert on_disk["schema"] == results.SCHEMA and on_disk["bench"] == "x" and on_disk["params"] == {"k": 1}
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", on_disk["date_utc"])
    assert {"cpu", "cores", "python", "os", "kernel"} <= set(on_disk["machine"])
    f = on_disk["figures"][0]
    assert f["value"] is None and f["ratio"] is None  # NaN is not JSON
    assert results.figure("f", 3.0, "s", "b", 2.0)["ratio"] == 1.5
    assert results.figure("f", 3.0, "s", "b", 0)["ratio"] is None
    assert results.write_result("x", {}, [], None, what="w")["bench"] == "x"  # nothing written without a path
    argv = ["bench_x.py", "7", "--json-out", "out.json", "--big"]
    assert results.pop_json_out(argv) == "out.json" and argv == ["bench_x.py", "7", "--big"]
    monkeypatch.setenv(results.ENV, "env.json")
    assert results.pop_json_out(["bench_x.py"]) == "env.json"


def test_every_listed_bench_writes_its_json():
    for bench in report.BENCHES:
        source = (BENCH.parent / bench.script).read_text()
        assert "write_result(" in source, bench.script
        assert f'"{bench.name}"' in source, (bench.script, bench.name)
    assert len({b.name for b in report.BENCHES}) == len(report.BENCHES)
