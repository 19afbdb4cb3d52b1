"""Point clouds for initialisation: COLMAP `points3D.bin` / `points3D.txt` and PLY point clouds
(`x y z` and optional `red green blue`, any numeric type, binary either endian or ASCII).

Every count a header or file claims is checked against the file size before anything is
allocated; problems are `FitDataError`s naming the file.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from morphgs.fit.data import FitDataError

__all__ = ["read_points"]

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_points(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(points (N,3) float32, colours (N,3) float32 in [0, 1]) of a point-cloud file.

    Raises:
        FileNotFoundError: no such file. FitDataError: malformed or unsupported file.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such point-cloud file")
    name = p.name.lower()
    if name.endswith(".bin"):
        return _colmap_bin(p)
    if name.endswith(".txt"):
        return _colmap_txt(p)
    if name.endswith(".ply"):
        return _ply(p)
    raise FitDataError(f"{p}: not a point cloud (points3D.bin, points3D.txt or .ply)")


def _colmap_bin(p: Path) -> tuple[np.ndarray, np.ndarray]:
    data = p.read_bytes()
    if len(data) < 8:
        raise FitDataError(f"{p}: file ends before the point count")
    (n,) = struct.unpack_from("<Q", data, 0)
    # each point takes at least 51 bytes (id, xyz, rgb, error, track length)
    if n * 51 > len(data) - 8:
        raise FitDataError(f"{p}: claims {n} points, more than the file holds")
    pts = np.empty((n, 3), np.float64)
    cols = np.empty((n, 3), np.uint8)
    off = 8
    for i in range(n):
        try:
            _, x, y, z, r, g, b, _, tl = struct.unpack_from("<Q3d3BdQ", data, off)
        except struct.error:
            raise FitDataError(f"{p}: file ends inside point {i}") from None
        off += 51 + 8 * tl
        if off > len(data):
            raise FitDataError(f"{p}: file ends inside the track of point {i}")
        pts[i] = (x, y, z)
        cols[i] = (r, g, b)
    return pts.astype(np.float32), cols.astype(np.float32) / 255.0


def _colmap_txt(p: Path) -> tuple[np.ndarray, np.ndarray]:
    pts, cols = [], []
    for ln, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        try:
            pts.append([float(v) for v in parts[1:4]])
            cols.append([int(v) for v in parts[4:7]])
        except ValueError:
            raise FitDataError(f"{p}:{ln}: expected 'POINT3D_ID X Y Z R G B ERROR TRACK...'") from None
        if len(pts[-1]) != 3 or len(cols[-1]) != 3:
            raise FitDataError(f"{p}:{ln}: expected 'POINT3D_ID X Y Z R G B ERROR TRACK...'")
    a = np.asarray(pts, np.float32).reshape(-1, 3)
    c = np.clip(np.asarray(cols, np.float32).reshape(-1, 3), 0, 255) / 255.0
    return a, c


def _ply(p: Path) -> tuple[np.ndarray, np.ndarray]:
    with open(p, "rb") as f:
        head = f.read(1 << 16)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise FitDataError(f"{p}: not a PLY file (no 'ply' magic or no end_header)")
    nl = head.find(b"\n", end)
    body_at = nl + 1 if nl >= 0 else len(head)
    lines = head[:end].decode("ascii", errors="replace").splitlines()
    fmt: str | None = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    current: tuple[str, int, list[tuple[str, str]]] | None = None
    for line in lines[1:]:
        t = line.split()
        if not t or t[0] in ("comment", "obj_info"):
            continue
        if t[0] == "format" and len(t) >= 2:
            fmt = t[1]
        elif t[0] == "element" and len(t) == 3:
            try:
                current = (t[1], int(t[2]), [])
            except ValueError:
                raise FitDataError(f"{p}: bad element line {line!r}") from None
            elements.append(current)
        elif t[0] == "property" and current is not None:
            if t[1] == "list":
                raise FitDataError(f"{p}: element '{current[0]}' has list properties; "
                                   "only plain point clouds are supported")
            if len(t) != 3 or t[1] not in _PLY_TYPES:
                raise FitDataError(f"{p}: unsupported property line {line!r}")
            current[2].append((t[2], _PLY_TYPES[t[1]]))
    if fmt not in ("binary_little_endian", "binary_big_endian", "ascii"):
        raise FitDataError(f"{p}: unsupported PLY format {fmt!r}")
    if not elements or elements[0][0] != "vertex":
        raise FitDataError(f"{p}: the first element must be 'vertex'")
    _, n, props = elements[0]
    names = [q[0] for q in props]
    for need in ("x", "y", "z"):
        if need not in names:
            raise FitDataError(f"{p}: element 'vertex' has no property '{need}'")
    if fmt == "ascii":
        text = p.read_bytes()[body_at:].decode("ascii", errors="replace").split()
        if len(text) < n * len(props):
            raise FitDataError(f"{p}: {n} vertices declared, the file holds fewer values")
        vals = np.asarray(text[:n * len(props)], np.float64).reshape(n, len(props))
        rec = {nm: vals[:, i] for i, nm in enumerate(names)}
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        dt = np.dtype([(nm, order + t) for nm, t in props])
        size = p.stat().st_size - body_at
        if n * dt.itemsize > size:
            raise FitDataError(f"{p}: {n} vertices declared, the file holds {size // max(dt.itemsize, 1)}")
        arr = np.fromfile(p, dtype=dt, count=n, offset=body_at)
        rec = {nm: arr[nm].astype(np.float64) for nm in names}
    pts = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float32)
    if all(c in rec for c in ("red", "green", "blue")):
        dtypes = dict(props)
        scale = 255.0 if dtypes["red"] in ("u1", "i1") else (65535.0 if dtypes["red"] in ("u2", "i2") else 1.0)
        cols = np.stack([rec["red"], rec["green"], rec["blue"]], axis=1) / scale
    else:
        cols = np.full((n, 3), 0.5)
    return pts, np.clip(cols, 0.0, 1.0).astype(np.float32)
