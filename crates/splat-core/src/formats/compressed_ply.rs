//! PlayCanvas/SuperSplat `compressed.ply` (playcanvas/splat-transform `decompress-ply.ts`).
//!
//! A binary PLY with three elements:
//! - `chunk` (one row per 256 splats): float min/max of x y z, of the log-scales
//!   (`min_scale_x` ... `max_scale_z`) and optionally of the colour (`min_r` ... `max_b`);
//! - `vertex`: four uint32 per splat — `packed_position` and `packed_scale` (11/10/11 bits, a
//!   lerp between the chunk's bounds), `packed_rotation` (2-bit index of the largest component,
//!   then three 10-bit components of the others in (w,x,y,z) order, scaled by sqrt(2)) and
//!   `packed_color` (RGBA8; RGB lerped in the chunk's colour bounds when present, A the opacity);
//! - optional `sh`: uchar `f_rest_0..` (channel-major as in the INRIA PLY), (v/256 - 0.5) * 8.
//!
//! The axes are the PLY's own; nothing is converted.
use std::path::Path;

use rayon::prelude::*;

use super::{check_finite, finish, logit_unit, sigmoid, unit_quat};
use crate::error::{Error, Result};
use crate::ply::{
    atomic_write, Element, Encoding, Header, LoadReport, OnInvalid, PropertyKind, ScalarType,
};
use crate::scene::{sh_degree_for_rest, sh_rest_count, Scene, SceneView, SH_C0};

/// Splats per chunk.
pub const CHUNK: usize = 256;

const CHUNK_BOUNDS: [&str; 12] = [
    "min_x",
    "min_y",
    "min_z",
    "max_x",
    "max_y",
    "max_z",
    "min_scale_x",
    "min_scale_y",
    "min_scale_z",
    "max_scale_x",
    "max_scale_y",
    "max_scale_z",
];
const CHUNK_COLORS: [&str; 6] = ["min_r", "min_g", "min_b", "max_r", "max_g", "max_b"];
const PACKED: [&str; 4] = [
    "packed_position",
    "packed_rotation",
    "packed_scale",
    "packed_color",
];

/// True when a PLY header describes a compressed PLY (a `chunk` element and a `vertex` element
/// with `packed_position`); [`read`] then checks everything else.
pub fn is_compressed(header: &Header) -> bool {
    header.element("chunk").is_some()
        && header
            .element("vertex")
            .is_some_and(|(_, v)| v.property("packed_position").is_some())
}

/// One element's rows inside the body.
struct Table<'a> {
    element: &'a Element,
    rows: &'a [u8],
    stride: usize,
    offsets: Vec<usize>,
}

impl<'a> Table<'a> {
    /// Byte offset and type of property `name`, or a format error naming it.
    fn column(&self, name: &str, path: &Path) -> Result<(usize, ScalarType)> {
        let Some((i, p)) = self.element.property(name) else {
            return Err(Error::format_at(
                path,
                self.element.name.clone(),
                Some(name),
                "missing (required by the compressed PLY layout)",
            ));
        };
        match p.kind {
            PropertyKind::Scalar(t) => Ok((self.offsets[i], t)),
            PropertyKind::List(..) => Err(Error::format_at(
                path,
                self.element.name.clone(),
                Some(name),
                "is a list; expected a scalar",
            )),
        }
    }
}

/// Split the body into element tables, checking each count against the bytes left.
fn tables<'a>(header: &'a Header, body: &'a [u8], path: &Path) -> Result<Vec<Table<'a>>> {
    let mut out = Vec::new();
    let mut off = 0usize;
    for e in &header.elements {
        let (Some(stride), Some(offsets)) = (e.fixed_stride(), e.offsets()) else {
            return Err(Error::format_at(
                path,
                e.name.clone(),
                None,
                "list properties are not supported in a compressed PLY",
            ));
        };
        let left = (body.len() - off) as u64;
        let need = e.count.saturating_mul(stride as u64);
        if need > left {
            return Err(Error::format_at(
                path,
                e.name.clone(),
                None,
                format!(
                    "the header declares {} rows of {stride} bytes ({need} bytes) but only {left} \
                     bytes remain (truncated file or lying count)",
                    e.count
                ),
            ));
        }
        let need = need as usize;
        out.push(Table {
            element: e,
            rows: &body[off..off + need],
            stride,
            offsets,
        });
        off += need;
    }
    Ok(out)
}

/// Read a compressed PLY whose header was parsed from `bytes` (the whole file).
pub fn read(
    path: &Path,
    header: &Header,
    bytes: &[u8],
    on_invalid: OnInvalid,
) -> Result<(Scene, LoadReport)> {
    let scene = decode(path, header, bytes)?;
    finish(scene, "compressed-ply", "vertex", path, on_invalid)
}

/// Decode a compressed PLY (header already parsed, `bytes` the whole file).
pub fn decode(path: &Path, header: &Header, bytes: &[u8]) -> Result<Scene> {
    let big = match header.encoding {
        Encoding::BinaryLittleEndian => false,
        Encoding::BinaryBigEndian => true,
        Encoding::Ascii => {
            return Err(Error::format(
                path,
                "an ASCII compressed PLY is not supported (SuperSplat writes binary)",
            ))
        }
    };
    let body = bytes.get(header.len..).unwrap_or(&[]);
    let tabs = tables(header, body, path)?;
    let find = |name: &str| tabs.iter().find(|t| t.element.name == name);
    let (Some(chunk), Some(vertex)) = (find("chunk"), find("vertex")) else {
        return Err(Error::format(
            path,
            "a compressed PLY needs 'chunk' and 'vertex' elements",
        ));
    };
    let n = vertex.element.count as usize;
    let n_chunks = n.div_ceil(CHUNK);
    if chunk.element.count as usize != n_chunks {
        return Err(Error::format_at(
            path,
            "chunk",
            None,
            format!(
                "{} chunks for {n} splats; {n_chunks} expected (one per {CHUNK})",
                chunk.element.count
            ),
        ));
    }
    // Chunk bounds as f32, chunk-major: 12 or 18 per chunk.
    let has_color = chunk.element.property("min_r").is_some();
    let names: Vec<&str> = CHUNK_BOUNDS
        .iter()
        .chain(if has_color { &CHUNK_COLORS[..] } else { &[] })
        .copied()
        .collect();
    let cols: Vec<(usize, ScalarType)> = names
        .iter()
        .map(|nm| chunk.column(nm, path))
        .collect::<Result<_>>()?;
    let nb = cols.len();
    let mut bounds = vec![0f32; n_chunks * nb];
    for (c, row) in chunk.rows.chunks_exact(chunk.stride).enumerate() {
        for (j, &(off, t)) in cols.iter().enumerate() {
            bounds[c * nb + j] = t.read(&row[off..], big) as f32;
        }
    }
    let mut packed_cols = [0usize; 4];
    for (slot, nm) in packed_cols.iter_mut().zip(PACKED) {
        let (off, t) = vertex.column(nm, path)?;
        if t != ScalarType::U32 {
            return Err(Error::format_at(
                path,
                "vertex",
                Some(nm),
                format!("is {t:?}; the packed fields must be uint32"),
            ));
        }
        *slot = off;
    }
    let sh = match find("sh") {
        Some(t) => Some(sh_table(t, n, path)?),
        None => None,
    };
    let degree = sh.as_ref().map_or(0, |s| s.1);
    let k = sh_rest_count(degree);

    let mut s = Scene::zeroed(n, degree);
    let vstride = vertex.stride;
    let rd = |b: &[u8], off: usize| -> u32 {
        let mut a = [0u8; 4];
        a.copy_from_slice(&b[off..off + 4]);
        if big {
            u32::from_be_bytes(a)
        } else {
            u32::from_le_bytes(a)
        }
    };
    s.means
        .par_chunks_mut(3 * CHUNK)
        .zip(s.quats.par_chunks_mut(4 * CHUNK))
        .zip(s.log_scales.par_chunks_mut(3 * CHUNK))
        .zip(s.opacity_logits.par_chunks_mut(CHUNK))
        .zip(s.sh0.par_chunks_mut(3 * CHUNK))
        .zip(vertex.rows.par_chunks(vstride * CHUNK))
        .enumerate()
        .for_each(|(c, (((((m, q), ls), op), dc), rows))| {
            let b = &bounds[c * nb..(c + 1) * nb];
            for (i, row) in rows.chunks_exact(vstride).enumerate() {
                let p = unpack_111011(rd(row, packed_cols[0]));
                let sc = unpack_111011(rd(row, packed_cols[2]));
                for d in 0..3 {
                    m[i * 3 + d] = lerp(b[d], b[3 + d], p[d]);
                    ls[i * 3 + d] = lerp(b[6 + d], b[9 + d], sc[d]);
                }
                q[i * 4..i * 4 + 4].copy_from_slice(&unpack_rotation(rd(row, packed_cols[1])));
                let col = rd(row, packed_cols[3]);
                for d in 0..3 {
                    let v = unorm((col >> (24 - 8 * d)) & 0xff, 8);
                    let v = if has_color {
                        lerp(b[12 + d], b[15 + d], v)
                    } else {
                        v
                    };
                    dc[i * 3 + d] = (v - 0.5) / SH_C0;
                }
                op[i] = logit_unit(unorm(col & 0xff, 8));
            }
        });
    if let Some((t, _, cols)) = sh {
        s.sh_rest
            .par_chunks_mut(3 * k * CHUNK)
            .zip(t.rows.par_chunks(t.stride * CHUNK))
            .for_each(|(o, rows)| {
                for (orow, row) in o.chunks_exact_mut(3 * k).zip(rows.chunks_exact(t.stride)) {
                    for (v, &off) in orow.iter_mut().zip(&cols) {
                        *v = sh_value(row[off]);
                    }
                }
            });
    }
    Ok(s)
}

/// The `sh` element: (table, degree, byte offset of each memory slot j*3+c).
fn sh_table<'a>(
    t: &'a Table<'a>,
    n: usize,
    path: &Path,
) -> Result<(&'a Table<'a>, u8, Vec<usize>)> {
    if t.element.count as usize != n {
        return Err(Error::format_at(
            path,
            "sh",
            None,
            format!(
                "{} rows for {n} splats (one per splat expected)",
                t.element.count
            ),
        ));
    }
    let count = t.element.properties.len();
    let Some(degree) = count
        .is_multiple_of(3)
        .then(|| sh_degree_for_rest(count / 3))
        .flatten()
        .filter(|&d| d > 0)
    else {
        return Err(Error::format_at(
            path,
            "sh",
            None,
            format!("{count} properties is no SH degree (expected 9, 24, 45 or 72)"),
        ));
    };
    let k = sh_rest_count(degree);
    let mut cols = vec![0usize; 3 * k];
    for c in 0..3 {
        for j in 0..k {
            let name = format!("f_rest_{}", c * k + j);
            let (off, ty) = t.column(&name, path)?;
            if ty != ScalarType::U8 {
                return Err(Error::format_at(
                    path,
                    "sh",
                    Some(&name),
                    format!("is {ty:?}; expected uchar"),
                ));
            }
            cols[j * 3 + c] = off;
        }
    }
    Ok((t, degree, cols))
}

#[inline]
fn lerp(a: f32, b: f32, t: f32) -> f32 {
    a * (1.0 - t) + b * t
}

#[inline]
fn unorm(v: u32, bits: u32) -> f32 {
    let m = (1u32 << bits) - 1;
    (v & m) as f32 / m as f32
}

#[inline]
fn unpack_111011(v: u32) -> [f32; 3] {
    [unorm(v >> 21, 11), unorm(v >> 11, 10), unorm(v, 11)]
}

/// (w,x,y,z): the largest component sits at index `v >> 30`.
#[inline]
fn unpack_rotation(v: u32) -> [f32; 4] {
    let norm = std::f32::consts::SQRT_2;
    let a = (unorm(v >> 20, 10) - 0.5) * norm;
    let b = (unorm(v >> 10, 10) - 0.5) * norm;
    let c = (unorm(v, 10) - 0.5) * norm;
    let m = (1.0 - (a * a + b * b + c * c)).max(0.0).sqrt();
    match v >> 30 {
        0 => [m, a, b, c],
        1 => [a, m, b, c],
        2 => [a, b, m, c],
        _ => [a, b, c, m],
    }
}

#[inline]
fn sh_value(v: u8) -> f32 {
    let n = match v {
        0 => 0.0,
        255 => 1.0,
        _ => (v as f32 + 0.5) / 256.0,
    };
    (n - 0.5) * 8.0
}

/// Highest SH degree written: web viewers of this format stop at 3 bands (45 `f_rest`).
pub const MAX_WRITE_DEGREE: u8 = 3;

/// Gaussian order for writing: Morton (Z-order) code of the centre in 21-bit cells of the
/// scene's bounds, ties broken by index, so each 256-splat chunk is spatially compact and its
/// quantisation bounds tight (splat-transform sorts the same way before writing).
pub fn morton_order(means: &[f32]) -> Vec<u32> {
    let n = means.len() / 3;
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in means.chunks_exact(3) {
        for d in 0..3 {
            lo[d] = lo[d].min(p[d]);
            hi[d] = hi[d].max(p[d]);
        }
    }
    let cells = ((1u32 << 21) - 1) as f32;
    let scale: Vec<f32> = (0..3)
        .map(|d| {
            let r = hi[d] - lo[d];
            if r > 0.0 {
                cells / r
            } else {
                0.0
            }
        })
        .collect();
    let spread = |mut v: u64| -> u64 {
        v &= 0x1f_ffff;
        v = (v | v << 32) & 0x1f_0000_0000_ffff;
        v = (v | v << 16) & 0x1f_0000_ff00_00ff;
        v = (v | v << 8) & 0x100f_00f0_0f00_f00f;
        v = (v | v << 4) & 0x10c3_0c30_c30c_30c3;
        v = (v | v << 2) & 0x1249_2492_4924_9249;
        v
    };
    let mut keys: Vec<(u64, u32)> = means
        .par_chunks(3)
        .enumerate()
        .map(|(i, p)| {
            let c = |d: usize| ((p[d] - lo[d]) * scale[d]).clamp(0.0, cells) as u64;
            (
                spread(c(0)) | spread(c(1)) << 1 | spread(c(2)) << 2,
                i as u32,
            )
        })
        .collect();
    keys.par_sort_unstable();
    debug_assert_eq!(keys.len(), n);
    keys.into_iter().map(|(_, i)| i).collect()
}

#[inline]
fn pack_unorm(v: f32, bits: u32) -> u32 {
    let t = ((1u32 << bits) - 1) as f32;
    (v * t + 0.5).floor().clamp(0.0, t) as u32
}

#[inline]
fn normalize(x: f32, lo: f32, hi: f32) -> f32 {
    if x <= lo {
        0.0
    } else if x >= hi {
        1.0
    } else if hi - lo < 1e-5 {
        0.0
    } else {
        (x - lo) / (hi - lo)
    }
}

/// (w,x,y,z) as 2 bits of the largest component's index and three 10-bit components.
fn pack_rotation(q: &[f32]) -> u32 {
    let mut a = unit_quat(q);
    let mut largest = 0;
    for i in 1..4 {
        if a[i].abs() > a[largest].abs() {
            largest = i;
        }
    }
    if a[largest] < 0.0 {
        a = a.map(|v| -v);
    }
    let norm = std::f32::consts::FRAC_1_SQRT_2;
    let mut r = largest as u32;
    for (i, v) in a.iter().enumerate() {
        if i != largest {
            r = r << 10 | pack_unorm(v * norm + 0.5, 10);
        }
    }
    r
}

/// One chunk: 18 bounds and 4 packed words per splat, from the scene rows `rows`.
fn pack_chunk(s: &SceneView<'_>, rows: &[u32], bounds: &mut [f32], packed: &mut [u32]) {
    let mut lo = [f32::INFINITY; 9];
    let mut hi = [f32::NEG_INFINITY; 9];
    let col = |i: usize, d: usize| 0.5 + SH_C0 * s.sh0[i * 3 + d];
    for &r in rows {
        let i = r as usize;
        for d in 0..3 {
            let v = [s.means[i * 3 + d], s.log_scales[i * 3 + d], col(i, d)];
            for (k, v) in v.iter().enumerate() {
                lo[k * 3 + d] = lo[k * 3 + d].min(*v);
                hi[k * 3 + d] = hi[k * 3 + d].max(*v);
            }
        }
    }
    for d in 3..6 {
        lo[d] = lo[d].clamp(-20.0, 20.0);
        hi[d] = hi[d].clamp(-20.0, 20.0);
    }
    for (o, &r) in packed.chunks_exact_mut(4).zip(rows) {
        let i = r as usize;
        let nrm = |k: usize, d: usize, v: f32| normalize(v, lo[k * 3 + d], hi[k * 3 + d]);
        let p111011 = |k: usize, v: [f32; 3]| {
            pack_unorm(nrm(k, 0, v[0]), 11) << 21
                | pack_unorm(nrm(k, 1, v[1]), 10) << 11
                | pack_unorm(nrm(k, 2, v[2]), 11)
        };
        let m = &s.means[i * 3..i * 3 + 3];
        let l = &s.log_scales[i * 3..i * 3 + 3];
        o[0] = p111011(0, [m[0], m[1], m[2]]);
        o[1] = pack_rotation(&s.quats[i * 4..i * 4 + 4]);
        o[2] = p111011(1, [l[0], l[1], l[2]]);
        o[3] = pack_unorm(nrm(2, 0, col(i, 0)), 8) << 24
            | pack_unorm(nrm(2, 1, col(i, 1)), 8) << 16
            | pack_unorm(nrm(2, 2, col(i, 2)), 8) << 8
            | pack_unorm(sigmoid(s.opacity_logits[i]), 8);
    }
    // file order: min xyz, max xyz, min scale, max scale, min rgb, max rgb
    for (k, slot) in [0usize, 1, 2].iter().enumerate() {
        bounds[k * 6..k * 6 + 3].copy_from_slice(&lo[slot * 3..slot * 3 + 3]);
        bounds[k * 6 + 3..k * 6 + 6].copy_from_slice(&hi[slot * 3..slot * 3 + 3]);
    }
}

/// The bytes of a SuperSplat compressed PLY (splat-transform `write-compressed-ply.ts` layout):
/// Gaussians in Morton order, 256 per chunk, SH bands above degree 3 dropped.
pub fn encode(scene: &SceneView<'_>, generator: &str) -> Result<Vec<u8>> {
    check_finite(scene, "compressed PLY")?;
    let n = scene.len();
    if n > u32::MAX as usize {
        return Err(Error::InvalidArgument(format!(
            "cannot write a compressed PLY of {n} Gaussians"
        )));
    }
    let degree = scene.sh_degree.min(MAX_WRITE_DEGREE);
    let k = sh_rest_count(degree);
    let sk = scene.sh_rest_k();
    let order = morton_order(scene.means);
    let n_chunks = n.div_ceil(CHUNK);
    let mut bounds = vec![0f32; n_chunks * 18];
    let mut packed = vec![0u32; n * 4];
    bounds
        .par_chunks_mut(18)
        .zip(packed.par_chunks_mut(4 * CHUNK))
        .zip(order.par_chunks(CHUNK))
        .for_each(|((b, p), rows)| pack_chunk(scene, rows, b, p));
    let mut sh = vec![0u8; n * k * 3];
    if k > 0 {
        sh.par_chunks_mut(3 * k)
            .zip(order.par_iter())
            .for_each(|(o, &r)| {
                let row = &scene.sh_rest[r as usize * sk * 3..];
                for c in 0..3 {
                    for j in 0..k {
                        let v = row[j * 3 + c] / 8.0 + 0.5;
                        o[c * k + j] = (v * 256.0).trunc().clamp(0.0, 255.0) as u8;
                    }
                }
            });
    }
    let mut header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment Generated by {generator}\nelement chunk \
         {n_chunks}\n"
    );
    for p in CHUNK_BOUNDS[..6]
        .iter()
        .chain(&CHUNK_BOUNDS[6..])
        .chain(&CHUNK_COLORS)
    {
        header.push_str(&format!("property float {p}\n"));
    }
    header.push_str(&format!("element vertex {n}\n"));
    for p in PACKED {
        header.push_str(&format!("property uint {p}\n"));
    }
    if k > 0 {
        header.push_str(&format!("element sh {n}\n"));
        for i in 0..3 * k {
            header.push_str(&format!("property uchar f_rest_{i}\n"));
        }
    }
    header.push_str("end_header\n");
    let mut out = Vec::with_capacity(header.len() + bounds.len() * 4 + packed.len() * 4 + sh.len());
    out.extend_from_slice(header.as_bytes());
    out.extend(bounds.iter().flat_map(|v| v.to_le_bytes()));
    out.extend(packed.iter().flat_map(|v| v.to_le_bytes()));
    out.extend_from_slice(&sh);
    Ok(out)
}

/// Write a SuperSplat compressed PLY, atomically.
pub fn write(path: &Path, scene: &SceneView<'_>) -> Result<()> {
    let bytes = encode(scene, concat!("morphgs ", env!("CARGO_PKG_VERSION")))?;
    atomic_write(path, |w| w.write_all(&bytes))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bit_fields_unpack_to_unit_range() {
        assert_eq!(unpack_111011(u32::MAX), [1.0, 1.0, 1.0]);
        assert_eq!(unpack_111011(0), [0.0, 0.0, 0.0]);
        // identity rotation: largest is w (index 0), others at the 10-bit midpoint
        let mid = 511u32; // (511/1023 - 0.5) * sqrt2 ~ -0.0007
        let q = unpack_rotation(mid << 20 | mid << 10 | mid);
        assert!((q[0] - 1.0).abs() < 1e-5 && q[1].abs() < 1e-3, "{q:?}");
        assert_eq!(sh_value(0), -4.0);
        assert_eq!(sh_value(255), 4.0);
    }
}
