//! glTF 2.0 / GLB with `KHR_gaussian_splatting` (KhronosGroup/glTF
//! `extensions/2.0/Khronos/KHR_gaussian_splatting/README.md`).
//!
//! A splat field is a `POINTS` mesh primitive whose `extensions.KHR_gaussian_splatting` object
//! names the kernel (`"ellipse"`) and colour space, with these attributes, all **activated**:
//!
//! | semantic | type | stored as |
//! |---|---|---|
//! | `POSITION` | VEC3 | mean, glTF axes (+Y up, +Z front, +X left: "LUF") |
//! | `KHR_gaussian_splatting:ROTATION` | VEC4 float / normalized byte, short | unit quaternion, glTF order (x,y,z,w) |
//! | `KHR_gaussian_splatting:SCALE` | VEC3 float / (normalized) ubyte, ushort | linear scale (see below) |
//! | `KHR_gaussian_splatting:OPACITY` | SCALAR float / normalized ubyte, ushort | sigmoid(logit), in [0,1] |
//! | `KHR_gaussian_splatting:SH_DEGREE_0_COEF_0` | VEC3 float | DC coefficient |
//! | `KHR_gaussian_splatting:SH_DEGREE_l_COEF_n` | VEC3 float | degree l = 1..3, n = 0..2l (m = -l..l) |
//!
//! The SH coefficients use the same real basis as the INRIA PLY and gsplat. morphgs keeps the
//! PLY's RDF axes, so reading maps glTF's LUF to RDF and writing maps back: both are the
//! 180-degree rotation about Z (x and y negated; quaternion x and y negated; SH by parity), what
//! playcanvas/splat-transform's GLB writer applies (`Transform.PLY`, a 180-degree Z rotation).
//!
//! **Log-space scales.** The extension's review draft stored `SCALE` in log space; the release
//! candidate says "Scale values are linear and MUST NOT be negative". playcanvas/splat-transform's
//! GLB writer still writes log-space scales (`write-glb.ts`: "log-space"). A `SCALE` accessor
//! holding any negative value cannot be linear, so it is read as log-space, with a note (the
//! caller's MorphgsWarning) naming the file and the generator; read as linear, such a file would
//! have silently become a scene of vanishing Gaussians. morphgs writes linear scales.
//!
//! Node transforms are applied to the splats they instance (translation, rotation and uniform
//! positive scale; rotating higher SH bands is not supported and is refused). Sparse accessors,
//! `KHR_gaussian_splatting` compression extensions and other required extensions are refused
//! with a clear error rather than misread.
use std::borrow::Cow;
use std::path::{Component, Path, PathBuf};

use rayon::prelude::*;
use serde_json::Value;

use super::{finish, flip_axes, logit_unit};
use crate::error::{Error, Result};
use crate::ply::{LoadReport, OnInvalid};
use crate::scene::{sh_rest_count, Scene};

mod write;
pub use write::{encode_glb, write};

pub const GLB_MAGIC: u32 = 0x4654_6C67; // "glTF"
const CHUNK_JSON: u32 = 0x4E4F_534A;
const CHUNK_BIN: u32 = 0x004E_4942;
const EXT: &str = "KHR_gaussian_splatting";
/// RDF <-> glTF LUF: negate x and y.
const TO_GLTF: [f32; 3] = [-1.0, -1.0, 1.0];

fn attr(name: &str) -> String {
    format!("{EXT}:{name}")
}

fn sh_attr(l: u8, n: usize) -> String {
    attr(&format!("SH_DEGREE_{l}_COEF_{n}"))
}

/// Errors about the glTF document: element "gltf", property = the JSON location.
fn gerr(path: &Path, at: &str, msg: impl Into<String>) -> Error {
    Error::format_at(path, "gltf", Some(at), msg)
}

/// True when `bytes` start like a glTF JSON document (an object with an `asset` key).
pub fn looks_like_gltf_json(bytes: &[u8]) -> bool {
    serde_json::from_slice::<Value>(bytes)
        .map(|v| v.get("asset").is_some() && v.get("meshes").is_some())
        .unwrap_or(false)
}

/// Split a GLB into its JSON and BIN chunks, checking every length.
fn split_glb<'a>(b: &'a [u8], path: &Path) -> Result<(Value, Option<&'a [u8]>)> {
    let u32_at = |o: usize| u32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]]);
    if b.len() < 20 {
        return Err(gerr(
            path,
            "header",
            "GLB shorter than its 12-byte header and first chunk",
        ));
    }
    let version = u32_at(4);
    if version != 2 {
        return Err(gerr(
            path,
            "header",
            format!("GLB version {version} (only 2 is supported)"),
        ));
    }
    let total = u32_at(8) as usize;
    if total > b.len() {
        return Err(gerr(
            path,
            "header",
            format!(
                "GLB header declares {total} bytes but the file has {} (truncated)",
                b.len()
            ),
        ));
    }
    let mut off = 12;
    let mut json = None;
    let mut bin = None;
    while off + 8 <= total {
        let len = u32_at(off) as usize;
        let ty = u32_at(off + 4);
        let start = off + 8;
        if start + len > total {
            return Err(gerr(
                path,
                "chunk",
                format!("chunk at byte {off} declares {len} bytes, past the {total}-byte GLB"),
            ));
        }
        let data = &b[start..start + len];
        match ty {
            CHUNK_JSON if json.is_none() => json = Some(data),
            CHUNK_BIN if bin.is_none() => bin = Some(data),
            _ => {}
        }
        off = start + len.next_multiple_of(4);
    }
    let json = json.ok_or_else(|| gerr(path, "chunk", "GLB has no JSON chunk"))?;
    let v = serde_json::from_slice(json)
        .map_err(|e| gerr(path, "json", format!("JSON chunk is not valid JSON ({e})")))?;
    Ok((v, bin))
}

/// Read a `.glb` (bytes of the file at `path`) or `.gltf` (JSON, buffers beside it or as data
/// URIs).
pub fn read(bytes: &[u8], path: &Path, on_invalid: OnInvalid) -> Result<(Scene, LoadReport)> {
    let (doc, glb_bin) = if bytes.starts_with(&GLB_MAGIC.to_le_bytes()) {
        split_glb(bytes, path)?
    } else {
        let v = serde_json::from_slice(bytes)
            .map_err(|e| gerr(path, "json", format!("not valid JSON ({e})")))?;
        (v, None)
    };
    let buffers = load_buffers(&doc, glb_bin, path)?;
    let g = Doc {
        v: &doc,
        path,
        buffers,
    };
    check_required(&doc, path)?;
    let prims = g.splat_primitives()?;
    if prims.is_empty() {
        return Err(gerr(
            path,
            "meshes",
            format!("no mesh primitive carries the {EXT} extension (not a Gaussian-splat glTF)"),
        ));
    }
    let mut parts = Vec::with_capacity(prims.len());
    let mut log_scaled = Vec::new();
    for (at, prim, m) in prims {
        let (mut s, log_space) = g.decode_primitive(&at, prim)?;
        if log_space {
            log_scaled.push(at.clone());
        }
        if let Some(m) = m {
            apply_transform(&mut s, &m, path, &at)?;
        }
        parts.push(s);
    }
    let mut scene = concat(parts);
    flip_axes(&mut scene, TO_GLTF);
    let (scene, mut report) = finish(scene, "gltf", "gltf", path, on_invalid)?;
    if !log_scaled.is_empty() {
        let generator = doc
            .pointer("/asset/generator")
            .and_then(Value::as_str)
            .map(|g| format!(" (written by {g:?})"))
            .unwrap_or_default();
        report.notes.push(format!(
            "{}{generator}: {EXT}:SCALE of {} holds negative values, which linear scales cannot; \
             read as log-space scales, as the extension's review draft and splat-transform's GLB \
             writer store them (the release candidate stores linear scales)",
            path.display(),
            log_scaled.join(", ")
        ));
    }
    Ok((scene, report))
}

fn check_required(doc: &Value, path: &Path) -> Result<()> {
    if let Some(req) = doc.get("extensionsRequired").and_then(Value::as_array) {
        for r in req {
            let name = r.as_str().unwrap_or("?");
            if name != EXT && name != "KHR_mesh_quantization" {
                return Err(gerr(
                    path,
                    "extensionsRequired",
                    format!("requires {name}, which morphgs does not read"),
                ));
            }
        }
    }
    Ok(())
}

fn load_buffers<'a>(
    doc: &Value,
    glb_bin: Option<&'a [u8]>,
    path: &Path,
) -> Result<Vec<Cow<'a, [u8]>>> {
    let Some(list) = doc.get("buffers").and_then(Value::as_array) else {
        return Ok(Vec::new());
    };
    let mut out = Vec::with_capacity(list.len());
    for (i, b) in list.iter().enumerate() {
        let at = format!("buffers[{i}]");
        let len = b
            .get("byteLength")
            .and_then(Value::as_u64)
            .ok_or_else(|| gerr(path, &at, "has no byteLength"))?;
        let data = match b.get("uri").and_then(Value::as_str) {
            None => {
                let bin = glb_bin
                    .filter(|_| i == 0)
                    .ok_or_else(|| gerr(path, &at, "has no uri and there is no GLB BIN chunk"))?;
                Cow::Borrowed(bin)
            }
            Some(uri) if uri.starts_with("data:") => {
                let (_, b64) = uri
                    .split_once(";base64,")
                    .ok_or_else(|| gerr(path, &at, "data URI is not base64"))?;
                Cow::Owned(
                    base64(b64).ok_or_else(|| gerr(path, &at, "data URI holds invalid base64"))?,
                )
            }
            Some(uri) => {
                let rel = Path::new(uri);
                if uri.contains("://")
                    || rel.is_absolute()
                    || rel.components().any(|c| !matches!(c, Component::Normal(_)))
                {
                    return Err(gerr(
                        path,
                        &at,
                        format!("uri '{uri}' must be a relative file name beside the .gltf"),
                    ));
                }
                let p: PathBuf = path.parent().unwrap_or(Path::new(".")).join(rel);
                Cow::Owned(std::fs::read(&p).map_err(|e| Error::io(&p, e))?)
            }
        };
        if (data.len() as u64) < len {
            return Err(gerr(
                path,
                &at,
                format!("declares {len} bytes but holds {} (truncated)", data.len()),
            ));
        }
        out.push(data);
    }
    Ok(out)
}

/// Standard base64 (padding optional).
fn base64(s: &str) -> Option<Vec<u8>> {
    let val = |c: u8| -> Option<u32> {
        Some(match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' | b'-' => 62,
            b'/' | b'_' => 63,
            _ => return None,
        } as u32)
    };
    let bytes: Vec<u8> = s
        .bytes()
        .filter(|&c| c != b'=' && !c.is_ascii_whitespace())
        .collect();
    let mut out = Vec::with_capacity(bytes.len() * 3 / 4);
    for chunk in bytes.chunks(4) {
        let mut acc = 0u32;
        for (i, &c) in chunk.iter().enumerate() {
            acc |= val(c)? << (18 - 6 * i);
        }
        let n = match chunk.len() {
            4 => 3,
            3 => 2,
            2 => 1,
            _ => return None,
        };
        out.extend_from_slice(&acc.to_be_bytes()[1..1 + n]);
    }
    Some(out)
}

type Mat4 = [f64; 16]; // column-major, as glTF

fn mat_mul(a: &Mat4, b: &Mat4) -> Mat4 {
    let mut r = [0f64; 16];
    for c in 0..4 {
        for row in 0..4 {
            r[c * 4 + row] = (0..4).map(|k| a[k * 4 + row] * b[c * 4 + k]).sum();
        }
    }
    r
}

const IDENTITY: Mat4 = [
    1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
];

struct Doc<'a> {
    v: &'a Value,
    path: &'a Path,
    buffers: Vec<Cow<'a, [u8]>>,
}

impl<'a> Doc<'a> {
    fn node_matrix(&self, node: &Value, at: &str) -> Result<Mat4> {
        let nums = |key: &str, n: usize| -> Result<Option<Vec<f64>>> {
            match node.get(key) {
                None => Ok(None),
                Some(a) => {
                    let v: Option<Vec<f64>> = a
                        .as_array()
                        .filter(|a| a.len() == n)
                        .and_then(|a| a.iter().map(Value::as_f64).collect());
                    v.map(Some).ok_or_else(|| {
                        gerr(
                            self.path,
                            &format!("{at}.{key}"),
                            format!("is not {n} numbers"),
                        )
                    })
                }
            }
        };
        if let Some(m) = nums("matrix", 16)? {
            let mut out = [0f64; 16];
            out.copy_from_slice(&m);
            return Ok(out);
        }
        let t = nums("translation", 3)?.unwrap_or_else(|| vec![0.0; 3]);
        let r = nums("rotation", 4)?.unwrap_or_else(|| vec![0.0, 0.0, 0.0, 1.0]);
        let s = nums("scale", 3)?.unwrap_or_else(|| vec![1.0; 3]);
        let (x, y, z, w) = (r[0], r[1], r[2], r[3]);
        let rm = [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y + w * z),
            2.0 * (x * z - w * y),
            2.0 * (x * y - w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z + w * x),
            2.0 * (x * z + w * y),
            2.0 * (y * z - w * x),
            1.0 - 2.0 * (x * x + y * y),
        ];
        let mut m = IDENTITY;
        for c in 0..3 {
            for row in 0..3 {
                m[c * 4 + row] = rm[c * 3 + row] * s[c];
            }
            m[12 + c] = t[c];
        }
        Ok(m)
    }

    /// (JSON location, primitive, world matrix if not the identity) for every splat primitive
    /// reached from the default scene (or, without scenes, every splat primitive as is).
    fn splat_primitives(&self) -> Result<Vec<(String, &'a Value, Option<Mat4>)>> {
        let meshes = self.v.get("meshes").and_then(Value::as_array);
        let Some(meshes) = meshes else {
            return Ok(Vec::new());
        };
        let splat_prims = |mi: usize| -> Vec<(String, &'a Value)> {
            meshes[mi]
                .get("primitives")
                .and_then(Value::as_array)
                .map(|ps| {
                    ps.iter()
                        .enumerate()
                        .filter(|(_, p)| p.pointer(&format!("/extensions/{EXT}")).is_some())
                        .map(|(pi, p)| (format!("meshes[{mi}].primitives[{pi}]"), p))
                        .collect()
                })
                .unwrap_or_default()
        };
        let nodes = self.v.get("nodes").and_then(Value::as_array);
        let scenes = self.v.get("scenes").and_then(Value::as_array);
        let (Some(nodes), Some(scenes)) = (nodes, scenes) else {
            return Ok((0..meshes.len())
                .flat_map(|mi| splat_prims(mi).into_iter().map(|(a, p)| (a, p, None)))
                .collect());
        };
        let si = self.v.get("scene").and_then(Value::as_u64).unwrap_or(0) as usize;
        let roots: Vec<u64> = scenes
            .get(si)
            .and_then(|s| s.get("nodes"))
            .and_then(Value::as_array)
            .map(|a| a.iter().filter_map(Value::as_u64).collect())
            .unwrap_or_default();
        let mut out = Vec::new();
        let mut stack: Vec<(u64, Mat4, usize)> = roots.iter().map(|&r| (r, IDENTITY, 0)).collect();
        let mut visited = 0usize;
        while let Some((ni, parent, depth)) = stack.pop() {
            visited += 1;
            let at = format!("nodes[{ni}]");
            let node = nodes
                .get(ni as usize)
                .ok_or_else(|| gerr(self.path, &at, "does not exist"))?;
            if depth > 64 || visited > 1 << 20 {
                return Err(gerr(self.path, &at, "node hierarchy is cyclic or too deep"));
            }
            let world = mat_mul(&parent, &self.node_matrix(node, &at)?);
            if let Some(mi) = node.get("mesh").and_then(Value::as_u64) {
                if mi as usize >= meshes.len() {
                    return Err(gerr(
                        self.path,
                        &format!("{at}.mesh"),
                        format!("mesh {mi} does not exist"),
                    ));
                }
                let m = (world != IDENTITY).then_some(world);
                out.extend(splat_prims(mi as usize).into_iter().map(|(a, p)| (a, p, m)));
            }
            if let Some(ch) = node.get("children").and_then(Value::as_array) {
                stack.extend(
                    ch.iter()
                        .filter_map(Value::as_u64)
                        .map(|c| (c, world, depth + 1)),
                );
            }
        }
        Ok(out)
    }

    /// The values of accessor `idx` as f32 rows of `comps` components (normalized integers
    /// mapped to [0,1] / [-1,1], other integers kept as is).
    fn accessor(&self, idx: u64, comps: usize, what: &str) -> Result<Vec<f32>> {
        let at = format!("accessors[{idx}]");
        let p = self.path;
        let a = self
            .v
            .get("accessors")
            .and_then(|a| a.get(idx as usize))
            .ok_or_else(|| gerr(p, &at, format!("({what}) does not exist")))?;
        if a.get("sparse").is_some() {
            return Err(gerr(
                p,
                &at,
                format!("({what}) is sparse; sparse accessors are not supported"),
            ));
        }
        let ty = a.get("type").and_then(Value::as_str).unwrap_or("");
        let want = match comps {
            1 => "SCALAR",
            3 => "VEC3",
            _ => "VEC4",
        };
        if ty != want {
            return Err(gerr(p, &at, format!("({what}) is {ty}, expected {want}")));
        }
        let ct = a.get("componentType").and_then(Value::as_u64).unwrap_or(0);
        let norm = a
            .get("normalized")
            .and_then(Value::as_bool)
            .unwrap_or(false);
        let size = match ct {
            5120 | 5121 => 1,
            5122 | 5123 => 2,
            5125 | 5126 => 4,
            _ => return Err(gerr(p, &at, format!("({what}) has componentType {ct}"))),
        };
        let count = a
            .get("count")
            .and_then(Value::as_u64)
            .ok_or_else(|| gerr(p, &at, "has no count"))?;
        let bv_idx = a
            .get("bufferView")
            .and_then(Value::as_u64)
            .ok_or_else(|| gerr(p, &at, format!("({what}) has no bufferView")))?;
        let bat = format!("bufferViews[{bv_idx}]");
        let bv = self
            .v
            .get("bufferViews")
            .and_then(|b| b.get(bv_idx as usize))
            .ok_or_else(|| gerr(p, &bat, "does not exist"))?;
        let buf_idx = bv.get("buffer").and_then(Value::as_u64).unwrap_or(u64::MAX);
        let buf = self
            .buffers
            .get(buf_idx as usize)
            .ok_or_else(|| gerr(p, &bat, format!("buffer {buf_idx} does not exist")))?;
        let bv_off = bv.get("byteOffset").and_then(Value::as_u64).unwrap_or(0);
        let bv_len = bv
            .get("byteLength")
            .and_then(Value::as_u64)
            .ok_or_else(|| gerr(p, &bat, "has no byteLength"))?;
        if bv_off.saturating_add(bv_len) > buf.len() as u64 {
            return Err(gerr(
                p,
                &bat,
                format!(
                    "bytes {bv_off}..{} lie outside buffer {buf_idx} ({} bytes)",
                    bv_off.saturating_add(bv_len),
                    buf.len()
                ),
            ));
        }
        let elem = (size * comps) as u64;
        let stride = bv.get("byteStride").and_then(Value::as_u64).unwrap_or(elem);
        if stride < elem {
            return Err(gerr(
                p,
                &bat,
                format!("byteStride {stride} is smaller than an element ({elem})"),
            ));
        }
        let a_off = a.get("byteOffset").and_then(Value::as_u64).unwrap_or(0);
        let need = if count == 0 {
            0
        } else {
            a_off
                .saturating_add((count - 1).saturating_mul(stride))
                .saturating_add(elem)
        };
        if need > bv_len {
            return Err(gerr(
                p,
                &at,
                format!(
                    "({what}) {count} elements of {elem} bytes (stride {stride}, offset {a_off}) \
                     need {need} bytes but bufferView {bv_idx} holds {bv_len}"
                ),
            ));
        }
        let base = (bv_off + a_off) as usize;
        let data = &buf[base..(bv_off + need) as usize];
        if ct == 5126 && stride == elem {
            // tightly packed floats: the common case, converted in parallel
            return Ok(data
                .par_chunks(4 * 4096)
                .flat_map_iter(|c| {
                    c.chunks_exact(4)
                        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                })
                .collect());
        }
        let mut out = Vec::with_capacity(count as usize * comps);
        for i in 0..count as usize {
            let e = &data[i * stride as usize..];
            for c in 0..comps {
                let b = &e[c * size..];
                let v = match (ct, norm) {
                    (5126, _) => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
                    (5121, true) => b[0] as f32 / 255.0,
                    (5121, false) => b[0] as f32,
                    (5120, true) => (b[0] as i8 as f32 / 127.0).max(-1.0),
                    (5120, false) => b[0] as i8 as f32,
                    (5123, true) => u16::from_le_bytes([b[0], b[1]]) as f32 / 65535.0,
                    (5123, false) => u16::from_le_bytes([b[0], b[1]]) as f32,
                    (5122, true) => (i16::from_le_bytes([b[0], b[1]]) as f32 / 32767.0).max(-1.0),
                    (5122, false) => i16::from_le_bytes([b[0], b[1]]) as f32,
                    _ => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
                };
                out.push(v);
            }
        }
        Ok(out)
    }

    /// The primitive's splats, and whether its `SCALE` was read as log-space (module docs).
    fn decode_primitive(&self, at: &str, prim: &Value) -> Result<(Scene, bool)> {
        let p = self.path;
        let mode = prim.get("mode").and_then(Value::as_u64).unwrap_or(4);
        if mode != 0 {
            return Err(gerr(
                p,
                at,
                format!("mode is {mode}; splat primitives must be POINTS (0)"),
            ));
        }
        let ext = prim
            .pointer(&format!("/extensions/{EXT}"))
            .unwrap_or(&Value::Null);
        if let Some(inner) = ext.get("extensions").and_then(Value::as_object) {
            if let Some(name) = inner.keys().next() {
                return Err(gerr(
                    p,
                    &format!("{at}.extensions.{EXT}.extensions"),
                    format!("uses {name}, which morphgs does not decode"),
                ));
            }
        }
        let kernel = ext
            .get("kernel")
            .and_then(Value::as_str)
            .unwrap_or("ellipse");
        if kernel != "ellipse" {
            return Err(gerr(
                p,
                at,
                format!("kernel '{kernel}' is not supported (only 'ellipse')"),
            ));
        }
        let attrs = prim
            .get("attributes")
            .and_then(Value::as_object)
            .ok_or_else(|| gerr(p, at, "has no attributes"))?;
        let get = |name: &str, comps: usize| -> Result<Option<Vec<f32>>> {
            match attrs.get(name).and_then(Value::as_u64) {
                None => Ok(None),
                Some(i) => self.accessor(i, comps, name).map(Some),
            }
        };
        let need = |name: &str, comps: usize| -> Result<Vec<f32>> {
            get(name, comps)?.ok_or_else(|| {
                gerr(
                    p,
                    &format!("{at}.attributes"),
                    format!("{name} is missing (required)"),
                )
            })
        };
        let pos = need("POSITION", 3)?;
        let n = pos.len() / 3;
        let rot = need(&attr("ROTATION"), 4)?;
        let scale = need(&attr("SCALE"), 3)?;
        let opacity = need(&attr("OPACITY"), 1)?;
        let dc = need(&sh_attr(0, 0), 3)?;
        let mut degree = 0u8;
        let mut bands: Vec<Vec<Vec<f32>>> = Vec::new();
        for l in 1..=3u8 {
            let coefs: Vec<Option<Vec<f32>>> = (0..(2 * l as usize + 1))
                .map(|c| get(&sh_attr(l, c), 3))
                .collect::<Result<_>>()?;
            let present = coefs.iter().filter(|c| c.is_some()).count();
            if present == 0 {
                break;
            }
            if present != coefs.len() {
                return Err(gerr(
                    p,
                    &format!("{at}.attributes"),
                    format!(
                        "SH degree {l} is partially defined ({present} of {} coefficients)",
                        coefs.len()
                    ),
                ));
            }
            degree = l;
            bands.push(coefs.into_iter().flatten().collect());
        }
        for (name, v, w) in [
            (attr("ROTATION"), &rot, 4),
            (attr("SCALE"), &scale, 3),
            (attr("OPACITY"), &opacity, 1),
            (sh_attr(0, 0), &dc, 3),
        ] {
            if v.len() != n * w {
                return Err(gerr(
                    p,
                    &format!("{at}.attributes"),
                    format!("{name} has {} elements but POSITION has {n}", v.len() / w),
                ));
            }
        }
        let k = sh_rest_count(degree);
        let mut s = Scene::zeroed(n, degree);
        s.means = pos;
        s.sh0 = dc;
        for (q, r) in s.quats.chunks_exact_mut(4).zip(rot.chunks_exact(4)) {
            q.copy_from_slice(&[r[3], r[0], r[1], r[2]]);
        }
        let log_space = scale.par_iter().any(|&v| v < 0.0);
        s.log_scales = if log_space {
            scale
        } else {
            scale
                .par_iter()
                .map(|&v| v.max(f32::MIN_POSITIVE).ln())
                .collect()
        };
        s.opacity_logits = opacity.par_iter().map(|&a| logit_unit(a)).collect();
        let coefs: Vec<&Vec<f32>> = bands.iter().flatten().collect();
        if coefs.iter().any(|c| c.len() != n * 3) {
            return Err(gerr(
                p,
                &format!("{at}.attributes"),
                "an SH attribute's count differs from POSITION's",
            ));
        }
        if k > 0 {
            s.sh_rest
                .par_chunks_mut(3 * k)
                .enumerate()
                .for_each(|(i, row)| {
                    for (j, c) in coefs.iter().enumerate() {
                        row[j * 3..j * 3 + 3].copy_from_slice(&c[i * 3..i * 3 + 3]);
                    }
                });
        }
        Ok((s, log_space))
    }
}

/// Apply a node's world matrix: translation, rotation and a uniform positive scale.
fn apply_transform(s: &mut Scene, m: &Mat4, path: &Path, at: &str) -> Result<()> {
    let col = |c: usize| [m[c * 4], m[c * 4 + 1], m[c * 4 + 2]];
    let len = |v: [f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    let sc = [len(col(0)), len(col(1)), len(col(2))];
    let r: Vec<[f64; 3]> = (0..3).map(|c| col(c).map(|x| x / sc[c])).collect();
    let det = r[0][0] * (r[1][1] * r[2][2] - r[2][1] * r[1][2])
        - r[1][0] * (r[0][1] * r[2][2] - r[2][1] * r[0][2])
        + r[2][0] * (r[0][1] * r[1][2] - r[1][1] * r[0][2]);
    let uniform = (sc[0] - sc[1]).abs() <= 1e-6 * sc[0] && (sc[0] - sc[2]).abs() <= 1e-6 * sc[0];
    if m[3] != 0.0
        || m[7] != 0.0
        || m[11] != 0.0
        || !uniform
        || sc[0] <= 0.0
        || (det - 1.0).abs() > 1e-4
    {
        return Err(gerr(
            path,
            at,
            "is instanced by a node whose transform is not translation + rotation + uniform \
             positive scale; such splat transforms are not supported",
        ));
    }
    let rot_identity =
        (0..3).all(|c| (0..3).all(|k| (r[c][k] - if c == k { 1.0 } else { 0.0 }).abs() < 1e-9));
    if !rot_identity && s.sh_degree > 0 {
        return Err(gerr(
            path,
            at,
            "is instanced by a rotated node; rotating SH bands above degree 0 is not supported",
        ));
    }
    // rotation matrix (columns r) to quaternion (w,x,y,z)
    let (m00, m11, m22) = (r[0][0], r[1][1], r[2][2]);
    let (m01, m10, m02, m20, m12, m21) = (r[1][0], r[0][1], r[2][0], r[0][2], r[2][1], r[1][2]);
    let tr = m00 + m11 + m22;
    let q = if tr > 0.0 {
        let s = (tr + 1.0).sqrt() * 2.0;
        [0.25 * s, (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s]
    } else if m00 > m11 && m00 > m22 {
        let s = (1.0 + m00 - m11 - m22).sqrt() * 2.0;
        [(m21 - m12) / s, 0.25 * s, (m01 + m10) / s, (m02 + m20) / s]
    } else if m11 > m22 {
        let s = (1.0 + m11 - m00 - m22).sqrt() * 2.0;
        [(m02 - m20) / s, (m01 + m10) / s, 0.25 * s, (m12 + m21) / s]
    } else {
        let s = (1.0 + m22 - m00 - m11).sqrt() * 2.0;
        [(m10 - m01) / s, (m02 + m20) / s, (m12 + m21) / s, 0.25 * s]
    };
    let ls = sc[0].ln() as f32;
    for p in s.means.chunks_exact_mut(3) {
        let v = [p[0] as f64, p[1] as f64, p[2] as f64];
        for row in 0..3 {
            p[row] = (m[row] * v[0] + m[4 + row] * v[1] + m[8 + row] * v[2] + m[12 + row]) as f32;
        }
    }
    for g in s.quats.chunks_exact_mut(4) {
        let b = [g[0] as f64, g[1] as f64, g[2] as f64, g[3] as f64];
        let a = q;
        g[0] = (a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3]) as f32;
        g[1] = (a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2]) as f32;
        g[2] = (a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1]) as f32;
        g[3] = (a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0]) as f32;
    }
    for v in s.log_scales.iter_mut() {
        *v += ls;
    }
    Ok(())
}

fn concat(mut parts: Vec<Scene>) -> Scene {
    if parts.len() == 1 {
        return parts.swap_remove(0);
    }
    let degree = parts.iter().map(|s| s.sh_degree).min().unwrap_or(0);
    let k = sh_rest_count(degree);
    let mut out = Scene::zeroed(0, degree);
    for s in parts {
        let sk = s.sh_rest_k();
        out.means.extend_from_slice(&s.means);
        out.quats.extend_from_slice(&s.quats);
        out.log_scales.extend_from_slice(&s.log_scales);
        out.opacity_logits.extend_from_slice(&s.opacity_logits);
        out.sh0.extend_from_slice(&s.sh0);
        for row in s
            .sh_rest
            .chunks_exact(3 * sk.max(1))
            .take(if sk == 0 { 0 } else { s.len() })
        {
            out.sh_rest.extend_from_slice(&row[..3 * k]);
        }
    }
    out
}
