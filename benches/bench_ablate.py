"""The ablation study's stage times and CPU per stage, against a baseline build: runs
`python -m morphgs ablate --preset P --out TMP -j J` in a fresh temporary folder for this
interpreter (its environment as given, so PYTHONPATH picks the checkout) and, with a baseline, the
same for the baseline build, the builds alternating over --rounds. From each run's
STUDY/runs.jsonl it prints, per stage: the jobs computed, their wall seconds summed over jobs,
their CPU seconds (user + system of the process that ran each job, all its threads; a build
without per-job CPU shows n/a) and CPU/wall; then the whole study's wall and CPU seconds (the
study process and its workers, measured from outside, so a baseline without per-job CPU has it
too). With several rounds each figure is the median over rounds. Reports; asserts nothing.

    python benches/bench_ablate.py                          # the toy preset, -j 2 (about 30 min on 2 cores)
    python benches/bench_ablate.py --preset smoke           # a quick look (about 30 s)
    python benches/bench_ablate.py --preset smoke --baseline-pythonpath ../main/python --rounds 3
    python benches/bench_ablate.py --baseline ../old/.venv/bin/python --json ablate.json

--baseline PYTHON runs another environment's interpreter (its own installed morphgs; PYTHONPATH is
cleared for it); --baseline-pythonpath DIR runs this interpreter with PYTHONPATH=DIR (another
checkout's python/ folder, with its built _core). Wall-clock times on a shared machine move with
its load: compare builds within one invocation, alternated, not across invocations.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

try:
    import resource
except ImportError:  # Windows
    resource = None  # type: ignore[assignment]


def cpu() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
        return next(line.split(":", 1)[1].strip() for line in out.splitlines() if line.startswith("Model name"))
    except (OSError, StopIteration):
        return platform.processor() or "unknown CPU"


def cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def children_cpu() -> float:
    """User + system CPU seconds of this process's ended, waited-for children so far."""
    if resource is None:
        t = os.times()
        return t.children_user + t.children_system
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def last_run(study: Path) -> dict[str, Any]:
    """The last record of a study folder's runs.jsonl."""
    lines = (study / "runs.jsonl").read_text(encoding="utf-8").splitlines()
    return dict(json.loads(next(x for x in reversed(lines) if x.strip())))


def stage_figures(rec: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per stage of one runs.jsonl record, in the order its jobs ran: {"jobs": computed jobs,
    "seconds": wall seconds summed over them, "cpu": CPU seconds summed over them (None when the
    record has no stage_cpu_seconds, as a build from before them)}. Stages that computed nothing
    are left out."""
    computed = [j for j in rec.get("jobs", []) if j.get("status") == "computed"]
    order = list(dict.fromkeys(j["stage"] for j in computed))
    walls = rec.get("stage_seconds", {})
    cpus = rec.get("stage_cpu_seconds")
    out: dict[str, dict[str, Any]] = {}
    for s in order + sorted(set(walls) - set(order)):
        out[s] = {"jobs": sum(1 for j in computed if j["stage"] == s), "seconds": float(walls.get(s, 0.0)),
                  "cpu": None if cpus is None else float(cpus.get(s, 0.0))}
    return out


def summarize(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """One build's runs ({"record": runs.jsonl record, "wall": process wall s, "cpu": process CPU
    s}) as medians over rounds: {"stages": {stage: {jobs, seconds, cpu}}, "study_seconds",
    "process_wall", "process_cpu"}."""
    per = [stage_figures(r["record"]) for r in runs]
    stages: dict[str, dict[str, Any]] = {}
    for s in dict.fromkeys(s for p in per for s in p):
        rows = [p[s] for p in per if s in p]
        cpus = [r["cpu"] for r in rows if r["cpu"] is not None]
        stages[s] = {"jobs": max(r["jobs"] for r in rows),
                     "seconds": statistics.median(r["seconds"] for r in rows),
                     "cpu": statistics.median(cpus) if len(cpus) == len(rows) else None}
    return {"stages": stages, "rounds": len(runs),
            "study_seconds": statistics.median(float(r["record"]["seconds"]) for r in runs),
            "process_wall": statistics.median(r["wall"] for r in runs),
            "process_cpu": statistics.median(r["cpu"] for r in runs)}


def _num(v: float | None, fmt: str = ".1f") -> str:
    return "n/a" if v is None else format(v, fmt)


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None or b <= 0 else a / b


def table(builds: dict[str, dict[str, Any]]) -> list[str]:
    """The report's lines for one or two summarized builds ("current", and "baseline" if run):
    per stage jobs, wall job-seconds, CPU seconds and CPU/wall of each build and, with a baseline,
    current/baseline of wall and CPU; then the totals and the whole study."""
    names = [n for n in ("baseline", "current") if n in builds]
    stages = list(dict.fromkeys(s for n in names for s in builds[n]["stages"]))
    head = f"{'stage':<12} {'jobs':>5}"
    for n in names:
        head += f" {n[:4] + ' wall':>10} {n[:4] + ' CPU':>9} {'CPU/wall':>8}"
    if len(names) == 2:
        head += f" {'wall x':>7} {'CPU x':>6}"
    lines = [head]

    def row(label: str, figs: dict[str, dict[str, Any] | None]) -> str:
        counts = [str(f["jobs"]) if f else "0" for f in figs.values()]
        jobs = counts[0] if len(set(counts)) == 1 else "/".join(counts)  # baseline/current when they differ
        line = f"{label:<12} {jobs:>5}"
        walls: dict[str, float | None] = {}
        cpus: dict[str, float | None] = {}
        for n in names:
            f = figs[n]
            walls[n], cpus[n] = (f["seconds"], f["cpu"]) if f else (None, None)
            line += f" {_num(walls[n]):>10} {_num(cpus[n]):>9} {_num(_ratio(cpus[n], walls[n]), '.2f'):>8}"
        if len(names) == 2:
            line += (f" {_num(_ratio(walls['current'], walls['baseline']), '.2f'):>7}"
                     f" {_num(_ratio(cpus['current'], cpus['baseline']), '.2f'):>6}")
        return line

    for s in stages:
        lines.append(row(s, {n: builds[n]["stages"].get(s) for n in names}))
    total: dict[str, dict[str, Any] | None] = {}
    for n in names:
        st = builds[n]["stages"].values()
        cpus = [f["cpu"] for f in st]
        total[n] = {"jobs": sum(f["jobs"] for f in st), "seconds": sum(f["seconds"] for f in st),
                    "cpu": None if None in cpus else sum(cpus)}
    lines.append(row("all jobs", total))
    for n in names:
        b = builds[n]
        lines.append(f"{n}: study {b['study_seconds']:.1f} s wall (runs.jsonl); process {b['process_wall']:.1f} s "
                     f"wall, {b['process_cpu']:.1f} s CPU ({_num(_ratio(b['process_cpu'], b['process_wall']), '.2f')} "
                     f"cores busy), median of {b['rounds']} round(s)")
    if len(names) == 2:
        w = _ratio(builds["current"]["study_seconds"], builds["baseline"]["study_seconds"])
        c = _ratio(builds["current"]["process_cpu"], builds["baseline"]["process_cpu"])
        lines.append(f"current/baseline: study wall x{_num(w, '.2f')}, process CPU x{_num(c, '.2f')}")
    return lines


def run_once(python: str, env: dict[str, str], preset: str, jobs: int) -> dict[str, Any]:
    """One study from scratch in a fresh temporary folder: its last runs.jsonl record and the
    process's wall and CPU seconds (the study process and its worker processes)."""
    with tempfile.TemporaryDirectory(prefix="morphgs-bench-ablate-") as tmp:
        study = Path(tmp) / "study"
        cmd = [python, "-m", "morphgs", "ablate", "--preset", preset, "--out", str(study), "-j", str(jobs)]
        c0, t0 = children_cpu(), time.perf_counter()
        r = subprocess.run(cmd, env=env, capture_output=True, text=True)
        wall, used = time.perf_counter() - t0, children_cpu() - c0
        if r.returncode != 0:
            raise SystemExit(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stderr[-3000:]}")
        return {"record": last_run(study), "wall": wall, "cpu": used}


def where(python: str, env: dict[str, str]) -> str:
    """The folder of the morphgs package that `python` imports in `env`."""
    r = subprocess.run([python, "-c", "import morphgs, os; print(os.path.dirname(morphgs.__file__))"], env=env,
                       capture_output=True, text=True)
    return r.stdout.strip() if r.returncode == 0 else f"(morphgs not importable: {r.stderr.strip()[-200:]})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="toy", help="toy (default) or smoke (a quick look)")
    ap.add_argument("-j", "--jobs", type=int, default=2, help="ablate -j (worker processes)")
    base = ap.add_mutually_exclusive_group()
    base.add_argument("--baseline", metavar="PYTHON", help="another environment's python with a baseline morphgs")
    base.add_argument("--baseline-pythonpath", metavar="DIR",
                      help="run this python with PYTHONPATH=DIR (another checkout's python/ folder)")
    ap.add_argument("--rounds", type=int, default=1, help="runs of each build, alternating (medians shown)")
    ap.add_argument("--json", type=Path, metavar="OUT", help="also save the figures as JSON")
    a = ap.parse_args()
    if a.baseline and not (Path(a.baseline).is_file() and os.access(a.baseline, os.X_OK)):
        ap.error(f"--baseline {a.baseline}: not an executable python (give another venv's bin/python)")
    if a.baseline_pythonpath and not (Path(a.baseline_pythonpath) / "morphgs").is_dir():
        ap.error(f"--baseline-pythonpath {a.baseline_pythonpath}: no morphgs package in it (give a checkout's "
                 "python/ folder)")
    if a.jobs < 1 or a.rounds < 1:
        ap.error("-j and --rounds must be at least 1")

    builds: dict[str, tuple[str, dict[str, str]]] = {"current": (sys.executable, dict(os.environ))}
    if a.baseline:
        env = dict(os.environ)
        env.pop("PYTHONPATH", None)
        builds["baseline"] = (a.baseline, env)
    elif a.baseline_pythonpath:
        builds["baseline"] = (sys.executable, dict(os.environ, PYTHONPATH=str(Path(a.baseline_pythonpath).resolve())))
    threads = os.environ.get("MORPHGS_NUM_THREADS")
    print(f"{cpu()}, {cores()} cores; preset {a.preset}, -j {a.jobs}, {a.rounds} round(s)"
          + (f", MORPHGS_NUM_THREADS={threads}" if threads else ""))
    for name, (py, env) in builds.items():
        print(f"{name}: {py} -> {where(py, env)}")
    runs: dict[str, list[dict[str, Any]]] = {n: [] for n in builds}
    order = list(builds)
    for i in range(a.rounds):
        for name in order if i % 2 == 0 else order[::-1]:
            py, env = builds[name]
            r = run_once(py, env, a.preset, a.jobs)
            runs[name].append(r)
            print(f"  round {i + 1} {name}: {r['record']['seconds']:.1f} s study wall", flush=True)
    figures = {n: summarize(rs) for n, rs in runs.items()}
    for line in table(figures):
        print(line)
    if a.json:
        a.json.write_text(json.dumps({"cpu": cpu(), "cores": cores(), "preset": a.preset, "jobs": a.jobs,
                                      "rounds": a.rounds, "builds": figures,
                                      "runs": {n: [{"wall": r["wall"], "cpu": r["cpu"], "record": r["record"]}
                                                   for r in rs] for n, rs in runs.items()}},
                                     indent=1, sort_keys=True) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
