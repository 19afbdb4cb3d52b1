//! antimatter15 `.splat`: a headerless array of 32-byte records
//! (antimatter15/splat `convert.py`, playcanvas/splat-transform `read-splat.ts`):
//!
//! | bytes | field |
//! |---|---|
//! | 0..12  | position, 3 x f32 little-endian |
//! | 12..24 | linear scale, 3 x f32 |
//! | 24..28 | RGBA u8: colour = 0.5 + C0*dc, alpha = sigmoid(logit) |
//! | 28..32 | rotation u8 (w,x,y,z), stored as q*128+128 |
//!
//! No SH, same axes as the PLY. With no magic, [`looks_like_splat`] checks the content.
use std::path::Path;

use rayon::prelude::*;

use super::{check_finite, finish, logit_u8, sigmoid, to_u8, unit_quat, ROWS_PER_TASK};
use crate::error::{Error, Result};
use crate::ply::{atomic_write, LoadReport, OnInvalid};
use crate::scene::{Scene, SceneView, SH_C0};

pub const RECORD_BYTES: usize = 32;
/// Records checked when sniffing a file without magic.
const SNIFF_RECORDS: usize = 4096;
/// Larger positions or scales are taken as evidence that the bytes are not a `.splat`.
const SNIFF_MAX_ABS: f32 = 1e7;

#[inline]
fn f32_at(b: &[u8], off: usize) -> f32 {
    let mut a = [0u8; 4];
    a.copy_from_slice(&b[off..off + 4]);
    f32::from_le_bytes(a)
}

/// Why `bytes` are not a plausible `.splat`, or `None` when they are: a non-zero multiple of 32
/// whose first records hold finite positions and finite, non-negative scales of sane magnitude.
pub fn looks_like_splat(bytes: &[u8]) -> Option<String> {
    if bytes.is_empty() || !bytes.len().is_multiple_of(RECORD_BYTES) {
        return Some(format!(
            "its size ({} bytes) is not a non-zero multiple of 32",
            bytes.len()
        ));
    }
    for (i, r) in bytes
        .chunks_exact(RECORD_BYTES)
        .take(SNIFF_RECORDS)
        .enumerate()
    {
        for d in 0..3 {
            let p = f32_at(r, d * 4);
            if !p.is_finite() || p.abs() > SNIFF_MAX_ABS {
                return Some(format!("record {i} has position {p}"));
            }
            let s = f32_at(r, 12 + d * 4);
            if !s.is_finite() || !(0.0..=SNIFF_MAX_ABS).contains(&s) {
                return Some(format!("record {i} has scale {s}"));
            }
        }
    }
    None
}

/// Decode `.splat` bytes (a multiple of 32) into a scene.
pub fn decode(bytes: &[u8]) -> Scene {
    let n = bytes.len() / RECORD_BYTES;
    let mut s = Scene::zeroed(n, 0);
    let src = &bytes[..n * RECORD_BYTES];
    s.means
        .par_chunks_mut(3 * ROWS_PER_TASK)
        .zip(s.quats.par_chunks_mut(4 * ROWS_PER_TASK))
        .zip(s.log_scales.par_chunks_mut(3 * ROWS_PER_TASK))
        .zip(s.opacity_logits.par_chunks_mut(ROWS_PER_TASK))
        .zip(s.sh0.par_chunks_mut(3 * ROWS_PER_TASK))
        .zip(src.par_chunks(RECORD_BYTES * ROWS_PER_TASK))
        .for_each(|(((((m, q), ls), op), dc), src)| {
            for (i, r) in src.chunks_exact(RECORD_BYTES).enumerate() {
                for d in 0..3 {
                    m[i * 3 + d] = f32_at(r, d * 4);
                    ls[i * 3 + d] = f32_at(r, 12 + d * 4).ln();
                    dc[i * 3 + d] = (r[24 + d] as f32 / 255.0 - 0.5) / SH_C0;
                }
                op[i] = logit_u8(r[27]);
                for c in 0..4 {
                    q[i * 4 + c] = (r[28 + c] as f32 - 128.0) / 128.0;
                }
            }
        });
    s
}

/// Read an antimatter15 `.splat` file.
pub fn read(path: &Path, on_invalid: OnInvalid) -> Result<(Scene, LoadReport)> {
    let bytes = super::read_file(path)?;
    if let Some(why) = looks_like_splat(&bytes) {
        return Err(Error::format(
            path,
            format!("not an antimatter15 .splat file: {why}"),
        ));
    }
    finish(decode(&bytes), "splat", "splat", path, on_invalid)
}

/// Encode a scene as `.splat` records (colour and alpha rounded to 8 bits, rotation normalised).
pub fn encode(scene: &SceneView<'_>) -> Result<Vec<u8>> {
    check_finite(scene, ".splat")?;
    let n = scene.len();
    let mut out = vec![0u8; n * RECORD_BYTES];
    out.par_chunks_mut(RECORD_BYTES * ROWS_PER_TASK)
        .enumerate()
        .for_each(|(t, chunk)| {
            let first = t * ROWS_PER_TASK;
            for (j, r) in chunk.chunks_exact_mut(RECORD_BYTES).enumerate() {
                let i = first + j;
                for d in 0..3 {
                    r[d * 4..d * 4 + 4].copy_from_slice(&scene.means[i * 3 + d].to_le_bytes());
                    let s = scene.log_scales[i * 3 + d].exp();
                    r[12 + d * 4..16 + d * 4].copy_from_slice(&s.to_le_bytes());
                    r[24 + d] = to_u8((0.5 + SH_C0 * scene.sh0[i * 3 + d]) * 255.0);
                }
                r[27] = to_u8(sigmoid(scene.opacity_logits[i]) * 255.0);
                let q = unit_quat(&scene.quats[i * 4..i * 4 + 4]);
                for c in 0..4 {
                    r[28 + c] = to_u8(q[c] * 128.0 + 128.0);
                }
            }
        });
    Ok(out)
}

/// Write a scene as antimatter15 `.splat`, atomically. Higher SH bands are dropped (the format
/// has none).
pub fn write(path: &Path, scene: &SceneView<'_>) -> Result<()> {
    let bytes = encode(scene)?;
    atomic_write(path, |w| w.write_all(&bytes))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn garbage_with_the_right_size_is_not_a_splat() {
        let mut b = vec![0u8; 64];
        b[12..16].copy_from_slice(&f32::NAN.to_le_bytes());
        assert!(looks_like_splat(&b).is_some());
        assert!(looks_like_splat(&[0u8; 33]).is_some());
        assert!(looks_like_splat(&[]).is_some());
        assert!(looks_like_splat(&[0u8; 32]).is_none());
    }

    #[test]
    fn encode_then_decode_is_within_a_byte() {
        let q = unit_quat(&[0.9, 0.1, -0.3, 0.2]);
        let view = SceneView::new(
            &[1.0, -2.0, 3.5],
            &q,
            &[-3.0, -4.0, -5.0],
            &[0.3],
            &[0.1, -0.2, 0.5],
            &[],
            0,
        )
        .expect("view");
        let back = decode(&encode(&view).expect("encode"));
        assert_eq!(back.means, [1.0, -2.0, 3.5]);
        for d in 0..3 {
            assert!((back.log_scales[d] - view.log_scales[d]).abs() < 1e-6);
            let c0 = 0.5 + SH_C0 * view.sh0[d];
            let c1 = 0.5 + SH_C0 * back.sh0[d];
            assert!((c0 - c1).abs() <= 0.5 / 255.0 + 1e-6);
        }
        let nq = unit_quat(&back.quats);
        let dot: f32 = (0..4).map(|c| nq[c] * q[c]).sum();
        assert!(dot.abs() > 0.9999, "{dot}");
    }
}
