"""Decode speed of morphgs.load against a vectorised NumPy decoder of the same format.

Cases: the real SuperSplat capture playcanvas_engine_guitar.compressed.ply (90,854 splats), a
1M-splat .spz v3 (SH degree 3) written by morphgs.save_spz from random data, the real PlayCanvas
SOG playcanvas_engine_monkey_0001.sog (31,658 splats; the NumPy side decodes its WebP textures
with Pillow/libwebp), a glTF KHR_gaussian_splatting .glb and a SceneSplat .npy folder of the
random scene. Each NumPy decoder is checked against morphgs before timing (max abs difference
printed). A second table times the writers (no NumPy peer). Times are the best of --repeat runs,
in milliseconds.

    python benches/bench_formats.py            # full sizes (< 1 minute on 2 cores)
    python benches/bench_formats.py --quick    # smoke check: tiny sizes
"""

from __future__ import annotations

import argparse
import gzip
import os
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

import morphgs

C0 = 0.28209479177387814
REPO = Path(__file__).resolve().parents[1]
FIXTURES = Path(os.environ.get("MORPHGS_FIXTURES", REPO / "tests" / "fixtures"))

_PLY_TYPES = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4",
              "uint": "u4", "float": "f4", "double": "f8", "int8": "i1", "uint8": "u1",
              "int16": "i2", "uint16": "u2", "int32": "i4", "uint32": "u4",
              "float32": "f4", "float64": "f8"}


def _logit_u8(a: np.ndarray) -> np.ndarray:
    p = np.clip(a.astype(np.float32) / 255.0, 1e-6, 1 - 1e-6)
    return np.log(p / (1 - p))


def numpy_compressed_ply(path: Path) -> dict[str, np.ndarray]:
    """Vectorised decoder of a little-endian SuperSplat compressed PLY."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in data[:end].decode().splitlines():
        w = line.split()
        if w[:1] == ["element"]:
            elements.append((w[1], int(w[2]), []))
        elif w[:1] == ["property"]:
            elements[-1][2].append((w[2], "<" + _PLY_TYPES[w[1]]))
    tables: dict[str, np.ndarray] = {}
    off = end
    for name, count, props in elements:
        dt = np.dtype(props)
        tables[name] = np.frombuffer(data, dtype=dt, count=count, offset=off)
        off += dt.itemsize * count
    ch, v = tables["chunk"], tables["vertex"]
    n = len(v)
    ci = np.arange(n) // 256

    def unorm(x: np.ndarray, bits: int) -> np.ndarray:
        m = (1 << bits) - 1
        return (x & m).astype(np.float32) / np.float32(m)

    def lerp(lo: str, hi: str, t: np.ndarray) -> np.ndarray:
        a, b = ch[lo][ci], ch[hi][ci]
        return a * (1 - t) + b * t

    def p111011(x: np.ndarray) -> list[np.ndarray]:
        return [unorm(x >> 21, 11), unorm(x >> 11, 10), unorm(x, 11)]

    pp, ps = p111011(v["packed_position"]), p111011(v["packed_scale"])
    means = np.stack([lerp(f"min_{a}", f"max_{a}", t) for a, t in zip("xyz", pp)], axis=1)
    log_scales = np.stack(
        [lerp(f"min_scale_{a}", f"max_scale_{a}", t) for a, t in zip("xyz", ps)], axis=1)
    r = v["packed_rotation"]
    norm = np.float32(np.sqrt(2.0))
    abc = np.stack([(unorm(r >> s, 10) - 0.5) * norm for s in (20, 10, 0)], axis=1)
    m = np.sqrt(np.maximum(0, 1 - (abc * abc).sum(axis=1)))
    which = (r >> 30).astype(np.int64)
    quats = np.empty((n, 4), np.float32)
    slots = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[which]
    rows = np.arange(n)[:, None]
    quats[rows, slots] = abc
    quats[np.arange(n), which] = m
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    c = v["packed_color"]
    rgb = np.stack([unorm(c >> s, 8) for s in (24, 16, 8)], axis=1)
    if "min_r" in ch.dtype.names:
        rgb = np.stack([lerp(f"min_{a}", f"max_{a}", rgb[:, i]) for i, a in enumerate("rgb")], 1)
    out = {"means": means, "log_scales": log_scales, "quats": quats,
           "sh0": (rgb - 0.5) / np.float32(C0), "opacity_logits": _logit_u8(c & 0xFF)}
    if "sh" in tables:
        sh = tables["sh"]
        raw = np.stack([sh[f"f_rest_{i}"] for i in range(len(sh.dtype.names))], axis=1)
        val = np.where(raw == 0, 0.0, np.where(raw == 255, 1.0, (raw + 0.5) / 256.0))
        k = raw.shape[1] // 3
        out["sh_rest"] = ((val - 0.5) * 8).astype(np.float32).reshape(n, 3, k).transpose(0, 2, 1)
    return out


def numpy_spz(path: Path) -> dict[str, np.ndarray]:
    """Vectorised decoder of a gzip .spz v2/v3, converted to RDF axes like morphgs.load."""
    raw = gzip.decompress(path.read_bytes())
    magic, version, n, degree, fb = np.frombuffer(raw[:14], dtype="<u4", count=3).tolist() + [
        raw[12], raw[13]]
    assert magic == 0x5053474E and version in (2, 3)
    k = (degree + 1) ** 2 - 1
    buf = np.frombuffer(raw, dtype=np.uint8, offset=16)
    off = 0

    def take(size: int) -> np.ndarray:
        nonlocal off
        a = buf[off:off + size]
        off += size
        return a

    p = take(9 * n).reshape(n, 3, 3).astype(np.int32)
    fixed = p[..., 0] | (p[..., 1] << 8) | (p[..., 2] << 16)
    fixed = (fixed << 8) >> 8  # sign-extend 24 bits
    means = fixed.astype(np.float32) / np.float32(1 << fb)
    alphas = take(n)
    colors = take(3 * n).reshape(n, 3)
    scales = take(3 * n).reshape(n, 3)
    if version == 2:
        xyz = take(3 * n).reshape(n, 3).astype(np.float32) / np.float32(127.5) - 1
        w = np.sqrt(np.maximum(0, 1 - (xyz * xyz).sum(axis=1)))
        xyzw = np.concatenate([xyz, w[:, None]], axis=1)
    else:
        comp = take(4 * n).view("<u4").astype(np.uint32)
        largest = (comp >> 30).astype(np.int64)
        # the three stored components, from the lowest bits up: highest index first
        vals = np.stack([(comp >> (10 * j)) & 0x3FF for j in range(3)], axis=1)
        mag = (vals & 0x1FF).astype(np.float32) * np.float32(np.sqrt(0.5) / 511)
        signed = np.where((vals >> 9) & 1 == 1, -mag, mag)
        order = np.array([[3, 2, 1], [3, 2, 0], [3, 1, 0], [2, 1, 0]])[largest]
        xyzw = np.empty((n, 4), np.float32)
        xyzw[np.arange(n)[:, None], order] = signed
        xyzw[np.arange(n), largest] = np.sqrt(np.maximum(0, 1 - (signed * signed).sum(axis=1)))
    sh = take(3 * k * n).reshape(n, k, 3).astype(np.float32) / np.float32(128) - 1
    flip_sh = np.array([-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1,
                        -1, 1, -1, 1, 1, -1, 1, -1, -1], np.float32)[:k]
    quats = xyzw[:, [3, 0, 1, 2]] * np.array([1, 1, -1, -1], np.float32)
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    return {"means": means * np.array([1, -1, -1], np.float32),
            "log_scales": scales.astype(np.float32) / 16 - 10,
            "quats": quats,
            "sh0": (colors.astype(np.float32) / 255 - 0.5) / np.float32(0.15),
            "opacity_logits": _logit_u8(alphas),
            "sh_rest": sh * flip_sh[None, :, None]}


def numpy_sog(path: Path) -> dict[str, np.ndarray]:
    """Vectorised decoder of a bundled SOG v2 without SH (WebP through Pillow)."""
    import io
    import json
    import zipfile

    from PIL import Image

    z = zipfile.ZipFile(path)
    meta = json.loads(z.read("meta.json"))
    n = meta["count"]

    def tex(name: str) -> np.ndarray:
        img = Image.open(io.BytesIO(z.read(name))).convert("RGBA")
        return np.asarray(img).reshape(-1, 4)[:n].astype(np.int32)

    lo, hi = tex(meta["means"]["files"][0]), tex(meta["means"]["files"][1])
    mins, maxs = np.array(meta["means"]["mins"]), np.array(meta["means"]["maxs"])
    v = mins + (maxs - mins) * (lo[:, :3] | hi[:, :3] << 8) / 65535.0
    means = (np.sign(v) * np.expm1(np.abs(v))).astype(np.float32)
    q = tex(meta["quats"]["files"][0])
    m = q[:, 3] - 252
    abc = ((q[:, :3] / 255.0 * 2 - 1) / np.sqrt(2)).astype(np.float32)
    quats = np.empty((n, 4), np.float32)
    slots = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[m]
    quats[np.arange(n)[:, None], slots] = abc
    quats[np.arange(n), m] = np.sqrt(np.maximum(0, 1 - (abc * abc).sum(1)))
    sc, c0 = tex(meta["scales"]["files"][0]), tex(meta["sh0"]["files"][0])
    return {"means": means, "quats": quats,
            "log_scales": np.array(meta["scales"]["codebook"], np.float32)[sc[:, :3]],
            "sh0": np.array(meta["sh0"]["codebook"], np.float32)[c0[:, :3]],
            "opacity_logits": _logit_u8(c0[:, 3])}


def numpy_glb(path: Path) -> dict[str, np.ndarray]:
    """Vectorised decoder of a float KHR_gaussian_splatting .glb, converted to RDF axes."""
    import json
    import struct

    data = path.read_bytes()
    jlen = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + jlen])
    bin_ = memoryview(data)[28 + jlen:]
    attrs = doc["meshes"][0]["primitives"][0]["attributes"]

    def get(name: str) -> np.ndarray:
        acc = doc["accessors"][attrs[name]]
        view = doc["bufferViews"][acc["bufferView"]]
        w = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
        return np.frombuffer(bin_, "<f4", acc["count"] * w, view["byteOffset"]).reshape(-1, w)

    e = "KHR_gaussian_splatting:"
    flip = np.array([-1, -1, 1], np.float32)
    rot = get(e + "ROTATION")
    op = np.clip(get(e + "OPACITY")[:, 0], 1e-6, 1 - 1e-6)
    out = {"means": get("POSITION") * flip,
           "quats": rot[:, [3, 0, 1, 2]] * np.array([1, -1, -1, 1], np.float32),
           "log_scales": np.log(get(e + "SCALE")), "sh0": get(e + "SH_DEGREE_0_COEF_0").copy(),
           "opacity_logits": np.log(op / (1 - op))}
    # parity of each SH basis function under (x, y) -> (-x, -y)
    sign = np.array([-1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1, 1, -1], np.float32)
    names = [f"{e}SH_DEGREE_{deg}_COEF_{c}" for deg in (1, 2, 3) for c in range(2 * deg + 1)]
    if names[0] in attrs:
        out["sh_rest"] = np.stack([get(nm) for nm in names], axis=1) * sign[:, None]
    return out


def numpy_scenesplat(folder: Path) -> dict[str, np.ndarray]:
    """np.load of a SceneSplat folder, un-activated as morphgs does."""
    c = np.load(folder / "color.npy").astype(np.float32)
    op = np.clip(np.load(folder / "opacity.npy"), 1e-6, 1 - 1e-6)
    return {"means": np.load(folder / "coord.npy"),
            "quats": np.load(folder / "quat.npy"),
            "log_scales": np.log(np.load(folder / "scale.npy")),
            "sh0": (np.minimum((c + 0.5) / 255, 1) - 0.5) / np.float32(C0),
            "opacity_logits": np.log(op / (1 - op))}


def _write_scenesplat(scene: morphgs.GaussianScene, folder: Path) -> None:
    folder.mkdir()
    np.save(folder / "coord.npy", scene.means)
    np.save(folder / "opacity.npy", scene.opacities)
    np.save(folder / "scale.npy", scene.scales)
    q = scene.quats * np.sign(scene.quats[:, :1])
    np.save(folder / "quat.npy", q / np.linalg.norm(q, axis=1, keepdims=True))
    np.save(folder / "color.npy", (scene.colors * 255).astype(np.uint8))


def _best_ms(fn: Callable[[], Any], repeat: int) -> float:
    fn()  # warm the page cache and the thread pool
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def _max_diff(scene: morphgs.GaussianScene, ref: dict[str, np.ndarray]) -> float:
    worst = 0.0
    for name, arr in ref.items():
        got = getattr(scene, name)
        if name == "quats":  # q and -q are one rotation
            d = np.minimum(np.abs(got - arr).max(axis=1), np.abs(got + arr).max(axis=1))
            worst = max(worst, float(d.max()))
        else:
            worst = max(worst, float(np.abs(got - arr).max()))
    return worst


def _random_scene(n: int, degree: int) -> morphgs.GaussianScene:
    rng = np.random.default_rng(0)
    k = (degree + 1) ** 2 - 1
    return morphgs.GaussianScene.from_arrays(
        means=rng.normal(0, 3, size=(n, 3)), quats=rng.normal(size=(n, 4)),
        log_scales=rng.uniform(-7, -2, size=(n, 3)), opacity_logits=rng.normal(0, 2, size=n),
        sh0=rng.normal(0, 0.8, size=(n, 3)), sh_rest=rng.normal(0, 0.1, size=(n, k, 3)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny sizes (smoke check)")
    ap.add_argument("--repeat", type=int, default=5, help="timed runs per case (best is kept)")
    ap.add_argument("--spz-splats", type=int, default=1_000_000)
    ap.add_argument("--sh-degree", type=int, default=3)
    args = ap.parse_args(argv)
    if args.quick:
        args.repeat, args.spz_splats = 1, 5_000
    ply = FIXTURES / ("playcanvas_engine_test.compressed.ply" if args.quick
                      else "playcanvas_engine_guitar.compressed.ply")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        spz = Path(tmp) / "random.spz"
        random_scene = _random_scene(args.spz_splats, args.sh_degree)
        morphgs.save_spz(random_scene, spz)
        glb = Path(tmp) / "random.glb"
        morphgs.save_glb(random_scene, glb)
        npy = Path(tmp) / "scenesplat"
        _write_scenesplat(random_scene, npy)
        sog = FIXTURES / "playcanvas_engine_monkey_0001.sog"
        tag = f"random {args.spz_splats:,} splats, SH {args.sh_degree}"
        cases = [(ply.name, ply, numpy_compressed_ply),
                 (f"{tag} (.spz v3)", spz, numpy_spz),
                 (sog.name, sog, numpy_sog),
                 (f"{tag} (.glb)", glb, numpy_glb),
                 (f"random {args.spz_splats:,} splats (SceneSplat .npy)", npy, numpy_scenesplat)]
        for label, path, np_decode in cases:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", morphgs.MorphgsWarning)  # SceneSplat is lossy
                scene = morphgs.load(path)
            diff = _max_diff(scene, np_decode(path))
            if diff > 1e-5:
                raise SystemExit(f"{label}: morphgs and the NumPy decoder disagree by {diff}")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", morphgs.MorphgsWarning)
                t_mg = _best_ms(lambda p=path: morphgs.load(p), args.repeat)
            t_np = _best_ms(lambda p=path, f=np_decode: f(p), args.repeat)
            size = sum(f.stat().st_size for f in path.iterdir()) if path.is_dir() \
                else path.stat().st_size
            rows.append((label, len(scene), size, t_mg, t_np, diff))
        writers = []
        for name, kw in [("w.spz", {}), ("w4.spz", {"spz_version": 4}),
                         ("w.compressed.ply", {}), ("w.glb", {}), ("w.ply", {})]:
            out = Path(tmp) / name
            t = _best_ms(lambda o=out, k=kw: morphgs.save(random_scene, o, **k), args.repeat)
            label = name.replace("w4.spz", ".spz v4").replace("w.spz", ".spz v3").lstrip("w")
            writers.append((label, t, out.stat().st_size))
    print(f"morphgs {morphgs.__version__}, {morphgs.num_threads()} threads, best of "
          f"{args.repeat}, NumPy {np.__version__}, Python {sys.version.split()[0]}")
    head = f"{'file':<52} {'splats':>9} {'bytes':>10} {'morphgs ms':>11} {'numpy ms':>9} " \
           f"{'numpy/morphgs':>13} {'max |diff|':>10}"
    print(head)
    print("-" * len(head))
    for label, n, size, t_mg, t_np, diff in rows:
        print(f"{label:<52} {n:>9,} {size:>10,} {t_mg:>11.2f} {t_np:>9.2f} "
              f"{t_np / t_mg:>12.1f}x {diff:>10.2e}")
    print(f"\nwriters, morphgs.save of the random {args.spz_splats:,}-splat SH {args.sh_degree} "
          "scene")
    print(f"{'format':<20} {'ms':>10} {'bytes':>12} {'Msplats/s':>10}")
    for label, t, size in writers:
        print(f"{label:<20} {t:>10.2f} {size:>12,} {args.spz_splats / t / 1e3:>10.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
