"""An independent INRIA-PLY reader built on plyfile, and helpers to write test PLY files.

It states SPEC §1 in numpy so tests can compare morphgs with it value for value: properties found
by name, every type cast to float32, f_rest reshaped (N,3,K) and transposed to (N,K,3), and
quaternions normalised by one float32 division by sqrt(((w*w + x*x) + y*y) + z*z) unless their
squared norm is already within 8 float32 epsilons of 1 (kept bit for bit, so load -> save -> load
is exact); a zero quaternion becomes the identity; one whose float32 squared norm overflows or is
subnormal is normalised in float64.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
from plyfile import PlyData, PlyElement

STANDARD = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
            "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
QUAT_NORM2_TOL = np.float32(8 * np.finfo(np.float32).eps)


def _is_rest(name: str) -> bool:
    return re.fullmatch(r"f_rest_[0-9]+", name) is not None


def normalise_quats(q: np.ndarray) -> np.ndarray:
    q = np.array(q, dtype=np.float32)
    w, x, y, z = q.T
    n2 = ((w * w + x * x) + y * y) + z * z
    fix = np.abs(n2 - np.float32(1)) > QUAT_NORM2_TOL
    zero = n2 == 0
    normal = np.isfinite(n2) & (n2 >= np.finfo(np.float32).tiny)
    div = fix & ~zero & normal
    q[div] = q[div] / np.sqrt(n2[div])[:, None]
    wide = fix & ~zero & ~normal & np.isfinite(q).all(axis=1)
    q64 = q[wide].astype(np.float64)
    q[wide] = (q64 / np.sqrt((q64 * q64).sum(axis=1))[:, None]).astype(np.float32)
    q[zero] = (1, 0, 0, 0)
    return q


def reference_arrays(path: str | Path) -> dict[str, Any]:
    """What morphgs.load must return for `path`, computed with plyfile and numpy."""
    v = PlyData.read(str(path))["vertex"].data
    names = list(v.dtype.names or ())

    def cols(keys: list[str]) -> np.ndarray:
        if not keys:
            return np.zeros((len(v), 0), dtype=np.float32)
        return np.stack([np.asarray(v[k]).astype(np.float32) for k in keys], axis=1)

    n_rest = sum(1 for k in names if _is_rest(k))
    k = n_rest // 3
    rest = cols([f"f_rest_{i}" for i in range(n_rest)]).reshape(len(v), 3, k)
    return {
        "means": cols(["x", "y", "z"]),
        "quats": normalise_quats(cols(["rot_0", "rot_1", "rot_2", "rot_3"])),
        "log_scales": cols(["scale_0", "scale_1", "scale_2"]),
        "opacity_logits": np.asarray(v["opacity"]).astype(np.float32),
        "sh0": cols(["f_dc_0", "f_dc_1", "f_dc_2"]),
        "sh_rest": np.ascontiguousarray(rest.transpose(0, 2, 1)),
        "sh_degree": {0: 0, 3: 1, 8: 2, 15: 3, 24: 4}[k],
        "extras": {n: np.asarray(v[n]).astype(np.float32) for n in names
                   if n not in STANDARD and not _is_rest(n)},
    }


FIELDS = ["means", "quats", "log_scales", "opacity_logits", "sh0", "sh_rest"]


def assert_scene_equals(scene: Any, ref: dict[str, Any]) -> None:
    """Bit-exact comparison of a GaussianScene with reference arrays (NaN-free data)."""
    for f in FIELDS:
        got, want = getattr(scene, f), ref[f]
        assert got.dtype == np.float32, f
        assert got.shape == want.shape, (f, got.shape, want.shape)
        np.testing.assert_array_equal(got.view(np.uint32), np.asarray(want, np.float32).view(np.uint32),
                                      err_msg=f)
    assert scene.sh_degree == ref["sh_degree"]
    assert list(scene.extras) == list(ref["extras"])
    for name, want in ref["extras"].items():
        np.testing.assert_array_equal(scene.extras[name].view(np.uint32),
                                      np.asarray(want, np.float32).view(np.uint32), err_msg=name)


def vertex_dtype(n_rest: int = 45, *, normals: bool = True, extras: tuple[str, ...] = (),
                 ftype: str = "f4") -> list[tuple[str, str]]:
    names = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals else []) + ["f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(n_rest)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    names += list(extras)
    return [(n, ftype) for n in names]


def random_vertices(n: int, dtype: list[tuple[str, str]], seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    arr = np.empty(n, dtype=dtype)
    for name, _ in dtype:
        arr[name] = rng.normal(size=n).astype(np.float32)
    return arr


def write_ply(path: str | Path, vertices: np.ndarray, *, text: bool = False, byte_order: str = "<",
              other: list[PlyElement] | None = None) -> Path:
    """Write `vertices` (a structured array) with plyfile; `other` elements go first."""
    els = list(other or []) + [PlyElement.describe(vertices, "vertex")]
    PlyData(els, text=text, byte_order=byte_order).write(str(path))
    return Path(path)


def header_bytes(props: list[str], count: int, fmt: str = "binary_little_endian 1.0",
                 element: str = "vertex") -> bytes:
    lines = ["ply", f"format {fmt}", f"element {element} {count}"]
    lines += [p if p.startswith("property") else f"property float {p}" for p in props]
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode()
