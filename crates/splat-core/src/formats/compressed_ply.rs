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

use super::{finish, logit_unit};
use crate::error::{Error, Result};
use crate::ply::{Element, Encoding, Header, LoadReport, OnInvalid, PropertyKind, ScalarType};
use crate::scene::{sh_degree_for_rest, sh_rest_count, Scene, SH_C0};

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
