//! The AVX2 + FMA blend-backward kernel: the AVX-512 kernel's organisation (see
//! `blend_bwd_avx512.rs`) with each 4x4-pixel block as two 4x2 halves (8 lanes each) and lane
//! masks held in vectors. Same operations in the same order per lane as the generic kernel, so
//! the same slot bits.
use super::blend_bwd::{block_lane, PixIn, SlotSink};
use super::slots::slot;
use crate::raster::blend::{
    prefetch, row_mask, BlendParams, EXP2_16THS, EXP_C_HI, EXP_C_LO, EXP_K16, EXP_MAGIC, LANES,
    PREFETCH_AHEAD, SIGMA_CLAMP, T_MIN,
};
use crate::raster::project::{Splat, ALPHA_THRESHOLD};

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::*;

/// Lanes of one AVX2 vector: a row is two halves.
const HALF: usize = 8;

#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Rows([[f32; LANES]; LANES]);

#[derive(Clone, Copy, Default)]
#[repr(C, align(64))]
struct Row([f32; LANES]);

/// The 16-lane sums of 12 rows given as (low, high) halves, each in the canonical
/// halving-tree order (see `blend_bwd::hsum16`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn hsum12(v: &[[__m256; 2]; 12]) -> [f32; slot::LEN] {
    // i + 8
    let h8: [__m256; 12] = std::array::from_fn(|i| _mm256_add_ps(v[i][0], v[i][1]));
    // i + 4: pairs (x, y) -> [x lo4 + x hi4 | y lo4 + y hi4]
    let mut s2 = [_mm256_setzero_ps(); 6];
    for j in 0..6 {
        let (x, y) = (h8[2 * j], h8[2 * j + 1]);
        s2[j] = _mm256_add_ps(
            _mm256_permute2f128_ps::<0x20>(x, y),
            _mm256_permute2f128_ps::<0x31>(x, y),
        );
    }
    // i + 2 within each 128-bit lane: [p0, p1, p2, p3] -> [p0 + p2, p1 + p3]
    let mut s3 = [_mm256_setzero_ps(); 3];
    for j in 0..3 {
        let (x, y) = (s2[2 * j], s2[2 * j + 1]);
        s3[j] = _mm256_add_ps(
            _mm256_shuffle_ps::<0x44>(x, y),
            _mm256_shuffle_ps::<0xEE>(x, y),
        );
    }
    // i + 1: [a0, a1, b0, b1] -> [a0 + a1, b0 + b1]
    let z = _mm256_setzero_ps();
    let r0 = _mm256_add_ps(
        _mm256_shuffle_ps::<0x88>(s3[0], s3[1]),
        _mm256_shuffle_ps::<0xDD>(s3[0], s3[1]),
    );
    let r1 = _mm256_add_ps(
        _mm256_shuffle_ps::<0x88>(s3[2], z),
        _mm256_shuffle_ps::<0xDD>(s3[2], z),
    );
    let mut a = [0.0f32; 8];
    let mut b = [0.0f32; 8];
    // SAFETY: both arrays hold 8 floats.
    unsafe {
        _mm256_storeu_ps(a.as_mut_ptr(), r0);
        _mm256_storeu_ps(b.as_mut_ptr(), r1);
    }
    // r0: 128-bit lane 0 = [v0, v2, v4, v6], lane 1 = [v1, v3, v5, v7];
    // r1: lane 0 = [v8, v10, 0, 0], lane 1 = [v9, v11, 0, 0]
    [
        a[0], a[4], a[1], a[5], a[2], a[6], a[3], a[7], b[0], b[4], b[1], b[5],
    ]
}

/// Replay one tile's list with AVX2 + FMA and emit every entry's slot: the AVX-512 kernel's
/// blocks (the same reached blocks, in the same order), each 4x4 block as its two 4x2 halves
/// (lanes 0-7 and 8-15 of the block), the two halves in turn so that one half's 12
/// accumulators stay in registers.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
pub(super) fn bwd_tile_avx2<'a, const ABS: bool, const DEPTH: bool, S: SlotSink>(
    x0: u32,
    y0: u32,
    p: &BlendParams,
    splats: &[Splat],
    lists: impl Iterator<Item = &'a [u32]>,
    pix: &PixIn,
    sink: &mut S,
) -> u64 {
    // live lanes per block, blocks with live lanes; lanes outside the image start done
    let mut live = [0u32; LANES];
    let mut alive: u32 = 0;
    let cols = p.width.saturating_sub(x0).min(LANES as u32) as usize;
    let rows = p.height.saturating_sub(y0).min(LANES as u32) as usize;
    for r in 0..rows {
        for l in 0..cols {
            let (b, i) = block_lane(r, l);
            live[b] |= 1 << i;
            alive |= 1 << b;
        }
    }
    let lane_f = _mm256_setr_ps(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0);
    let eight = _mm256_set1_ps(8.0);
    let half = _mm256_set1_ps(0.5);
    let x0v = _mm256_set1_ps(x0 as f32);
    let px = [
        _mm256_add_ps(_mm256_add_ps(x0v, lane_f), half),
        _mm256_add_ps(_mm256_add_ps(x0v, _mm256_add_ps(lane_f, eight)), half),
    ];
    let y0f = y0 as f32;
    let y0v = _mm256_set1_ps(y0f);
    let py = [
        _mm256_add_ps(_mm256_add_ps(y0v, lane_f), half),
        _mm256_add_ps(_mm256_add_ps(y0v, _mm256_add_ps(lane_f, eight)), half),
    ];
    // lane 4 j + bc: the first and last pixel centres of block column bc (exact in float)
    let col_f = _mm256_setr_ps(0.0, 4.0, 8.0, 12.0, 0.0, 4.0, 8.0, 12.0);
    let v_bxl = _mm256_add_ps(_mm256_add_ps(x0v, col_f), half);
    let v_bxh = _mm256_add_ps(_mm256_add_ps(x0v, col_f), _mm256_set1_ps(3.5));
    let inf = _mm256_set1_ps(f32::INFINITY);
    let neg_inf = _mm256_set1_ps(f32::NEG_INFINITY);
    let zero = _mm256_setzero_ps();
    let one = _mm256_set1_ps(1.0);
    let max_alpha = _mm256_set1_ps(p.max_alpha);
    let thr = _mm256_set1_ps(ALPHA_THRESHOLD);
    let t_min = _mm256_set1_ps(T_MIN);
    let clamp = _mm256_set1_epi32(SIGMA_CLAMP.to_bits() as i32);
    let magic = _mm256_set1_ps(EXP_MAGIC);
    let k16 = _mm256_set1_ps(EXP_K16);
    let (c_hi, c_lo) = (_mm256_set1_ps(EXP_C_HI), _mm256_set1_ps(EXP_C_LO));
    let sixth = _mm256_set1_ps(-1.0 / 6.0);
    let minus_one = _mm256_set1_ps(-1.0);
    let abs_mask = _mm256_castsi256_ps(_mm256_set1_epi32(0x7FFF_FFFF));
    // SAFETY: the table holds 16 u32.
    let (tab_lo, tab_hi) = unsafe {
        (
            _mm256_loadu_si256(EXP2_16THS.as_ptr() as *const _),
            _mm256_loadu_si256(EXP2_16THS.as_ptr().add(HALF) as *const _),
        )
    };
    let lane_bits = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
    let mut tt = Rows([[1.0; LANES]; LANES]);
    let mut ss = Rows([[0.0; LANES]; LANES]);
    // per-row terms of the current splat: dy, b dy, 0.5 c dy^2, dy^2, c dy
    let mut rterm = [Row::default(); 5];
    // per-column terms: dx, 0.5 a dx^2, dx^2, a dx, b dx
    let mut cterm = [Row::default(); 5];
    let t_ptr = tt.0.as_mut_ptr() as *mut f32;
    let s_ptr = ss.0.as_mut_ptr() as *mut f32;
    let g_ptr = [0, 1, 2, 3].map(|c| pix.g[c].as_ptr() as *const f32);
    let q_ptr = pix.q.as_ptr() as *const f32;
    let mut evals = 0u64;
    let mut done = alive == 0;
    for list in lists {
        for (k, &gi) in list.iter().enumerate() {
            if done {
                sink.zero(gi);
                continue;
            }
            if let Some(&ahead) = list.get(k + PREFETCH_AHEAD) {
                prefetch(splats, ahead as usize);
            }
            let s = &splats[gi as usize];
            let (mx, my) = (s.xy[0], s.xy[1]);
            let [ca, cb, cc] = s.conic;
            let range = row_mask(my, s.half_height, y0f);
            let v_mx = _mm256_set1_ps(mx);
            // the blocks it reaches, as the AVX-512 kernel finds them: rows 8 h .. 8 h + 8 give
            // bands 2 h and 2 h + 1, i.e. blocks 8 h .. 8 h + 8 (lane 4 j + bc)
            let mut blocks = 0u32;
            for h in 0..2 {
                let dy = _mm256_sub_ps(_mm256_set1_ps(my), py[h]);
                let bdy = _mm256_mul_ps(_mm256_set1_ps(cb), dy);
                let dy2 = _mm256_mul_ps(dy, dy);
                let disc = _mm256_sub_ps(
                    _mm256_set1_ps(s.two_a_level),
                    _mm256_mul_ps(dy2, _mm256_set1_ps(s.conic_det)),
                );
                let sq = _mm256_sqrt_ps(disc);
                let inv_a = _mm256_set1_ps(s.inv_a);
                let left = _mm256_sub_ps(v_mx, _mm256_mul_ps(_mm256_sub_ps(sq, bdy), inv_a));
                let right = _mm256_add_ps(v_mx, _mm256_mul_ps(_mm256_add_ps(sq, bdy), inv_a));
                let rbits = _mm256_set1_epi32(((range >> (h * HALF)) & 0xFF) as i32);
                let in_range = _mm256_castsi256_ps(_mm256_cmpeq_epi32(
                    _mm256_and_si256(rbits, lane_bits),
                    lane_bits,
                ));
                let ok = _mm256_and_ps(in_range, _mm256_cmp_ps::<_CMP_GE_OQ>(disc, zero));
                let l = _mm256_blendv_ps(inf, left, ok);
                let r = _mm256_blendv_ps(neg_inf, right, ok);
                let l = _mm256_min_ps(l, _mm256_permute_ps::<0b10_11_00_01>(l));
                let r = _mm256_max_ps(r, _mm256_permute_ps::<0b10_11_00_01>(r));
                let l = _mm256_min_ps(l, _mm256_permute_ps::<0b01_00_11_10>(l));
                let r = _mm256_max_ps(r, _mm256_permute_ps::<0b01_00_11_10>(r));
                let m = _mm256_and_ps(
                    _mm256_cmp_ps::<_CMP_LE_OQ>(l, v_bxh),
                    _mm256_cmp_ps::<_CMP_GE_OQ>(r, v_bxl),
                );
                blocks |= (_mm256_movemask_ps(m) as u32) << (h * HALF);
                let cdy2 = _mm256_mul_ps(_mm256_mul_ps(_mm256_set1_ps(0.5 * cc), dy), dy);
                let cdy = _mm256_mul_ps(_mm256_set1_ps(cc), dy);
                // dx and its terms, lanes 8 h .. 8 h + 8
                let dx = _mm256_sub_ps(v_mx, px[h]);
                let adx2 = _mm256_mul_ps(_mm256_mul_ps(_mm256_set1_ps(0.5 * ca), dx), dx);
                let dx2 = _mm256_mul_ps(dx, dx);
                let adx = _mm256_mul_ps(_mm256_set1_ps(ca), dx);
                let bdx = _mm256_mul_ps(_mm256_set1_ps(cb), dx);
                // SAFETY: each row holds 16 floats, 32-byte aligned at h * 8.
                unsafe {
                    let o = h * HALF;
                    for (row, v) in rterm.iter_mut().zip([dy, bdy, cdy2, dy2, cdy]) {
                        _mm256_store_ps(row.0.as_mut_ptr().add(o), v);
                    }
                    for (row, v) in cterm.iter_mut().zip([dx, adx2, dx2, adx, bdx]) {
                        _mm256_store_ps(row.0.as_mut_ptr().add(o), v);
                    }
                }
            }
            let todo_all = blocks & alive;
            let ln_op = _mm256_set1_ps(s.ln_opacity);
            let col = [
                _mm256_set1_ps(s.rgb[0]),
                _mm256_set1_ps(s.rgb[1]),
                _mm256_set1_ps(s.rgb[2]),
                _mm256_set1_ps(s.depth),
            ];
            // the two 4x2 halves of the blocks in turn; every lane's operations and their order
            // are the generic kernel's
            let mut blk_live = [0u32; LANES];
            let mut v = [[zero; 2]; slot::LEN];
            for h in 0..2 {
                let mut acc = [zero; slot::LEN];
                let mut todo = todo_all;
                let mut band = usize::MAX;
                let (mut bdy, mut cdy2, mut dyv, mut dy2v, mut cdy) =
                    (zero, zero, zero, zero, zero);
                while todo != 0 {
                    let b = todo.trailing_zeros() as usize;
                    todo &= todo - 1;
                    if b / 4 != band {
                        band = b / 4;
                        // rows 4 band + 2 h (lanes 0-3) and + 1 (lanes 4-7) of the half
                        let r0 = 4 * band + 2 * h;
                        let two = |row: &Row| {
                            _mm256_set_m128(_mm_set1_ps(row.0[r0 + 1]), _mm_set1_ps(row.0[r0]))
                        };
                        dyv = two(&rterm[0]);
                        bdy = two(&rterm[1]);
                        cdy2 = two(&rterm[2]);
                        dy2v = two(&rterm[3]);
                        cdy = two(&rterm[4]);
                    }
                    let c = 4 * (b % 4);
                    let o = b * LANES + h * HALF;
                    // SAFETY: b < 16, h < 2: o..o + 8 lies inside each 256-float array, 32-byte
                    // aligned; c + 4 <= 16.
                    let (t, sr, g0, g1, g2, g3, q, dx, adx2, dx2) = unsafe {
                        let quad = |row: &Row| {
                            _mm256_broadcast_ps(&*(row.0.as_ptr().add(c) as *const __m128))
                        };
                        (
                            _mm256_load_ps(t_ptr.add(o)),
                            _mm256_load_ps(s_ptr.add(o)),
                            _mm256_load_ps(g_ptr[0].add(o)),
                            _mm256_load_ps(g_ptr[1].add(o)),
                            _mm256_load_ps(g_ptr[2].add(o)),
                            if DEPTH {
                                _mm256_load_ps(g_ptr[3].add(o))
                            } else {
                                zero
                            },
                            _mm256_load_ps(q_ptr.add(o)),
                            quad(&cterm[0]),
                            quad(&cterm[1]),
                            quad(&cterm[2]),
                        )
                    };
                    let lbits = (live[b] >> (h * HALF)) & 0xFF;
                    let lv = _mm256_castsi256_ps(_mm256_cmpeq_epi32(
                        _mm256_and_si256(_mm256_set1_epi32(lbits as i32), lane_bits),
                        lane_bits,
                    ));
                    let sigma = _mm256_add_ps(_mm256_fmadd_ps(bdy, dx, adx2), cdy2);
                    let sg =
                        _mm256_castsi256_ps(_mm256_min_epu32(_mm256_castps_si256(sigma), clamp));
                    let u = _mm256_sub_ps(sg, ln_op);
                    let tk = _mm256_fnmadd_ps(u, k16, magic);
                    let kf = _mm256_sub_ps(tk, magic);
                    let rr = _mm256_fmadd_ps(kf, c_hi, u);
                    let rr = _mm256_fmadd_ps(kf, c_lo, rr);
                    let y = _mm256_fmadd_ps(rr, sixth, half);
                    let y = _mm256_fmadd_ps(y, rr, minus_one);
                    let y = _mm256_fmadd_ps(y, rr, one);
                    let ti = _mm256_castps_si256(tk);
                    let tab = _mm256_blendv_ps(
                        _mm256_castsi256_ps(_mm256_permutevar8x32_epi32(tab_lo, ti)),
                        _mm256_castsi256_ps(_mm256_permutevar8x32_epi32(tab_hi, ti)),
                        _mm256_castsi256_ps(_mm256_slli_epi32::<28>(ti)),
                    );
                    let scale = _mm256_add_epi32(
                        _mm256_castps_si256(tab),
                        _mm256_slli_epi32::<23>(_mm256_srli_epi32::<4>(ti)),
                    );
                    let e = _mm256_mul_ps(y, _mm256_castsi256_ps(scale));
                    let alpha = _mm256_min_ps(e, max_alpha);
                    let valid = _mm256_and_ps(lv, _mm256_cmp_ps::<_CMP_GE_OQ>(alpha, thr));
                    let w = _mm256_mul_ps(alpha, t);
                    let tn = _mm256_sub_ps(t, w);
                    let contrib = _mm256_and_ps(valid, _mm256_cmp_ps::<_CMP_GT_OQ>(tn, t_min));
                    let m2 = _mm256_and_ps(contrib, _mm256_cmp_ps::<_CMP_LT_OQ>(e, max_alpha));
                    let gc = _mm256_mul_ps(g0, col[0]);
                    let gc = _mm256_fmadd_ps(g1, col[1], gc);
                    let gc = _mm256_fmadd_ps(g2, col[2], gc);
                    // no depth gradient: the depth channel's terms are left out (see `bwd_tile`)
                    let gc = if DEPTH {
                        _mm256_fmadd_ps(g3, col[3], gc)
                    } else {
                        gc
                    };
                    let s_new = _mm256_fmadd_ps(gc, w, sr);
                    let ra = _mm256_div_ps(one, _mm256_sub_ps(one, alpha));
                    let tq = _mm256_mul_ps(_mm256_sub_ps(q, s_new), ra);
                    let va = _mm256_fmsub_ps(gc, t, tq);
                    let uu = _mm256_mul_ps(e, va);
                    let dxdy = _mm256_mul_ps(dx, dyv);
                    let fm = |a: __m256, b: __m256, acc: __m256, m: __m256| {
                        _mm256_blendv_ps(acc, _mm256_fmadd_ps(a, b, acc), m)
                    };
                    acc[0] = fm(w, g0, acc[0], contrib);
                    acc[1] = fm(w, g1, acc[1], contrib);
                    acc[2] = fm(w, g2, acc[2], contrib);
                    if DEPTH {
                        acc[3] = fm(w, g3, acc[3], contrib);
                    }
                    let v0 = acc[slot::V0];
                    acc[slot::V0] = _mm256_blendv_ps(v0, _mm256_add_ps(v0, uu), m2);
                    acc[slot::VDX] = fm(uu, dx, acc[slot::VDX], m2);
                    acc[slot::VDY] = fm(uu, dyv, acc[slot::VDY], m2);
                    acc[slot::VDX2] = fm(uu, dx2, acc[slot::VDX2], m2);
                    acc[slot::VDXDY] = fm(uu, dxdy, acc[slot::VDXDY], m2);
                    acc[slot::VDY2] = fm(uu, dy2v, acc[slot::VDY2], m2);
                    if ABS {
                        // SAFETY: as above
                        let (adx, bdx) = unsafe {
                            (
                                _mm256_broadcast_ps(
                                    &*(cterm[3].0.as_ptr().add(c) as *const __m128),
                                ),
                                _mm256_broadcast_ps(
                                    &*(cterm[4].0.as_ptr().add(c) as *const __m128),
                                ),
                            )
                        };
                        let ax =
                            _mm256_and_ps(_mm256_mul_ps(uu, _mm256_add_ps(adx, bdy)), abs_mask);
                        let ay =
                            _mm256_and_ps(_mm256_mul_ps(uu, _mm256_add_ps(bdx, cdy)), abs_mask);
                        let (a7, a8) = (acc[slot::ABSX], acc[slot::ABSY]);
                        acc[slot::ABSX] = _mm256_blendv_ps(a7, _mm256_add_ps(a7, ax), m2);
                        acc[slot::ABSY] = _mm256_blendv_ps(a8, _mm256_add_ps(a8, ay), m2);
                    }
                    // SAFETY: see above
                    unsafe {
                        _mm256_store_ps(t_ptr.add(o), _mm256_blendv_ps(t, tn, contrib));
                        _mm256_store_ps(s_ptr.add(o), _mm256_blendv_ps(sr, s_new, contrib));
                    }
                    // valid lanes that do not contribute stop
                    let lv = _mm256_or_ps(_mm256_andnot_ps(valid, lv), contrib);
                    blk_live[b] |= (_mm256_movemask_ps(lv) as u32) << (h * HALF);
                }
                for (vk, a) in v.iter_mut().zip(acc) {
                    vk[h] = a;
                }
            }
            // a splat's blocks are fixed at its start, so the count does not depend on the order
            evals += LANES as u64 * todo_all.count_ones() as u64;
            let mut todo = todo_all;
            while todo != 0 {
                let b = todo.trailing_zeros() as usize;
                todo &= todo - 1;
                live[b] = blk_live[b];
                if blk_live[b] == 0 {
                    alive &= !(1 << b);
                }
            }
            done = alive == 0;
            sink.put(gi, &hsum12(&v));
        }
    }
    evals
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raster::diff::blend_bwd::hsum16;

    #[test]
    fn hsum12_gives_each_rows_canonical_sum_bit_for_bit() {
        if !std::is_x86_feature_detected!("avx2") || !std::is_x86_feature_detected!("fma") {
            return;
        }
        let mut h = 0x0bad_cafe_dead_beefu64;
        let mut next = || {
            h ^= h << 13;
            h ^= h >> 7;
            h ^= h << 17;
            let m = (h >> 40) as f32 / (1u64 << 24) as f32 - 0.5;
            m * 2f32.powi(((h >> 20) % 24) as i32 - 12)
        };
        for _ in 0..200 {
            let vals: Vec<[f32; 16]> = (0..12).map(|_| std::array::from_fn(|_| next())).collect();
            // SAFETY: AVX2 is present (checked above); each array holds 16 floats.
            let got = unsafe {
                let v: [[__m256; 2]; 12] = std::array::from_fn(|i| {
                    [
                        _mm256_loadu_ps(vals[i].as_ptr()),
                        _mm256_loadu_ps(vals[i].as_ptr().add(8)),
                    ]
                });
                hsum12(&v)
            };
            for i in 0..12 {
                assert_eq!(got[i].to_bits(), hsum16(&vals[i]).to_bits(), "row {i}");
            }
        }
    }
}
