"""The benchmark scripts without a smoke test of their own still run end to end in their quick
mode and print their tables (benchmarks report; nothing here checks a time)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

BENCHES = Path(__file__).resolve().parents[1] / "benches"

CASES = {
    # script, arguments, modules it needs, a line its report must hold
    "pair": ("bench_pair.py", ["--quick"], [], "end to end (curate call)"),
    "perturb": ("bench_perturb.py", ["--quick"], [], "morphological"),
    "render": ("bench_render.py", ["--quick"], [], "useful M"),
    "data": ("bench_data.py", ["--quick"], ["torch"], "PairDataset"),
    "train": ("bench_train.py", ["--quick", "--steps", "2"], ["torch", "accelerate"], "tiny refiner training step"),
    "refiners": ("bench_refiners.py", ["--steps", "2", "--threads", "1"], ["torch", "diffusers", "peft"],
                 "sandbox"),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_bench_quick_runs(name: str) -> None:
    script, args, needs, line = CASES[name]
    for mod in needs:
        if importlib.util.find_spec(mod) is None:
            pytest.skip(f"{script} needs {mod}")
    out = subprocess.run([sys.executable, str(BENCHES / script), *args], capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-4000:]
    assert line in out.stdout + out.stderr, out.stdout[-2000:]
