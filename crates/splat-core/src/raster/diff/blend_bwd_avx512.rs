//! The AVX-512 blend-backward kernel (`core::arch` intrinsics): the operations of the generic
//! kernel (`blend_bwd::bwd_tile_impl::<true, _, _>`) in the same order per lane, so the same slot
//! bits. One splat at a time: its per-lane terms and its 12 per-lane accumulators stay in
//! registers while the 4x4-pixel blocks it reaches are replayed in block order (each block's
//! transmittance and running colour are loaded and stored back); the 16-lane sums of the 12
//! slot values are done together by a transposing halving tree, the canonical order of
//! `blend_bwd::hsum16`.
use super::blend_bwd::{block_lane, PixIn, SlotSink};
use super::slots::slot;
use crate::raster::blend::{
    prefetch, row_mask, BlendParams, Stream, EXP2_16THS, EXP_C_HI, EXP_C_LO, EXP_K16, EXP_MAGIC,
    LANES, SIGMA_CLAMP, T_MIN,
};
use crate::raster::blend_avx512::{copy_entries, reached_blocks};
use crate::raster::project::{Splat, ALPHA_THRESHOLD};

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::*;

/// List entries whose reached blocks are found ahead of their replay, at a time.
const REACH_CHUNK: usize = 16;

/// Rows of 16 floats, 64-byte aligned.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Rows([[f32; LANES]; LANES]);

#[derive(Clone, Copy, Default)]
#[repr(C, align(64))]
struct Row([f32; LANES]);

/// The 16-lane sums of 12 vectors, each in the canonical halving-tree order (i + 8, i + 4,
/// i + 2, i + 1), computed together: lane i of the result holds vector i's sum (i < 12).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx2,fma")]
fn hsum12(v: &[__m512; 12]) -> __m512 {
    // i + 8: pairs (a, b) -> [a lo8 + a hi8, b lo8 + b hi8]
    let mut s1 = [_mm512_setzero_ps(); 6];
    for i in 0..6 {
        let (a, b) = (v[2 * i], v[2 * i + 1]);
        s1[i] = _mm512_add_ps(
            _mm512_shuffle_f32x4::<0x44>(a, b),
            _mm512_shuffle_f32x4::<0xEE>(a, b),
        );
    }
    // i + 4: pairs ([A8, B8], [C8, D8]) -> [A4, B4, C4, D4]
    let mut s2 = [_mm512_setzero_ps(); 3];
    for j in 0..3 {
        let (x, y) = (s1[2 * j], s1[2 * j + 1]);
        s2[j] = _mm512_add_ps(
            _mm512_shuffle_f32x4::<0x88>(x, y),
            _mm512_shuffle_f32x4::<0xDD>(x, y),
        );
    }
    // i + 2 within each 128-bit quarter: [p0, p1, p2, p3] -> [p0 + p2, p1 + p3]
    let z = _mm512_setzero_ps();
    let h2 = |x: __m512, y: __m512| {
        _mm512_add_ps(
            _mm512_shuffle_ps::<0x44>(x, y),
            _mm512_shuffle_ps::<0xEE>(x, y),
        )
    };
    let s3a = h2(s2[0], s2[1]);
    let s3b = h2(s2[2], z);
    // i + 1: [a0, a1, b0, b1] -> [a0 + a1, b0 + b1]
    let r = _mm512_add_ps(
        _mm512_shuffle_ps::<0x88>(s3a, s3b),
        _mm512_shuffle_ps::<0xDD>(s3a, s3b),
    );
    // lane i of the result: vector i's sum (i < 12), from lane 4 (i % 4) + i / 4 of r
    let idx = _mm512_setr_epi32(0, 4, 8, 12, 1, 5, 9, 13, 2, 6, 10, 14, 3, 7, 11, 15);
    _mm512_permutexvar_ps(idx, r)
}

/// Replay one tile's list with AVX-512 and emit every entry's slot (see the generic kernel):
/// per splat, the blocks of 4x4 pixels it reaches (the forward AVX-512 kernel's test: each
/// reached row's contour range, its hull over each band of 4 rows, against each block's
/// columns), then per reached block, in block order, the per-pixel backward step on the block's
/// 16 lanes (a lane's row terms by a permute of the splat's 16-row vectors, taken once per band;
/// its column terms by a 4-lane broadcast). The tile's transmittance and running colour are
/// kept in block order, as `PixIn` is. The reach tests run [`REACH_CHUNK`] entries ahead of
/// the replay (the same masks, ANDed with the blocks still live when the entry is replayed).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx2,fma")]
pub(super) fn bwd_tile_avx512<'a, const ABS: bool, const DEPTH: bool, S: SlotSink>(
    x0: u32,
    y0: u32,
    p: &BlendParams,
    splats: &[Splat],
    lists: impl Iterator<Item = &'a [u32]>,
    pix: &PixIn,
    sink: &mut S,
) -> u64 {
    // live lanes per block; lanes outside the image start done; `alive` the blocks with live
    // lanes
    let mut live = [0u16; LANES];
    let mut alive: u16 = 0;
    let cols = p.width.saturating_sub(x0).min(LANES as u32) as usize;
    let rows = p.height.saturating_sub(y0).min(LANES as u32) as usize;
    for r in 0..rows {
        for l in 0..cols {
            let (b, i) = block_lane(r, l);
            live[b] |= 1 << i;
            alive |= 1 << b;
        }
    }
    let lane_f = _mm512_setr_ps(
        0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0, 13.0, 14.0, 15.0,
    );
    let px = _mm512_add_ps(
        _mm512_add_ps(_mm512_set1_ps(x0 as f32), lane_f),
        _mm512_set1_ps(0.5),
    );
    let y0f = y0 as f32;
    let py = _mm512_add_ps(
        _mm512_add_ps(_mm512_set1_ps(y0f), lane_f),
        _mm512_set1_ps(0.5),
    );
    // lane 4 br + bc: the first and last pixel centres of block column bc (exact in float)
    let col_f = _mm512_setr_ps(
        0.0, 4.0, 8.0, 12.0, 0.0, 4.0, 8.0, 12.0, 0.0, 4.0, 8.0, 12.0, 0.0, 4.0, 8.0, 12.0,
    );
    let v_bxl = _mm512_add_ps(
        _mm512_add_ps(_mm512_set1_ps(x0 as f32), col_f),
        _mm512_set1_ps(0.5),
    );
    let v_bxh = _mm512_add_ps(
        _mm512_add_ps(_mm512_set1_ps(x0 as f32), col_f),
        _mm512_set1_ps(3.5),
    );
    // lane i of a block of band br takes the row terms of row 4 br + i / 4
    let quarter = _mm512_setr_epi32(0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3);
    let zero = _mm512_setzero_ps();
    let one = _mm512_set1_ps(1.0);
    let max_alpha = _mm512_set1_ps(p.max_alpha);
    let thr = _mm512_set1_ps(ALPHA_THRESHOLD);
    let t_min = _mm512_set1_ps(T_MIN);
    let clamp = _mm512_set1_epi32(SIGMA_CLAMP.to_bits() as i32);
    let magic = _mm512_set1_ps(EXP_MAGIC);
    let k16 = _mm512_set1_ps(EXP_K16);
    let (c_hi, c_lo) = (_mm512_set1_ps(EXP_C_HI), _mm512_set1_ps(EXP_C_LO));
    let (sixth, half) = (_mm512_set1_ps(-1.0 / 6.0), _mm512_set1_ps(0.5));
    let minus_one = _mm512_set1_ps(-1.0);
    let abs_mask = _mm512_set1_epi32(0x7FFF_FFFF);
    // SAFETY: the table holds 16 u32.
    let table = unsafe { _mm512_loadu_si512(EXP2_16THS.as_ptr() as *const _) };
    let mut tt = Rows([[1.0; LANES]; LANES]);
    let mut ss = Rows([[0.0; LANES]; LANES]);
    // per-column terms of the current splat: dx, 0.5 a dx^2, dx^2, a dx, b dx
    let mut cterm = [Row::default(); 5];
    let t_ptr = tt.0.as_mut_ptr() as *mut f32;
    let s_ptr = ss.0.as_mut_ptr() as *mut f32;
    let g_ptr = [0, 1, 2, 3].map(|c| pix.g[c].as_ptr() as *const f32);
    let q_ptr = pix.q.as_ptr() as *const f32;
    let mut evals = 0u64;
    let mut done = alive == 0;
    // the blocks each splat reaches, found for REACH_CHUNK entries of the list ahead of their
    // replay: a splat's reach test (its loads, square roots and hull, about 60 cycles of
    // latency) then does not wait behind the replay of the splats before it in the
    // out-of-order window, and its block loop starts on a known mask
    let mut reach = [0u16; REACH_CHUNK];
    // the tile's lists as one stream of chunks (a frame of many binning chunks gives a tile many
    // short lists): the next chunk's splats are prefetched during this one's reach tests,
    // across the lists' ends, as the forward kernel does (`blend::Stream`)
    let mut stream = Stream::new(lists);
    let copy = |src: &[u32], dst: &mut [u32]| copy_entries(src, dst);
    let mut next = [0u32; REACH_CHUNK];
    let mut n_next = stream.fill(&mut next, copy);
    for &gi in &next[..n_next] {
        prefetch(splats, gi as usize);
    }
    while n_next != 0 {
        let (cur, n) = (next, n_next);
        n_next = stream.fill(&mut next, copy);
        let chunk = &cur[..n];
        {
            if !done {
                for (j, (&gi, reached)) in chunk.iter().zip(reach.iter_mut()).enumerate() {
                    if j < n_next {
                        prefetch(splats, next[j] as usize);
                    }
                    let s = &splats[gi as usize];
                    let my = s.xy[1];
                    let cb = s.conic[1];
                    // the blocks it reaches: each row's contour range (the rows test of the
                    // generic kernel), the hull of the reached rows' ranges over each band of 4
                    // rows (in every lane of the band), against each block's columns (lane
                    // 4 br + bc); the tile's live blocks are taken at its replay
                    let range = row_mask(my, s.half_height, y0f) as u16;
                    let dy = _mm512_sub_ps(_mm512_set1_ps(my), py);
                    let bdy = _mm512_mul_ps(_mm512_set1_ps(cb), dy);
                    *reached = reached_blocks(s, range, dy, bdy, (v_bxl, v_bxh));
                }
            }
            for (j, &gi) in chunk.iter().enumerate() {
                if done {
                    sink.zero(gi);
                    continue;
                }
                let s = &splats[gi as usize];
                let (mx, my) = (s.xy[0], s.xy[1]);
                let [ca, cb, cc] = s.conic;
                let v_mx = _mm512_set1_ps(mx);
                let dy = _mm512_sub_ps(_mm512_set1_ps(my), py);
                let dy2 = _mm512_mul_ps(dy, dy);
                let bdy = _mm512_mul_ps(_mm512_set1_ps(cb), dy);
                let mut todo = reach[j] & alive;
                let cdy2 = _mm512_mul_ps(_mm512_mul_ps(_mm512_set1_ps(0.5 * cc), dy), dy);
                let cdy = _mm512_mul_ps(_mm512_set1_ps(cc), dy);
                // per-column terms
                let dx = _mm512_sub_ps(v_mx, px);
                let adx2 = _mm512_mul_ps(_mm512_mul_ps(_mm512_set1_ps(0.5 * ca), dx), dx);
                let dx2 = _mm512_mul_ps(dx, dx);
                // SAFETY: each row holds 16 aligned floats.
                unsafe {
                    _mm512_store_ps(cterm[0].0.as_mut_ptr(), dx);
                    _mm512_store_ps(cterm[1].0.as_mut_ptr(), adx2);
                    _mm512_store_ps(cterm[2].0.as_mut_ptr(), dx2);
                    if ABS {
                        _mm512_store_ps(
                            cterm[3].0.as_mut_ptr(),
                            _mm512_mul_ps(_mm512_set1_ps(ca), dx),
                        );
                        _mm512_store_ps(
                            cterm[4].0.as_mut_ptr(),
                            _mm512_mul_ps(_mm512_set1_ps(cb), dx),
                        );
                    }
                }
                let ln_op = _mm512_set1_ps(s.ln_opacity);
                let col = [s.rgb[0], s.rgb[1], s.rgb[2], s.depth].map(|v| _mm512_set1_ps(v));
                let mut acc = [zero; slot::LEN];
                // the row terms of the current band in block lanes
                let mut band = usize::MAX;
                let (mut b_bdy, mut b_cdy2, mut b_dy, mut b_dy2, mut b_cdy) =
                    (zero, zero, zero, zero, zero);
                while todo != 0 {
                    let b = todo.trailing_zeros() as usize;
                    todo &= todo - 1;
                    evals += LANES as u64;
                    if b / 4 != band {
                        band = b / 4;
                        let idx = _mm512_add_epi32(quarter, _mm512_set1_epi32(4 * band as i32));
                        b_bdy = _mm512_permutexvar_ps(idx, bdy);
                        b_cdy2 = _mm512_permutexvar_ps(idx, cdy2);
                        b_dy = _mm512_permutexvar_ps(idx, dy);
                        b_dy2 = _mm512_permutexvar_ps(idx, dy2);
                        if ABS {
                            b_cdy = _mm512_permutexvar_ps(idx, cdy);
                        }
                    }
                    let c = 4 * (b % 4);
                    let o = b * LANES;
                    // SAFETY: b < 16, so o..o + 16 lies inside each 256-float array; c + 4 <= 16.
                    let (t, sr, g0, g1, g2, g3, q, dx, adx2, dx2) = unsafe {
                        (
                            _mm512_load_ps(t_ptr.add(o)),
                            _mm512_load_ps(s_ptr.add(o)),
                            _mm512_load_ps(g_ptr[0].add(o)),
                            _mm512_load_ps(g_ptr[1].add(o)),
                            _mm512_load_ps(g_ptr[2].add(o)),
                            if DEPTH {
                                _mm512_load_ps(g_ptr[3].add(o))
                            } else {
                                zero
                            },
                            _mm512_load_ps(q_ptr.add(o)),
                            _mm512_broadcast_f32x4(_mm_load_ps(cterm[0].0.as_ptr().add(c))),
                            _mm512_broadcast_f32x4(_mm_load_ps(cterm[1].0.as_ptr().add(c))),
                            _mm512_broadcast_f32x4(_mm_load_ps(cterm[2].0.as_ptr().add(c))),
                        )
                    };
                    let lv = live[b];
                    let sigma = _mm512_add_ps(_mm512_fmadd_ps(b_bdy, dx, adx2), b_cdy2);
                    // e = exp(ln_op - sigma), exactly as blend::opacity_exp::<true>
                    let sg =
                        _mm512_castsi512_ps(_mm512_min_epu32(_mm512_castps_si512(sigma), clamp));
                    let u = _mm512_sub_ps(sg, ln_op);
                    let tk = _mm512_fnmadd_ps(u, k16, magic);
                    let kf = _mm512_sub_ps(tk, magic);
                    let rr = _mm512_fmadd_ps(kf, c_hi, u);
                    let rr = _mm512_fmadd_ps(kf, c_lo, rr);
                    let y = _mm512_fmadd_ps(rr, sixth, half);
                    let y = _mm512_fmadd_ps(y, rr, minus_one);
                    let y = _mm512_fmadd_ps(y, rr, one);
                    let ti = _mm512_castps_si512(tk);
                    let scale = _mm512_add_epi32(
                        _mm512_permutexvar_epi32(ti, table),
                        _mm512_slli_epi32::<23>(_mm512_srli_epi32::<4>(ti)),
                    );
                    let e = _mm512_mul_ps(y, _mm512_castsi512_ps(scale));
                    let alpha = _mm512_min_ps(e, max_alpha);
                    let valid = _mm512_mask_cmp_ps_mask::<_CMP_GE_OQ>(lv, alpha, thr);
                    let w = _mm512_mul_ps(alpha, t);
                    let tn = _mm512_sub_ps(t, w);
                    let contrib = _mm512_mask_cmp_ps_mask::<_CMP_GT_OQ>(valid, tn, t_min);
                    let m2 = _mm512_mask_cmp_ps_mask::<_CMP_LT_OQ>(contrib, e, max_alpha);
                    // dL/dalpha = (g . c) T - (Q - S) / (1 - alpha)
                    let gc = _mm512_mul_ps(g0, col[0]);
                    let gc = _mm512_fmadd_ps(g1, col[1], gc);
                    let gc = _mm512_fmadd_ps(g2, col[2], gc);
                    // without a depth gradient (g3 = +0.0 everywhere) the depth channel's terms
                    // are left out: they change no slot bit (see `bwd_tile`)
                    let gc = if DEPTH {
                        _mm512_fmadd_ps(g3, col[3], gc)
                    } else {
                        gc
                    };
                    let s_new = _mm512_fmadd_ps(gc, w, sr);
                    let ra = _mm512_div_ps(one, _mm512_sub_ps(one, alpha));
                    let tq = _mm512_mul_ps(_mm512_sub_ps(q, s_new), ra);
                    let va = _mm512_fmsub_ps(gc, t, tq);
                    let uu = _mm512_mul_ps(e, va);
                    let dxdy = _mm512_mul_ps(dx, b_dy);
                    acc[0] = _mm512_mask3_fmadd_ps(w, g0, acc[0], contrib);
                    acc[1] = _mm512_mask3_fmadd_ps(w, g1, acc[1], contrib);
                    acc[2] = _mm512_mask3_fmadd_ps(w, g2, acc[2], contrib);
                    if DEPTH {
                        acc[3] = _mm512_mask3_fmadd_ps(w, g3, acc[3], contrib);
                    }
                    acc[slot::V0] = _mm512_mask_add_ps(acc[slot::V0], m2, acc[slot::V0], uu);
                    acc[slot::VDX] = _mm512_mask3_fmadd_ps(uu, dx, acc[slot::VDX], m2);
                    acc[slot::VDY] = _mm512_mask3_fmadd_ps(uu, b_dy, acc[slot::VDY], m2);
                    acc[slot::VDX2] = _mm512_mask3_fmadd_ps(uu, dx2, acc[slot::VDX2], m2);
                    acc[slot::VDXDY] = _mm512_mask3_fmadd_ps(uu, dxdy, acc[slot::VDXDY], m2);
                    acc[slot::VDY2] = _mm512_mask3_fmadd_ps(uu, b_dy2, acc[slot::VDY2], m2);
                    if ABS {
                        // SAFETY: as above
                        let (adx, bdx) = unsafe {
                            (
                                _mm512_broadcast_f32x4(_mm_load_ps(cterm[3].0.as_ptr().add(c))),
                                _mm512_broadcast_f32x4(_mm_load_ps(cterm[4].0.as_ptr().add(c))),
                            )
                        };
                        let ax = _mm512_mul_ps(uu, _mm512_add_ps(adx, b_bdy));
                        let ay = _mm512_mul_ps(uu, _mm512_add_ps(bdx, b_cdy));
                        let ax = _mm512_castsi512_ps(_mm512_and_si512(
                            _mm512_castps_si512(ax),
                            abs_mask,
                        ));
                        let ay = _mm512_castsi512_ps(_mm512_and_si512(
                            _mm512_castps_si512(ay),
                            abs_mask,
                        ));
                        acc[slot::ABSX] =
                            _mm512_mask_add_ps(acc[slot::ABSX], m2, acc[slot::ABSX], ax);
                        acc[slot::ABSY] =
                            _mm512_mask_add_ps(acc[slot::ABSY], m2, acc[slot::ABSY], ay);
                    }
                    // SAFETY: see above
                    unsafe {
                        _mm512_store_ps(t_ptr.add(o), _mm512_mask_mov_ps(t, contrib, tn));
                        _mm512_store_ps(s_ptr.add(o), _mm512_mask_mov_ps(sr, contrib, s_new));
                    }
                    // valid lanes that do not contribute stop
                    let lv = (lv & !valid) | contrib;
                    live[b] = lv;
                    if lv == 0 {
                        alive &= !(1 << b);
                        if alive == 0 {
                            done = true;
                            break;
                        }
                    }
                }
                // SAFETY: AVX-512F is present (this function's target features).
                unsafe { sink.put_m512(gi, hsum12(&acc)) };
            }
        }
    }
    evals
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raster::diff::blend_bwd::hsum16;

    #[test]
    fn hsum12_gives_each_vectors_canonical_sum_bit_for_bit() {
        if !std::is_x86_feature_detected!("avx512f")
            || !std::is_x86_feature_detected!("avx512dq")
            || !std::is_x86_feature_detected!("avx512bw")
            || !std::is_x86_feature_detected!("avx512vl")
        {
            return;
        }
        let mut h = 0x1234_5678_9abc_def0u64;
        let mut next = || {
            h ^= h << 13;
            h ^= h >> 7;
            h ^= h << 17;
            // magnitudes over many binades, so the summation order shows in the bits
            let m = (h >> 40) as f32 / (1u64 << 24) as f32 - 0.5;
            m * 2f32.powi(((h >> 20) % 24) as i32 - 12)
        };
        for _ in 0..200 {
            let vals: Vec<[f32; 16]> = (0..12).map(|_| std::array::from_fn(|_| next())).collect();
            // SAFETY: the features are present (checked above); each array holds 16 floats.
            let got = unsafe {
                let v: [__m512; 12] = std::array::from_fn(|i| _mm512_loadu_ps(vals[i].as_ptr()));
                let mut lanes = [0.0f32; 16];
                _mm512_storeu_ps(lanes.as_mut_ptr(), hsum12(&v));
                lanes
            };
            for i in 0..12 {
                assert_eq!(got[i].to_bits(), hsum16(&vals[i]).to_bits(), "vector {i}");
            }
        }
    }
}
