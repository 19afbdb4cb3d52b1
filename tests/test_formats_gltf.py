"""glTF/GLB KHR_gaussian_splatting: what `save_glb` writes is checked field by field against the
extension text (attribute semantics, accessor types, activated values, glTF axes) by a parser
written here, files built by hand to the spec (interleaved views, normalized integers, node
transforms, data URIs) load as the spec says, and malformed documents fail clearly."""

from __future__ import annotations

import base64
import json
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import morphgs

EXT = "KHR_gaussian_splatting"
C0 = 0.28209479177387814


def _parse_glb(data: bytes) -> tuple[dict[str, Any], bytes]:
    magic, version, total = struct.unpack_from("<III", data)
    assert magic == 0x46546C67 and version == 2 and total == len(data)
    jlen, jtype = struct.unpack_from("<II", data, 12)
    assert jtype == 0x4E4F534A
    doc = json.loads(data[20 : 20 + jlen])
    blen, btype = struct.unpack_from("<II", data, 20 + jlen)
    assert btype == 0x004E4942
    return doc, data[28 + jlen : 28 + jlen + blen]


def _attribute(doc: dict[str, Any], bin_: bytes, name: str) -> np.ndarray:
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"][name]]
    view = doc["bufferViews"][acc["bufferView"]]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc["type"]]
    dtype = {5126: np.float32, 5121: np.uint8}[acc["componentType"]]
    raw = np.frombuffer(bin_, dtype, count=acc["count"] * width,
                        offset=view["byteOffset"] + acc.get("byteOffset", 0))
    return raw.reshape(acc["count"], width)


def test_glb_writer_follows_the_extension(fixtures_dir: Path, tmp_path: Path) -> None:
    scene = morphgs.load(fixtures_dir / "metalsplatter_train3.ply")
    out = tmp_path / "train3.glb"
    morphgs.save_glb(scene, out)
    doc, bin_ = _parse_glb(out.read_bytes())
    assert doc["asset"]["version"] == "2.0" and EXT in doc["extensionsUsed"]
    prim = doc["meshes"][0]["primitives"][0]
    assert prim["mode"] == 0
    assert prim["extensions"][EXT]["kernel"] == "ellipse"
    assert prim["extensions"][EXT]["colorSpace"] == "srgb_rec709_display"
    names = set(prim["attributes"])
    want = {"POSITION", "COLOR_0", f"{EXT}:ROTATION", f"{EXT}:SCALE", f"{EXT}:OPACITY",
            f"{EXT}:SH_DEGREE_0_COEF_0"}
    want |= {f"{EXT}:SH_DEGREE_{l}_COEF_{n}" for l in (1, 2, 3) for n in range(2 * l + 1)}
    assert names == want
    # glTF axes: RDF (PLY) -> +Y up, +Z front = negate x and y
    pos = _attribute(doc, bin_, "POSITION")
    np.testing.assert_array_equal(pos, scene.means * np.array([-1, -1, 1], np.float32))
    pacc = doc["accessors"][prim["attributes"]["POSITION"]]
    np.testing.assert_allclose(pacc["min"], pos.min(0))
    rot = _attribute(doc, bin_, f"{EXT}:ROTATION")  # (x, y, z, w), x and y negated
    w, x, y, z = scene.quats.T
    np.testing.assert_allclose(rot, np.c_[-x, -y, z, w], atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(rot, axis=1), 1, atol=1e-6)
    np.testing.assert_allclose(_attribute(doc, bin_, f"{EXT}:SCALE"), scene.scales, rtol=1e-6)
    np.testing.assert_allclose(_attribute(doc, bin_, f"{EXT}:OPACITY")[:, 0], scene.opacities,
                               rtol=1e-6)
    np.testing.assert_array_equal(_attribute(doc, bin_, f"{EXT}:SH_DEGREE_0_COEF_0"), scene.sh0)
    # degree-1 basis (y, z, x) flips with y and x: coefficients 0 and 2 negated, 1 kept
    d1 = np.stack([_attribute(doc, bin_, f"{EXT}:SH_DEGREE_1_COEF_{n}") for n in range(3)], 1)
    np.testing.assert_array_equal(d1, scene.sh_rest[:, :3] * np.array([-1, 1, -1])[None, :, None])
    color = _attribute(doc, bin_, "COLOR_0")
    np.testing.assert_allclose(color[:, :3] / 255, np.clip(0.5 + C0 * scene.sh0, 0, 1), atol=0.5 / 255)

    back = morphgs.load(out)
    np.testing.assert_array_equal(back.means, scene.means)
    np.testing.assert_array_equal(back.sh_rest, scene.sh_rest)
    np.testing.assert_allclose(back.quats, scene.quats, atol=1e-6)
    np.testing.assert_allclose(back.log_scales, scene.log_scales, atol=1e-5)
    np.testing.assert_allclose(back.opacity_logits, scene.opacity_logits, atol=1e-4)


def _gltf(tmp_path: Path, attrs: dict[str, tuple[np.ndarray, int, bool]], *,
          node: dict[str, Any] | None = None, interleave: bool = False,
          uri: str = "file", extra: dict[str, Any] | None = None) -> Path:
    """A .gltf document with its buffer beside it (or as a data URI)."""
    accessors, views, blob = [], [], b""
    n = len(next(iter(attrs.values()))[0])
    if interleave:  # one view, byteStride covering every attribute
        parts = [(name, a.astype({5126: "<f4", 5121: "u1", 5123: "<u2", 5120: "i1"}[ct]), ct, norm)
                 for name, (a, ct, norm) in attrs.items()]
        stride = sum(p[1].dtype.itemsize * p[1].shape[1] for p in parts)
        stride += -stride % 4
        rows = bytearray(stride * n)
        off = 0
        for name, a, ct, norm in parts:
            for i in range(n):
                b = a[i].tobytes()
                rows[i * stride + off : i * stride + off + len(b)] = b
            ty = {1: "SCALAR", 3: "VEC3", 4: "VEC4"}[a.shape[1]]
            accessors.append({"bufferView": 0, "byteOffset": off, "componentType": ct,
                              "count": n, "type": ty, "normalized": norm})
            off += a.dtype.itemsize * a.shape[1]
        views.append({"buffer": 0, "byteOffset": 0, "byteLength": len(rows), "byteStride": stride})
        blob = bytes(rows)
    else:
        for name, (a, ct, norm) in attrs.items():
            a = a.astype({5126: "<f4", 5121: "u1", 5123: "<u2", 5120: "i1"}[ct])
            ty = {1: "SCALAR", 3: "VEC3", 4: "VEC4"}[a.shape[1]]
            views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": a.nbytes})
            accessors.append({"bufferView": len(views) - 1, "componentType": ct, "count": n,
                              "type": ty, "normalized": norm})
            blob += a.tobytes() + b"\0" * (-a.nbytes % 4)
    if uri == "file":
        (tmp_path / "splats.bin").write_bytes(blob)
        buffer = {"uri": "splats.bin", "byteLength": len(blob)}
    else:
        buffer = {"uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode(),
                  "byteLength": len(blob)}
    doc = {
        "asset": {"version": "2.0"}, "extensionsUsed": [EXT], "scene": 0,
        "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, **(node or {})}],
        "meshes": [{"primitives": [{
            "mode": 0, "attributes": {name: i for i, name in enumerate(attrs)},
            "extensions": {EXT: {"kernel": "ellipse", "colorSpace": "srgb_rec709_display"}}}]}],
        "buffers": [buffer], "bufferViews": views, "accessors": accessors, **(extra or {}),
    }
    p = tmp_path / "scene.gltf"
    p.write_text(json.dumps(doc))
    return p


def _attrs(n: int, rng: np.random.Generator) -> dict[str, tuple[np.ndarray, int, bool]]:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return {
        "POSITION": (rng.normal(size=(n, 3)), 5126, False),
        f"{EXT}:ROTATION": (q, 5126, False),
        f"{EXT}:SCALE": (rng.uniform(0.01, 0.2, (n, 3)), 5126, False),
        f"{EXT}:SH_DEGREE_0_COEF_0": (rng.normal(size=(n, 3)), 5126, False),
        f"{EXT}:OPACITY": (rng.integers(0, 256, (n, 1)), 5121, True),  # last: keeps alignment
    }


@pytest.mark.parametrize("interleave,uri", [(False, "file"), (True, "data")])
def test_hand_built_gltf(tmp_path: Path, interleave: bool, uri: str) -> None:
    rng = np.random.default_rng(7)
    attrs = _attrs(11, rng)
    p = _gltf(tmp_path, attrs, interleave=interleave, uri=uri,
              node={"translation": [1.0, 2.0, 3.0], "scale": [2.0, 2.0, 2.0]})
    s = morphgs.load(p)
    pos = attrs["POSITION"][0].astype(np.float32) * 2 + [1, 2, 3]
    np.testing.assert_allclose(s.means, pos * [-1, -1, 1], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(s.scales, attrs[f"{EXT}:SCALE"][0] * 2, rtol=1e-5)
    op = attrs[f"{EXT}:OPACITY"][0][:, 0] / 255
    np.testing.assert_allclose(s.opacities, np.clip(op, 1e-6, 1 - 1e-6), atol=1e-5)
    x, y, z, w = attrs[f"{EXT}:ROTATION"][0].T
    np.testing.assert_allclose(s.quats, np.c_[w, -x, -y, z], atol=1e-6)


def test_rotated_node_without_sh_is_applied(tmp_path: Path) -> None:
    rng = np.random.default_rng(8)
    attrs = _attrs(5, rng)
    half = np.sqrt(0.5)  # 90 degrees about +Y: (x, y, z) -> (z, y, -x)
    p = _gltf(tmp_path, attrs, node={"rotation": [0.0, half, 0.0, half]})
    s = morphgs.load(p)
    x, y, z = attrs["POSITION"][0].T
    np.testing.assert_allclose(s.means, np.c_[z, y, -x] * [-1, -1, 1], atol=1e-6)


def test_malformed_gltf(tmp_path: Path) -> None:
    rng = np.random.default_rng(9)

    def expect(p: Path, pattern: str) -> None:
        with pytest.raises(morphgs.SceneFormatError, match=pattern) as e:
            morphgs.load(p)
        assert str(p) in str(e.value)

    attrs = _attrs(4, rng)
    p = _gltf(tmp_path, attrs)
    (tmp_path / "splats.bin").write_bytes((tmp_path / "splats.bin").read_bytes()[:40])
    expect(p, r"buffers\[0\].*truncated")

    attrs = _attrs(4, rng)
    p = _gltf(tmp_path, attrs)
    doc = json.loads(p.read_text())
    doc["accessors"][0]["count"] = 1000  # runs out of its bufferView
    p.write_text(json.dumps(doc))
    expect(p, r"accessors\[0\].*need .* bytes but bufferView")

    doc["accessors"][0]["count"] = 4
    del doc["meshes"][0]["primitives"][0]["attributes"][f"{EXT}:SCALE"]
    p.write_text(json.dumps(doc))
    expect(p, "SCALE is missing")

    p = _gltf(tmp_path, _attrs(4, rng), extra={"extensionsRequired": ["KHR_draco_mesh_compression"]})
    expect(p, "requires KHR_draco_mesh_compression")

    sh = dict(_attrs(4, rng))
    sh[f"{EXT}:SH_DEGREE_1_COEF_0"] = (rng.normal(size=(4, 3)), 5126, False)
    expect(_gltf(tmp_path, sh), "SH degree 1 is partially defined")
    sh[f"{EXT}:SH_DEGREE_1_COEF_1"] = (rng.normal(size=(4, 3)), 5126, False)
    sh[f"{EXT}:SH_DEGREE_1_COEF_2"] = (rng.normal(size=(4, 3)), 5126, False)
    expect(_gltf(tmp_path, sh, node={"rotation": [0.0, 0.6, 0.0, 0.8]}), "rotated node")

    glb = tmp_path / "cut.glb"
    scene = morphgs.load(_gltf(tmp_path, _attrs(4, rng)))
    morphgs.save_glb(scene, glb)
    glb.write_bytes(glb.read_bytes()[:-10])
    expect(glb, "truncated")


def _glb(doc: dict[str, Any], bin_: bytes) -> bytes:
    j = json.dumps(doc).encode()
    j += b" " * (-len(j) % 4)
    b = bin_ + b"\0" * (-len(bin_) % 4)
    return (struct.pack("<III", 0x46546C67, 2, 28 + len(j) + len(b)) + struct.pack("<II", len(j), 0x4E4F534A) + j
            + struct.pack("<II", len(b), 0x004E4942) + b)


def test_log_space_scales_as_splat_transform_writes_them(fixtures_dir: Path, tmp_path: Path) -> None:
    """playcanvas/splat-transform's write-glb.ts stores SCALE in log space (the extension's review
    draft); the release candidate says linear and never negative. A SCALE with negative values
    is read as log-space, with a warning naming the generator, instead of silently becoming a
    scene of vanishing Gaussians."""
    scene = morphgs.load(fixtures_dir / "metalsplatter_train3.ply")
    ours = tmp_path / "linear.glb"
    morphgs.save(scene, ours)
    doc, bin_ = _parse_glb(ours.read_bytes())
    # the same file as splat-transform writes it: SCALE = the PLY's log-scales, its generator
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"][f"{EXT}:SCALE"]]
    off = doc["bufferViews"][acc["bufferView"]]["byteOffset"] + acc.get("byteOffset", 0)
    linear = _attribute(doc, bin_, f"{EXT}:SCALE")
    assert (linear > 0).all()
    buf = bytearray(bin_)
    buf[off : off + linear.nbytes] = np.log(linear).astype(np.float32).tobytes()
    doc["asset"]["generator"] = "splat-transform 1.7.0"
    st = tmp_path / "splat-transform.glb"
    st.write_bytes(_glb(doc, bytes(buf)))

    with pytest.warns(morphgs.MorphgsWarning, match=r"splat-transform 1\.7\.0.*log-space") as w:
        back = morphgs.load(st)
    assert str(st) in str(w[0].message)
    want = morphgs.load(ours)
    np.testing.assert_allclose(np.asarray(back.log_scales), np.asarray(want.log_scales), atol=1e-5)
    np.testing.assert_array_equal(np.asarray(back.means), np.asarray(want.means))
    r1 = morphgs.render(back, morphgs.trajectory.for_scene(back, n_frames=1, resolution=(64, 48))[0]).rgb
    r2 = morphgs.render(want, morphgs.trajectory.for_scene(want, n_frames=1, resolution=(64, 48))[0]).rgb
    assert np.abs(r1 - r2).max() < 1e-3
    # a file with linear scales (ours) loads without the warning
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", morphgs.MorphgsWarning)
        morphgs.load(ours)
