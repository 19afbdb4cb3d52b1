"""benches/bench_ablate.py's reading of runs.jsonl and its table, on hand-written records (the
parser and the arithmetic, not timings: benchmarks report, tests check no time)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from types import ModuleType

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benches" / "bench_ablate.py"


def _bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_ablate", BENCH)
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _job(stage: str, name: str, status: str, secs: float, cpu: float | None = None) -> dict:
    j = {"stage": stage, "name": name, "key": "0" * 16, "status": status, "seconds": secs}
    if cpu is not None:
        j["cpu_seconds"] = cpu
    return j


CURRENT = {
    "time": "2026-12-01T10:00:00", "workers": 2, "seconds": 12.5,
    "counts": {"captures": {"computed": 2, "reused": 0}, "training": {"computed": 1, "reused": 0},
               "report": {"computed": 0, "reused": 1}},
    "stage_seconds": {"captures": 3.0, "training": 8.0},
    "stage_cpu_seconds": {"captures": 1.5, "training": 16.0},
    "jobs": [_job("captures", "a", "computed", 1.0, 0.5), _job("captures", "b", "computed", 2.0, 1.0),
             _job("training", "t", "computed", 8.0, 16.0), _job("report", "report", "reused", 0.0)],
}
# a build from before CPU seconds were logged
BASELINE = {
    "time": "2026-12-01T09:00:00", "workers": 2, "seconds": 25.0,
    "counts": {"captures": {"computed": 2, "reused": 0}, "training": {"computed": 1, "reused": 0}},
    "stage_seconds": {"captures": 4.0, "training": 16.0},
    "jobs": [_job("captures", "a", "computed", 2.0), _job("captures", "b", "computed", 2.0),
             _job("training", "t", "computed", 16.0)],
}


def test_the_last_record_of_runs_jsonl_and_its_stage_figures(tmp_path: Path) -> None:
    b = _bench()
    (tmp_path / "runs.jsonl").write_text(json.dumps(BASELINE) + "\n" + json.dumps(CURRENT) + "\n\n")
    rec = b.last_run(tmp_path)
    assert rec["seconds"] == 12.5
    assert b.stage_figures(rec) == {"captures": {"jobs": 2, "seconds": 3.0, "cpu": 1.5},
                                    "training": {"jobs": 1, "seconds": 8.0, "cpu": 16.0}}
    assert b.stage_figures(BASELINE)["training"] == {"jobs": 1, "seconds": 16.0, "cpu": None}


def test_rounds_are_medians_and_the_table_compares_the_builds() -> None:
    b = _bench()
    slower = json.loads(json.dumps(CURRENT))
    slower["seconds"], slower["stage_seconds"]["training"], slower["stage_cpu_seconds"]["training"] = 30.0, 20.0, 30.0
    cur = b.summarize([{"record": CURRENT, "wall": 13.0, "cpu": 20.0}, {"record": slower, "wall": 31.0, "cpu": 40.0},
                       {"record": CURRENT, "wall": 14.0, "cpu": 21.0}])
    assert cur["stages"]["training"] == {"jobs": 1, "seconds": 8.0, "cpu": 16.0}
    assert (cur["study_seconds"], cur["process_wall"], cur["process_cpu"], cur["rounds"]) == (12.5, 14.0, 21.0, 3)
    base = b.summarize([{"record": BASELINE, "wall": 21.0, "cpu": 22.0}])
    lines = b.table({"current": cur, "baseline": base})
    rows = {ln.split()[0]: ln.split()[1:] for ln in lines[1:]}
    # jobs | base wall, CPU, CPU/wall | current wall, CPU, CPU/wall | wall x, CPU x
    assert rows["captures"] == ["2", "4.0", "n/a", "n/a", "3.0", "1.5", "0.50", "0.75", "n/a"]
    assert rows["training"] == ["1", "16.0", "n/a", "n/a", "8.0", "16.0", "2.00", "0.50", "n/a"]
    assert rows["all"] == ["jobs", "3", "20.0", "n/a", "n/a", "11.0", "17.5", "1.59", "0.55", "n/a"]
    assert "current/baseline: study wall x0.50, process CPU x0.95" in lines
    alone = b.table({"current": cur})
    assert alone[0].split() == ["stage", "jobs", "curr", "wall", "curr", "CPU", "CPU/wall"]
    assert alone[1].split() == ["captures", "2", "3.0", "1.5", "0.50"]
    assert not any(ln.startswith("current/baseline") for ln in alone)


@pytest.mark.parametrize("missing", ["current", "baseline"])
def test_a_stage_only_one_build_computed_shows_both_job_counts(missing: str) -> None:
    b = _bench()
    extra = json.loads(json.dumps(CURRENT))
    extra["stage_seconds"]["pairfits"], extra["stage_cpu_seconds"]["pairfits"] = 5.0, 4.0
    extra["jobs"].append(_job("pairfits", "p", "computed", 5.0, 4.0))
    builds = {"current": extra, "baseline": BASELINE} if missing == "baseline" else \
        {"current": CURRENT, "baseline": {**extra, "stage_cpu_seconds": None}}
    figs = {n: b.summarize([{"record": r, "wall": 1.0, "cpu": 1.0}]) for n, r in builds.items()}
    row = next(ln for ln in b.table(figs) if ln.startswith("pairfits")).split()
    assert row[1] == ("0/1" if missing == "baseline" else "1/0")
