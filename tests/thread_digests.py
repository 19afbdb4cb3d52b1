"""Run a test module's `digest()` in fresh processes at several thread counts (the native pool's
size is fixed per process), for the tests that pin bytes for any thread count."""

from __future__ import annotations

import os
import subprocess
import sys

TESTS = os.path.dirname(os.path.abspath(__file__))


def digests_by_threads(module: str, threads: tuple[int, ...] = (1, 2, 8)) -> dict[int, str]:
    """{threads: `module.digest()` computed in a process whose native pool has that many threads}."""
    code = (f"import sys; sys.path.insert(0, {TESTS!r}); import morphgs; from {module} import digest; "
            "print(morphgs.num_threads(), digest())")
    out = {}
    for n in threads:
        env = {**os.environ, "RAYON_NUM_THREADS": str(n)}
        env.pop("MORPHGS_NUM_THREADS", None)
        res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
        assert res.returncode == 0, res.stderr
        used, d = res.stdout.split()
        assert int(used) == n, (used, n)
        out[n] = d
    return out
