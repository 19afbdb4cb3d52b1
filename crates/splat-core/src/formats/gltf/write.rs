//! Writing GLB: a scene as one `KHR_gaussian_splatting` POINTS primitive, linear scales, RDF
//! axes mapped to glTF's LUF.
use std::path::Path;

use serde_json::{json, Value};

use super::{attr, sh_attr, CHUNK_BIN, CHUNK_JSON, EXT, GLB_MAGIC, TO_GLTF};
use crate::error::{Error, Result};
use crate::formats::{check_finite, flip_axes, sigmoid, to_u8, unit_quat};
use crate::ply::atomic_write;
use crate::scene::{SceneView, SH_C0};

/// The GLB bytes for a scene in RDF axes. SH degree 4 has no glTF attributes and is written
/// as degree 3 (callers warn).
pub fn encode_glb(scene: &SceneView<'_>, generator: &str) -> Result<Vec<u8>> {
    check_finite(scene, ".glb")?;
    let n = scene.len();
    let mut owned = scene.to_owned_scene();
    flip_axes(&mut owned, TO_GLTF);
    let degree = scene.sh_degree.min(3);
    let k = scene.sh_rest_k();
    let mut bin: Vec<u8> = Vec::new();
    let mut views = Vec::new();
    let mut accessors = Vec::new();
    let mut attributes = serde_json::Map::new();
    let mut push = |name: String, bytes: Vec<u8>, ct: u32, ty: &str, extra: Value| {
        let off = bin.len();
        let len = bytes.len();
        bin.extend_from_slice(&bytes);
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        let i = views.len();
        views.push(json!({"buffer": 0, "byteOffset": off, "byteLength": len, "target": 34962}));
        let mut acc = json!({"bufferView": i, "componentType": ct, "count": n, "type": ty});
        if let (Some(a), Some(e)) = (acc.as_object_mut(), extra.as_object()) {
            a.extend(e.clone());
        }
        accessors.push(acc);
        attributes.insert(name, json!(i));
    };
    let f32s =
        |v: &mut dyn Iterator<Item = f32>| -> Vec<u8> { v.flat_map(f32::to_le_bytes).collect() };
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for p in owned.means.chunks_exact(3) {
        for d in 0..3 {
            lo[d] = lo[d].min(p[d]);
            hi[d] = hi[d].max(p[d]);
        }
    }
    let bounds = if n > 0 {
        json!({"min": lo, "max": hi})
    } else {
        json!({})
    };
    push(
        "POSITION".into(),
        f32s(&mut owned.means.iter().copied()),
        5126,
        "VEC3",
        bounds,
    );
    let mut color = Vec::with_capacity(n * 4);
    for i in 0..n {
        for c in 0..3 {
            color.push(to_u8((owned.sh0[i * 3 + c] * SH_C0 + 0.5) * 255.0));
        }
        color.push(to_u8(sigmoid(owned.opacity_logits[i]) * 255.0));
    }
    push(
        "COLOR_0".into(),
        color,
        5121,
        "VEC4",
        json!({"normalized": true}),
    );
    let rot: Vec<f32> = owned
        .quats
        .chunks_exact(4)
        .flat_map(|q| {
            let [w, x, y, z] = unit_quat(q);
            [x, y, z, w]
        })
        .collect();
    push(
        attr("ROTATION"),
        f32s(&mut rot.into_iter()),
        5126,
        "VEC4",
        json!({}),
    );
    push(
        attr("SCALE"),
        f32s(&mut owned.log_scales.iter().map(|v| v.exp())),
        5126,
        "VEC3",
        json!({}),
    );
    push(
        attr("OPACITY"),
        f32s(&mut owned.opacity_logits.iter().map(|&v| sigmoid(v))),
        5126,
        "SCALAR",
        json!({}),
    );
    push(
        sh_attr(0, 0),
        f32s(&mut owned.sh0.iter().copied()),
        5126,
        "VEC3",
        json!({}),
    );
    let mut j = 0;
    for l in 1..=degree {
        for c in 0..(2 * l as usize + 1) {
            let vals: Vec<f32> = (0..n)
                .flat_map(|i| {
                    let b = (i * k + j) * 3;
                    [owned.sh_rest[b], owned.sh_rest[b + 1], owned.sh_rest[b + 2]]
                })
                .collect();
            push(
                sh_attr(l, c),
                f32s(&mut vals.into_iter()),
                5126,
                "VEC3",
                json!({}),
            );
            j += 1;
        }
    }
    let doc = json!({
        "asset": {"version": "2.0", "generator": generator},
        "extensionsUsed": [EXT],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{
            "attributes": attributes,
            "mode": 0,
            "extensions": {EXT: {
                "kernel": "ellipse",
                "colorSpace": "srgb_rec709_display",
                "sortingMethod": "cameraDistance",
                "projection": "perspective"
            }}
        }]}],
        "buffers": [{"byteLength": bin.len()}],
        "bufferViews": views,
        "accessors": accessors,
    });
    let mut json_bytes = serde_json::to_vec(&doc)
        .map_err(|e| Error::InvalidArgument(format!("cannot encode glTF JSON: {e}")))?;
    while !json_bytes.len().is_multiple_of(4) {
        json_bytes.push(b' ');
    }
    let total = 12 + 8 + json_bytes.len() + 8 + bin.len();
    let total32 = u32::try_from(total).map_err(|_| {
        Error::InvalidArgument(format!("cannot write .glb: {total} bytes exceed 4 GiB"))
    })?;
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(&GLB_MAGIC.to_le_bytes());
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&total32.to_le_bytes());
    out.extend_from_slice(&(json_bytes.len() as u32).to_le_bytes());
    out.extend_from_slice(&CHUNK_JSON.to_le_bytes());
    out.extend_from_slice(&json_bytes);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(&CHUNK_BIN.to_le_bytes());
    out.extend_from_slice(&bin);
    Ok(out)
}

/// Write a scene (RDF axes) as a `.glb` with `KHR_gaussian_splatting`, atomically.
pub fn write(path: &Path, scene: &SceneView<'_>) -> Result<()> {
    let bytes = encode_glb(scene, concat!("morphgs ", env!("CARGO_PKG_VERSION")))?;
    atomic_write(path, |w| w.write_all(&bytes))
}
