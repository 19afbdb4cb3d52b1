//! AVX-512 forms of three steps of the projection block ([`super::block`]): the depth test, the
//! loads into lanes and the transposition of lanes into splat rows, each giving the plain
//! code's values. Called only from the build compiled for AVX-512, on a CPU that has it.
use super::block::{Rows, BLOCK};
use std::arch::x86_64::*;

/// [`super::Projector::any_in_depth`]: the same float64 operations in the same order (no
/// fused multiply-add), 8 lanes per vector (LLVM's own code for it read the lane arrays
/// across their stores, stalling on store forwarding).
#[target_feature(enable = "avx512f")]
#[inline]
pub(super) unsafe fn any_in_depth(
    rot: &[f64; 3],
    tr: f64,
    near: f64,
    far: f64,
    mean: &[[f32; BLOCK]; 3],
) -> bool {
    let mut any = 0u8;
    for h in 0..2 {
        // SAFETY: lanes 8 h .. 8 h + 8 of each 16-lane array
        let ld =
            |c: usize| _mm512_cvtps_pd(unsafe { _mm256_loadu_ps(mean[c].as_ptr().add(8 * h)) });
        let z = _mm512_add_pd(
            _mm512_add_pd(
                _mm512_add_pd(
                    _mm512_mul_pd(_mm512_set1_pd(rot[0]), ld(0)),
                    _mm512_mul_pd(_mm512_set1_pd(rot[1]), ld(1)),
                ),
                _mm512_mul_pd(_mm512_set1_pd(rot[2]), ld(2)),
            ),
            _mm512_set1_pd(tr),
        );
        let m = _mm512_cmp_pd_mask::<_CMP_GT_OQ>(z, _mm512_set1_pd(near));
        any |= _mm512_mask_cmp_pd_mask::<_CMP_LT_OQ>(m, z, _mm512_set1_pd(far));
    }
    any != 0
}

/// [`super::block::deinterleave`] of a full block `v` (16 Gaussians of C = 1, 3 or 4 values) in
/// two-source permutes.
#[target_feature(enable = "avx512f")]
#[inline]
pub(super) unsafe fn deinterleave<const C: usize>(v: &[f32], dst: &mut [[f32; BLOCK]; C]) {
    assert_eq!(v.len(), C * BLOCK);
    // SAFETY: v holds C * 16 floats (asserted); the index tables hold 16 i32 each; each
    // `dst[c]` holds 16 floats
    let ld = |k: usize| unsafe { _mm512_loadu_ps(v.as_ptr().add(16 * k)) };
    let ix = |t: &[i32; 16]| unsafe { _mm512_loadu_epi32(t.as_ptr()) };
    let st = |d: &mut [f32; BLOCK], x: __m512| unsafe { _mm512_storeu_ps(d.as_mut_ptr(), x) };
    match C {
        1 => st(&mut dst[0], ld(0)),
        3 => {
            let (a, b, c) = (ld(0), ld(1), ld(2));
            for (d, [i1, i2]) in dst.iter_mut().zip(&IDX3) {
                let t = _mm512_permutex2var_ps(a, ix(i1), b);
                st(d, _mm512_permutex2var_ps(t, ix(i2), c));
            }
        }
        4 => {
            let (a, b, c, e) = (ld(0), ld(1), ld(2), ld(3));
            for (d, i) in dst.iter_mut().zip(&IDX4) {
                let lo = _mm512_permutex2var_ps(a, ix(i), b);
                let hi = _mm512_permutex2var_ps(c, ix(i), e);
                st(d, _mm512_mask_blend_ps(0xFF00, lo, hi));
            }
        }
        _ => unreachable!("deinterleave of {C} values"),
    }
}

/// Value c of lane l of a 3-value block is at 3 l + c: lanes up to 10 come from the first
/// two vectors (first table), the others from the third (second table, indices 16 + p - 32).
const IDX3: [[[i32; 16]; 2]; 3] = [idx3(0), idx3(1), idx3(2)];
const fn idx3(c: usize) -> [[i32; 16]; 2] {
    let mut o = [[0i32; 16]; 2];
    let mut l = 0;
    while l < 16 {
        let p = 3 * l + c;
        if p < 32 {
            o[0][l] = p as i32;
            o[1][l] = l as i32;
        } else {
            o[1][l] = (p - 16) as i32;
        }
        l += 1;
    }
    o
}

/// Value c of lane l of a 4-value block is at 4 l + c: lanes 0-7 from the first two
/// vectors, lanes 8-15 from the last two, the same indices modulo 32.
const IDX4: [[i32; 16]; 4] = [idx4(0), idx4(1), idx4(2), idx4(3)];
const fn idx4(c: usize) -> [i32; 16] {
    let mut o = [0i32; 16];
    let mut l = 0;
    while l < 16 {
        o[l] = ((4 * l + c) % 32) as i32;
        l += 1;
    }
    o
}

/// [`super::block::transpose`] in 64 shuffles (unpacks of floats, then of pairs, then 128-bit
/// blocks twice).
#[target_feature(enable = "avx512f")]
#[inline]
pub(super) unsafe fn transpose(f: &[[f32; BLOCK]; 16], rows: &mut Rows) {
    // SAFETY: each `f[c]` holds 16 floats
    let r: [__m512; 16] = std::array::from_fn(|c| unsafe { _mm512_loadu_ps(f[c].as_ptr()) });
    let mut t = [_mm512_setzero_ps(); 16];
    for i in 0..8 {
        t[2 * i] = _mm512_unpacklo_ps(r[2 * i], r[2 * i + 1]);
        t[2 * i + 1] = _mm512_unpackhi_ps(r[2 * i], r[2 * i + 1]);
    }
    let pd = |v: __m512| _mm512_castps_pd(v);
    let ps = |v: __m512d| _mm512_castpd_ps(v);
    let mut u = [_mm512_setzero_ps(); 16];
    for i in 0..4 {
        let b = 4 * i;
        u[b] = ps(_mm512_unpacklo_pd(pd(t[b]), pd(t[b + 2])));
        u[b + 1] = ps(_mm512_unpackhi_pd(pd(t[b]), pd(t[b + 2])));
        u[b + 2] = ps(_mm512_unpacklo_pd(pd(t[b + 1]), pd(t[b + 3])));
        u[b + 3] = ps(_mm512_unpackhi_pd(pd(t[b + 1]), pd(t[b + 3])));
    }
    // u[4 i + j] holds, in each 128-bit block, column j of rows 4 i .. 4 i + 4
    for h in 0..2 {
        for j in 0..4 {
            let (a, b) = (u[8 * h + j], u[8 * h + 4 + j]);
            t[8 * h + j] = _mm512_shuffle_f32x4::<0x88>(a, b);
            t[8 * h + 4 + j] = _mm512_shuffle_f32x4::<0xdd>(a, b);
        }
    }
    for j in 0..8 {
        let (a, b) = (t[j], t[8 + j]);
        let lo = _mm512_shuffle_f32x4::<0x88>(a, b);
        let hi = _mm512_shuffle_f32x4::<0xdd>(a, b);
        // SAFETY: each row holds 16 floats, 64-byte aligned (`Rows` is)
        unsafe {
            _mm512_store_ps(rows.0[j].as_mut_ptr(), lo);
            _mm512_store_ps(rows.0[8 + j].as_mut_ptr(), hi);
        }
    }
}
