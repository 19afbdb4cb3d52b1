"""Every warning reaches a CLI user as one line `morphgs CMD: warning: ...`: MorphgsWarnings,
NumPy's RuntimeWarnings and other libraries' warnings (category first), multi-line messages, and
warnings raised in the worker processes a command spawns (`morphgs fit A B` fits in spawned
workers, where Python's format printed `file.py:NNN:` and the source line of the call)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from capture_helpers import forward_facing_cameras, room, write_transforms
from fit_helpers import small_config
from morphgs.fit import FitConfig

ENV = {**os.environ, "MORPHGS_NUM_THREADS": "1"}
ENV.pop("MORPHGS_TRACEBACK", None)
PYTHON_FORMAT = re.compile(r"\.py:\d+: |^\s")  # `file.py:NNN: Category: ...` and the indented source line


def _warning_lines(stderr: str, command: str) -> list[str]:
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    bad = [ln for ln in lines if PYTHON_FORMAT.search(ln)]
    assert not bad, stderr
    return [ln for ln in lines if ln.startswith(f"morphgs {command}: warning: ")]


def test_fit_warnings_from_spawned_workers_are_one_line(tmp_path: Path) -> None:
    scene = room(1500)
    for name in ("a", "b"):  # forward-facing captures fitted from random points: a MorphgsWarning each
        write_transforms(tmp_path / name, scene, forward_facing_cameras((32, 24), (3, 2)))
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(FitConfig.from_dict(small_config(5)).to_toml())
    r = subprocess.run([sys.executable, "-m", "morphgs", "fit", str(tmp_path / "a"), str(tmp_path / "b"), "--out",
                        str(tmp_path / "runs"), "--config", str(cfg), "--init", "random", "--no-progress"],
                       env=ENV, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    warned = _warning_lines(r.stderr, "fit")
    assert len(warned) == 2 and all("forward-facing" in ln for ln in warned), r.stderr


SCRIPT = '''
import multiprocessing as mp
import sys
import warnings

import numpy as np

import morphgs.commands.info as info
from morphgs.cli import main


def child():
    np.array([1e308]) * 10  # overflow in a worker process


def run(args):
    np.array([1e308]) * 10  # NumPy's RuntimeWarning
    warnings.warn("a note\\nspanning two lines", UserWarning)
    p = mp.get_context("spawn").Process(target=child)
    p.start()
    p.join()
    return real(args)


if __name__ == "__main__":
    real = info.run
    info.run = run
    sys.exit(main(["info", sys.argv[1]]))
'''


def test_numpy_and_library_warnings_in_the_command_and_its_workers_are_one_line(tmp_path: Path) -> None:
    import morphgs

    scene = tmp_path / "s.ply"
    morphgs.save(morphgs.synthetic.scene(50, sh_degree=0, seed=0), scene)
    script = tmp_path / "warn.py"
    script.write_text(SCRIPT)
    r = subprocess.run([sys.executable, str(script), str(scene)], env=ENV, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    warned = _warning_lines(r.stderr, "info")
    assert warned == ["morphgs info: warning: RuntimeWarning: overflow encountered in multiply",
                      "morphgs info: warning: UserWarning: a note | spanning two lines",
                      "morphgs info: warning: RuntimeWarning: overflow encountered in multiply"], r.stderr
    # for a bug report, MORPHGS_TRACEBACK=1 keeps Python's format
    r = subprocess.run([sys.executable, str(script), str(scene)], env={**ENV, "MORPHGS_TRACEBACK": "1"},
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "warn.py:" in r.stderr, r.stderr


def test_the_cli_leaves_the_warning_format_as_it_found_it(tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    import warnings

    from morphgs.cli import main

    before, env = warnings.formatwarning, os.environ.get("MORPHGS_CLI_COMMAND")
    assert main(["info", str(tmp_path / "missing.ply")]) == 1
    assert capsys.readouterr().err.startswith("morphgs info: error: ")
    assert warnings.formatwarning is before and os.environ.get("MORPHGS_CLI_COMMAND") == env
