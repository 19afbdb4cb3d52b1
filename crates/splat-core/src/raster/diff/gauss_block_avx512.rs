//! AVX-512 loads of a per-Gaussian block ([`super::gauss_block`]): each Gaussian's inputs
//! gathered into 16-float rows by a few masked loads (its mean, quaternion, scales, logit and
//! splat conic in one row; its summed slots, already one aligned row; its SH coefficients, up
//! to three rows), and each 16 rows turned into 16 lane vectors by a 16x16 transpose in
//! registers, instead of one scalar load and store per value and lane.
//!
//! Only moves: every value reaches the lane the scalar [`super::gauss_block::InLanes::set`]
//! puts it in, so the bits are the scalar path's (the tests compare the AVX-512 build against
//! the scalar reference). The gradients still leave lane by lane (`Scatter::put_lane`): the
//! same transposes with masked read-modify-writes were slower (docs/backward.md, seventh pass).
//!
//! The masked loads address a row at `entry - k` so that the entry's values land in lanes k..
//! of the row: only the mask's lanes are read (AVX-512 suppresses the faults and the accesses
//! of masked-off lanes), and those lie inside the buffers.
use std::arch::x86_64::*;

use super::gauss_block::{InLanes, Lane, BLOCK};
use super::gauss_bwd::GaussCtx;
use super::project::Splat;
use super::slots::slot;
use super::slots::Sums;

/// A 16x16 float matrix held as 16 rows.
type Rows = [__m512; BLOCK];

/// Transpose `r` in place (row i lane k <-> row k lane i): 64 shuffles.
#[inline]
#[target_feature(enable = "avx512f")]
pub(super) fn transpose16(r: &mut Rows) {
    // rows 2i, 2i+1 interleaved within each 128-bit lane
    let mut t = [_mm512_setzero_ps(); BLOCK];
    for i in 0..8 {
        t[2 * i] = _mm512_unpacklo_ps(r[2 * i], r[2 * i + 1]);
        t[2 * i + 1] = _mm512_unpackhi_ps(r[2 * i], r[2 * i + 1]);
    }
    // u[4g + j], 128-bit lane m: value 4m + j of rows 4g..4g+4
    let mut u = [_mm512_setzero_ps(); BLOCK];
    let pd = _mm512_castps_pd;
    let ps = _mm512_castpd_ps;
    for g in 0..4 {
        let (t0, t1, t2, t3) = (t[4 * g], t[4 * g + 1], t[4 * g + 2], t[4 * g + 3]);
        u[4 * g] = ps(_mm512_unpacklo_pd(pd(t0), pd(t2)));
        u[4 * g + 1] = ps(_mm512_unpackhi_pd(pd(t0), pd(t2)));
        u[4 * g + 2] = ps(_mm512_unpacklo_pd(pd(t1), pd(t3)));
        u[4 * g + 3] = ps(_mm512_unpackhi_pd(pd(t1), pd(t3)));
    }
    // value 4m + j of all rows: 128-bit lane m of u[j], u[4 + j], u[8 + j], u[12 + j]
    for j in 0..4 {
        let v_even = _mm512_shuffle_f32x4::<0x88>(u[j], u[4 + j]);
        let v_odd = _mm512_shuffle_f32x4::<0xDD>(u[j], u[4 + j]);
        let w_even = _mm512_shuffle_f32x4::<0x88>(u[8 + j], u[12 + j]);
        let w_odd = _mm512_shuffle_f32x4::<0xDD>(u[8 + j], u[12 + j]);
        r[j] = _mm512_shuffle_f32x4::<0x88>(v_even, w_even);
        r[8 + j] = _mm512_shuffle_f32x4::<0xDD>(v_even, w_even);
        r[4 + j] = _mm512_shuffle_f32x4::<0x88>(v_odd, w_odd);
        r[12 + j] = _mm512_shuffle_f32x4::<0xDD>(v_odd, w_odd);
    }
}

/// A mask of lanes [lo, hi).
#[inline(always)]
fn lanes(lo: usize, hi: usize) -> __mmask16 {
    (((1u32 << hi) - 1) & !((1u32 << lo) - 1)) as __mmask16
}

/// Row lanes [k, k + len) from `p[0..len]` (the other lanes of `row` kept).
///
/// # Safety
/// `p[0..len]` is readable; k + len <= 16.
#[inline]
#[target_feature(enable = "avx512f")]
unsafe fn put(row: __m512, k: usize, len: usize, p: *const f32) -> __m512 {
    // SAFETY: only lanes k..k + len are read, at p[0..len] (the caller's contract)
    unsafe { _mm512_mask_loadu_ps(row, lanes(k, k + len), p.wrapping_sub(k)) }
}

/// Store lane vectors `r` into `dst` (pairwise).
#[inline]
#[target_feature(enable = "avx512f")]
fn store_lanes(r: &[__m512], dst: &mut [Lane]) {
    for (d, v) in dst.iter_mut().zip(r) {
        // SAFETY: a Lane holds 16 floats
        unsafe { _mm512_storeu_ps(d.as_mut_ptr(), *v) };
    }
}

/// `Lane`s as one flat slice (an array of lane arrays is contiguous).
fn flat<const A: usize, const B: usize>(v: &mut [[Lane; B]; A]) -> &mut [Lane] {
    v.as_flattened_mut()
}

/// Load the block's inputs as [`InLanes::set`] does for lanes 0..n (Gaussians `ids`, splats
/// `ss`, summed slots `acc.get(pos)`); lanes n.. get zeros (computed, never read).
///
/// # Safety
/// The CPU has AVX-512F; every id is a Gaussian of `ctx.scene` (whose buffers the scene's
/// validation sized) and every position indexes `acc`.
#[inline]
#[target_feature(enable = "avx512f")]
pub(super) unsafe fn load_block(
    ctx: &GaussCtx<'_>,
    g: &mut InLanes,
    ss: &[Splat],
    ids: &[u32],
    pos: &[u32],
    acc: Sums<'_>,
) {
    let sc = ctx.scene;
    let n = ss.len().min(ids.len()).min(pos.len()).min(BLOCK);
    let zero = _mm512_setzero_ps();
    // mean 0..3, quaternion 3..7, scale 7..10, logit 10, conic 11..14
    let mut r = [zero; BLOCK];
    for l in 0..n {
        let i = ids[l] as usize;
        // SAFETY: Gaussian i's entries of buffers sized for the scene (the caller's
        // contract), and splat l's conic.
        unsafe {
            let mut v = put(zero, 0, 3, sc.means.as_ptr().add(i * 3));
            v = put(v, 3, 4, sc.quats.as_ptr().add(i * 4));
            v = put(v, 7, 3, ctx.scales.as_ptr().add(i * 3));
            v = put(v, 10, 1, sc.opacity_logits.as_ptr().add(i));
            r[l] = put(v, 11, 3, ss[l].conic.as_ptr());
        }
    }
    transpose16(&mut r);
    store_lanes(&r[0..3], &mut g.mean);
    store_lanes(&r[3..7], &mut g.q);
    store_lanes(&r[7..10], &mut g.scale);
    store_lanes(&r[10..11], std::slice::from_mut(&mut g.logit));
    store_lanes(&r[11..14], &mut g.conic);

    // the summed slots: one aligned row each
    let mut r = [zero; BLOCK];
    for l in 0..n {
        let p = pos[l] as usize;
        // zeros where no slot was added (as `Sums::get`)
        let m: __mmask16 = if acc.touched[p] != 0 { 0xFFFF } else { 0 };
        // SAFETY: p indexes the sums (the caller's contract; `touched` has the same length);
        // an AccRow is 64 aligned bytes.
        r[l] = unsafe { _mm512_maskz_load_ps(m, acc.acc.get_unchecked(p).0.as_ptr()) };
    }
    transpose16(&mut r);
    store_lanes(&r[..slot::LEN], &mut g.acc);

    if ctx.colors.is_none() {
        // sh0 then the rest in use: 3 nb values, basis-major, in rows of 16
        let nb = (ctx.degree as usize + 1) * (ctx.degree as usize + 1);
        let k3 = sc.sh_rest_k() * 3;
        let coef = flat(&mut g.coef);
        for (c0, out) in coef[..3 * nb].chunks_mut(BLOCK).enumerate() {
            let c0 = c0 * BLOCK;
            let c1 = (c0 + BLOCK).min(3 * nb);
            let mut r = [zero; BLOCK];
            for l in 0..n {
                let i = ids[l] as usize;
                // SAFETY: Gaussian i's sh0 and its first 3 (nb - 1) <= k3 rest values
                // (the caller's contract; `ctx.degree` is at most the scene's).
                unsafe {
                    let rest = sc.sh_rest.as_ptr().add(i * k3);
                    let mut v = zero;
                    if c0 == 0 {
                        v = put(v, 0, 3, sc.sh0.as_ptr().add(i * 3));
                        if c1 > 3 {
                            v = put(v, 3, c1 - 3, rest);
                        }
                    } else {
                        v = put(v, 0, c1 - c0, rest.add(c0 - 3));
                    }
                    r[l] = v;
                }
            }
            transpose16(&mut r);
            store_lanes(&r[..c1 - c0], out);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transpose16_transposes() {
        if !std::is_x86_feature_detected!("avx512f") {
            return;
        }
        let m: Vec<f32> = (0..256).map(|v| v as f32).collect();
        let mut out = [[0.0f32; 16]; 16];
        // SAFETY: AVX-512F checked above; every pointer holds 16 floats
        unsafe {
            let mut r = [_mm512_setzero_ps(); BLOCK];
            for (i, v) in r.iter_mut().enumerate() {
                *v = _mm512_loadu_ps(m[i * 16..].as_ptr());
            }
            transpose16(&mut r);
            for (o, v) in out.iter_mut().zip(&r) {
                _mm512_storeu_ps(o.as_mut_ptr(), *v);
            }
        }
        for (k, row) in out.iter().enumerate() {
            for (i, &v) in row.iter().enumerate() {
                assert_eq!(v, m[i * 16 + k], "lane {i} of value {k}");
            }
        }
    }

    #[test]
    fn lane_masks() {
        assert_eq!(lanes(0, 3), 0b111);
        assert_eq!(lanes(3, 7), 0b111_1000);
        assert_eq!(lanes(14, 16), 0xC000);
        assert_eq!(lanes(0, 16), 0xFFFF);
    }
}
