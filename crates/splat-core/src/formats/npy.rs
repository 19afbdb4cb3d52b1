//! A strict reader for NumPy `.npy` files (format versions 1-3), enough for per-attribute
//! scene folders such as SceneSplat's.
//!
//! Layout (numpy `lib/format.py`): the magic `\x93NUMPY`, a major and minor version byte, the
//! header length (u16 little-endian in v1, u32 in v2/v3), then an ASCII Python dict literal
//! `{'descr': '<f4', 'fortran_order': False, 'shape': (N, 3), }` padded with spaces and a
//! newline, then the raw array bytes. The declared shape and dtype must account for exactly the
//! bytes that follow, which is checked before anything is allocated.
use std::path::Path;

use crate::error::{Error, Result};

const MAGIC: &[u8; 6] = b"\x93NUMPY";
/// Header dicts are short (numpy pads them to 64 bytes); refuse absurd lengths.
const MAX_HEADER: usize = 1 << 16;

/// Element types the reader understands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dtype {
    F16,
    F32,
    F64,
    U8,
    I8,
}

impl Dtype {
    fn size(self) -> usize {
        match self {
            Dtype::F16 => 2,
            Dtype::F32 => 4,
            Dtype::F64 => 8,
            Dtype::U8 | Dtype::I8 => 1,
        }
    }

    /// True for floating-point types.
    pub fn is_float(self) -> bool {
        matches!(self, Dtype::F16 | Dtype::F32 | Dtype::F64)
    }
}

/// A decoded array: its shape (C order) and values.
#[derive(Debug, Clone)]
pub struct Npy {
    pub dtype: Dtype,
    pub shape: Vec<usize>,
    /// Values widened to f32 in C (row-major) order.
    pub values: Vec<f32>,
}

impl Npy {
    /// Number of rows (the first dimension; 1 for a 0-d array).
    pub fn rows(&self) -> usize {
        self.shape.first().copied().unwrap_or(1)
    }
}

/// Read and decode the `.npy` file at `path`. `field` names the array in error messages.
pub fn read(path: &Path, field: &str) -> Result<Npy> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode(&bytes, path, field)
}

fn fail(path: &Path, field: &str, msg: impl Into<String>) -> Error {
    Error::format_at(path, field, None, msg)
}

/// Decode `.npy` bytes (`path` and `field` only name them in errors).
pub fn decode(bytes: &[u8], path: &Path, field: &str) -> Result<Npy> {
    if bytes.len() < 10 || &bytes[..6] != MAGIC {
        return Err(fail(
            path,
            field,
            "not a NumPy .npy file (missing the \\x93NUMPY magic)",
        ));
    }
    let major = bytes[6];
    let (hlen, start) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err(fail(path, field, "truncated .npy header"));
            }
            (
                u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
                12,
            )
        }
        v => {
            return Err(fail(
                path,
                field,
                format!("unsupported .npy format version {v} (1-3 are)"),
            ))
        }
    };
    if hlen > MAX_HEADER || start + hlen > bytes.len() {
        return Err(fail(
            path,
            field,
            format!(
                "the .npy header claims {hlen} bytes but the file has {}",
                bytes.len()
            ),
        ));
    }
    let header = std::str::from_utf8(&bytes[start..start + hlen])
        .map_err(|_| fail(path, field, "the .npy header is not text"))?;
    let descr = dict_value(header, "descr")
        .ok_or_else(|| fail(path, field, "the .npy header has no 'descr'"))?;
    let fortran = dict_value(header, "fortran_order")
        .ok_or_else(|| fail(path, field, "the .npy header has no 'fortran_order'"))?;
    let shape_txt = dict_value(header, "shape")
        .ok_or_else(|| fail(path, field, "the .npy header has no 'shape'"))?;
    let (dtype, big) = parse_descr(descr).ok_or_else(|| {
        fail(
            path,
            field,
            format!(
                "dtype {descr} is not supported (float16/32/64, uint8 or int8 are; structured \
                 and object arrays are not)"
            ),
        )
    })?;
    let fortran = match fortran.trim() {
        "False" => false,
        "True" => true,
        other => {
            return Err(fail(
                path,
                field,
                format!("fortran_order is {other}, not True or False"),
            ))
        }
    };
    let shape = parse_shape(shape_txt)
        .ok_or_else(|| fail(path, field, format!("cannot parse shape {shape_txt}")))?;
    let count = shape
        .iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .ok_or_else(|| fail(path, field, format!("shape {shape:?} overflows")))?;
    let need = count
        .checked_mul(dtype.size())
        .ok_or_else(|| fail(path, field, format!("shape {shape:?} overflows")))?;
    let body = &bytes[start + hlen..];
    if body.len() != need {
        return Err(fail(
            path,
            field,
            format!(
                "the header declares shape {shape:?} of {descr} ({need} bytes) but {} bytes \
                 follow it ({})",
                body.len(),
                if body.len() < need {
                    "truncated file or lying header"
                } else {
                    "trailing data"
                }
            ),
        ));
    }
    let mut values = widen(body, dtype, big);
    if fortran && shape.len() > 1 {
        values = fortran_to_c(&values, &shape);
    }
    Ok(Npy {
        dtype,
        shape,
        values,
    })
}

/// The text after `'key':` up to the next top-level comma or closing brace.
fn dict_value<'a>(header: &'a str, key: &str) -> Option<&'a str> {
    let pat = format!("'{key}'");
    let at = header.find(&pat)? + pat.len();
    let rest = header[at..].trim_start().strip_prefix(':')?.trim_start();
    if let Some(inner) = rest.strip_prefix('(') {
        let end = inner.find(')')?;
        return Some(&rest[..end + 2]);
    }
    if let Some(inner) = rest.strip_prefix('\'') {
        let end = inner.find('\'')?;
        return Some(&inner[..end]);
    }
    let end = rest.find([',', '}'])?;
    Some(rest[..end].trim())
}

/// `'<f4'` -> (F32, big-endian?). `|` and `=` mean native (little-endian here).
fn parse_descr(d: &str) -> Option<(Dtype, bool)> {
    let (order, ty) = d.split_at(1.min(d.len()));
    let big = match order {
        "<" | "|" | "=" => false,
        ">" => true,
        _ => return None,
    };
    let t = match ty {
        "f2" => Dtype::F16,
        "f4" => Dtype::F32,
        "f8" => Dtype::F64,
        "u1" => Dtype::U8,
        "i1" => Dtype::I8,
        _ => return None,
    };
    Some((t, big))
}

/// `(12, 3)`, `(12,)` or `()`.
fn parse_shape(s: &str) -> Option<Vec<usize>> {
    let inner = s.trim().strip_prefix('(')?.strip_suffix(')')?;
    inner
        .split(',')
        .map(str::trim)
        .filter(|t| !t.is_empty())
        .map(|t| t.trim_end_matches('L').parse::<usize>().ok())
        .collect()
}

fn widen(body: &[u8], dtype: Dtype, big: bool) -> Vec<f32> {
    match dtype {
        Dtype::U8 => body.iter().map(|&b| b as f32).collect(),
        Dtype::I8 => body.iter().map(|&b| b as i8 as f32).collect(),
        Dtype::F16 => body
            .chunks_exact(2)
            .map(|c| {
                let a = [c[0], c[1]];
                f16_to_f32(if big {
                    u16::from_be_bytes(a)
                } else {
                    u16::from_le_bytes(a)
                })
            })
            .collect(),
        Dtype::F32 => body
            .chunks_exact(4)
            .map(|c| {
                let a = [c[0], c[1], c[2], c[3]];
                if big {
                    f32::from_be_bytes(a)
                } else {
                    f32::from_le_bytes(a)
                }
            })
            .collect(),
        Dtype::F64 => body
            .chunks_exact(8)
            .map(|c| {
                let mut a = [0u8; 8];
                a.copy_from_slice(c);
                (if big {
                    f64::from_be_bytes(a)
                } else {
                    f64::from_le_bytes(a)
                }) as f32
            })
            .collect(),
    }
}

/// Reorder a column-major array of `shape` into row-major order.
fn fortran_to_c(v: &[f32], shape: &[usize]) -> Vec<f32> {
    let n = v.len();
    let mut out = vec![0f32; n];
    let nd = shape.len();
    let mut idx = vec![0usize; nd];
    for (c_pos, slot) in out.iter_mut().enumerate() {
        // c_pos -> multi-index (row-major), then its column-major offset
        let mut rem = c_pos;
        for d in (0..nd).rev() {
            idx[d] = rem % shape[d];
            rem /= shape[d];
        }
        let mut f = 0;
        for d in (0..nd).rev() {
            f = f * shape[d] + idx[d];
        }
        *slot = v[f];
    }
    out
}

/// IEEE half to single precision (subnormals, infinities and NaN included).
pub fn f16_to_f32(h: u16) -> f32 {
    let sign = ((h >> 15) as u32) << 31;
    let exp = ((h >> 10) & 0x1f) as u32;
    let man = (h & 0x3ff) as u32;
    let bits = match (exp, man) {
        (0, 0) => sign,
        (0, m) => {
            // subnormal: value = m * 2^-24
            let v = m as f32 * (1.0 / 16_777_216.0);
            return if sign != 0 { -v } else { v };
        }
        (0x1f, 0) => sign | 0x7f80_0000,
        (0x1f, m) => sign | 0x7fc0_0000 | (m << 13),
        (e, m) => sign | ((e + 112) << 23) | (m << 13),
    };
    f32::from_bits(bits)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn npy(descr: &str, shape: &str, fortran: bool, body: &[u8]) -> Vec<u8> {
        let mut h = format!(
            "{{'descr': '{descr}', 'fortran_order': {}, 'shape': {shape}, }}",
            if fortran { "True" } else { "False" }
        );
        while (10 + h.len() + 1) % 64 != 0 {
            h.push(' ');
        }
        h.push('\n');
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&[1, 0]);
        out.extend_from_slice(&(h.len() as u16).to_le_bytes());
        out.extend_from_slice(h.as_bytes());
        out.extend_from_slice(body);
        out
    }

    #[test]
    fn decodes_c_and_fortran_order() {
        let body: Vec<u8> = [1f32, 2., 3., 4., 5., 6.]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let p = Path::new("a.npy");
        let c = decode(&npy("<f4", "(2, 3)", false, &body), p, "a").expect("c");
        assert_eq!(c.shape, vec![2, 3]);
        assert_eq!(c.values, vec![1., 2., 3., 4., 5., 6.]);
        let f = decode(&npy("<f4", "(2, 3)", true, &body), p, "a").expect("f");
        assert_eq!(f.values, vec![1., 3., 5., 2., 4., 6.]);
    }

    #[test]
    fn lying_shapes_fail_before_allocating() {
        let p = Path::new("a.npy");
        let err = decode(
            &npy("<f4", "(1000000000000, 3)", false, &[0; 12]),
            p,
            "coord",
        )
        .expect_err("lie")
        .to_string();
        assert!(err.contains("truncated"), "{err}");
        let err = decode(&npy("<f4", "(18446744073709551615, 3)", false, &[]), p, "x")
            .expect_err("overflow")
            .to_string();
        assert!(err.contains("overflows"), "{err}");
    }

    #[test]
    fn half_floats() {
        assert_eq!(f16_to_f32(0x3c00), 1.0);
        assert_eq!(f16_to_f32(0xc000), -2.0);
        assert_eq!(f16_to_f32(0x7bff), 65504.0);
        assert_eq!(f16_to_f32(0x0001), 2f32.powi(-24));
        assert!(f16_to_f32(0x7c00).is_infinite());
    }
}
