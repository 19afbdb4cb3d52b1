//! The AVX-512 blend kernel, written with `core::arch` intrinsics (see `blend.rs` for the
//! generic kernel it mirrors operation for operation, so both give the same bits).
use super::blend::{prefetch, BlendParams, TileOut, LANES, PREFETCH_AHEAD, T_MIN};
use super::project::{Splat, ALPHA_THRESHOLD};

/// Explicit AVX-512 kernel: the same formulas and operation order as `blend_tile_impl::<true>`
/// (so the same bits), with the per-row contour test done for all 16 rows of the tile at once
/// (one mask per splat instead of a scalar square root and two branches per row), masked
/// accumulations and a movemask test for finished rows.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx2,fma")]
pub(super) fn blend_tile_avx512<'a>(
    x0: u32,
    y0: u32,
    p: &BlendParams,
    splats: &[Splat],
    lists: impl Iterator<Item = &'a [u32]>,
    out: &mut TileOut,
) -> u64 {
    use std::arch::x86_64::*;
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const MAGIC: f32 = 12_583_039.0;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;

    // lanes and rows outside the image start done
    let mut alive: u32 = 0;
    for r in 0..LANES {
        for l in 0..LANES {
            if x0 + l as u32 >= p.width || y0 + r as u32 >= p.height {
                out.t[r][l] = -1.0;
            }
        }
        if y0 + (r as u32) < p.height {
            alive |= 1 << r;
        }
    }
    let lane_f = _mm512_setr_ps(
        0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0, 13.0, 14.0, 15.0,
    );
    // pixel centres: (x0 + l) + 0.5 and (y0 + r) + 0.5, as the generic kernel rounds them
    let px = _mm512_add_ps(
        _mm512_add_ps(_mm512_set1_ps(x0 as f32), lane_f),
        _mm512_set1_ps(0.5),
    );
    let y0f = y0 as f32;
    let py = _mm512_add_ps(
        _mm512_add_ps(_mm512_set1_ps(y0f), lane_f),
        _mm512_set1_ps(0.5),
    );
    let (xl, xh) = ((x0 as f32) + 0.5, ((x0 + LANES as u32 - 1) as f32) + 0.5);
    let (v_xl, v_xh) = (_mm512_set1_ps(xl), _mm512_set1_ps(xh));
    let zero = _mm512_setzero_ps();
    let one = _mm512_set1_ps(1.0);
    let max_alpha = _mm512_set1_ps(p.max_alpha);
    let thr = _mm512_set1_ps(ALPHA_THRESHOLD);
    let t_min = _mm512_set1_ps(T_MIN);
    let clamp = _mm512_set1_ps(87.0);
    let magic = _mm512_set1_ps(MAGIC);
    let half = _mm512_set1_ps(0.5);
    let mut evals = 0u64;
    let mut bdy_rows = [0.0f32; LANES];
    let mut cdy2_rows = [0.0f32; LANES];
    let t_ptr = out.t.as_mut_ptr() as *mut f32;
    let c0_ptr = out.c[0].as_mut_ptr() as *mut f32;
    let c1_ptr = out.c[1].as_mut_ptr() as *mut f32;
    let c2_ptr = out.c[2].as_mut_ptr() as *mut f32;
    let d_ptr = out.d.as_mut_ptr() as *mut f32;
    for list in lists {
        for (k, &gi) in list.iter().enumerate() {
            if let Some(&ahead) = list.get(k + PREFETCH_AHEAD) {
                prefetch(splats, ahead as usize);
            }
            let s = &splats[gi as usize];
            let (mx, my) = (s.xy[0], s.xy[1]);
            let [ca, cb, cc] = s.conic;
            let ey = s.half_height;
            let lo = (my - ey - 0.5 - y0f).ceil().clamp(0.0, 16.0) as u32;
            let hi = (my + ey - 0.5 - y0f).floor().clamp(-1.0, 15.0) as i32 + 1;
            let hi = hi.max(0) as u32;
            let range = ((1u32 << hi) - 1) & !((1u32 << lo) - 1);
            let mut rows = range & alive;
            if rows == 0 {
                continue;
            }
            // the contour test of every row at once: disc = 2 a level - dy^2 det >= 0 and the
            // contour's dx range [(-b dy - sq) / a, (-b dy + sq) / a] reaches the tile
            let v_mx = _mm512_set1_ps(mx);
            let dy = _mm512_sub_ps(_mm512_set1_ps(my), py);
            let bdy = _mm512_mul_ps(_mm512_set1_ps(cb), dy);
            let dy2 = _mm512_mul_ps(dy, dy);
            let disc = _mm512_sub_ps(
                _mm512_set1_ps(s.two_a_level),
                _mm512_mul_ps(dy2, _mm512_set1_ps(s.conic_det)),
            );
            let ok = _mm512_cmp_ps_mask::<_CMP_GE_OQ>(disc, zero);
            let sq = _mm512_sqrt_ps(disc);
            let inv_a = _mm512_set1_ps(s.inv_a);
            let left = _mm512_sub_ps(v_mx, _mm512_mul_ps(_mm512_sub_ps(sq, bdy), inv_a));
            let right = _mm512_add_ps(v_mx, _mm512_mul_ps(_mm512_add_ps(sq, bdy), inv_a));
            let ok = _mm512_mask_cmp_ps_mask::<_CMP_NGT_UQ>(ok, left, v_xh);
            let ok = _mm512_mask_cmp_ps_mask::<_CMP_NLT_UQ>(ok, right, v_xl);
            rows &= ok as u32;
            if rows == 0 {
                continue;
            }
            let cdy2 = _mm512_mul_ps(_mm512_mul_ps(_mm512_set1_ps(0.5 * cc), dy), dy);
            // SAFETY: both arrays hold 16 floats.
            unsafe {
                _mm512_storeu_ps(bdy_rows.as_mut_ptr(), bdy);
                _mm512_storeu_ps(cdy2_rows.as_mut_ptr(), cdy2);
            }
            // per-lane terms shared by every row: dx and 0.5 a dx^2
            let dx = _mm512_sub_ps(v_mx, px);
            let adx2 = _mm512_mul_ps(_mm512_mul_ps(_mm512_set1_ps(0.5 * ca), dx), dx);
            let op = _mm512_set1_ps(s.opacity);
            let (cr, cg, cbl) = (
                _mm512_set1_ps(s.rgb[0]),
                _mm512_set1_ps(s.rgb[1]),
                _mm512_set1_ps(s.rgb[2]),
            );
            let z = _mm512_set1_ps(s.depth);
            evals += (LANES as u32 * rows.count_ones()) as u64;
            while rows != 0 {
                let r = rows.trailing_zeros() as usize;
                rows &= rows - 1;
                let o = r * LANES;
                // SAFETY: r < 16, so o..o + 16 lies inside each 256-float array of `out`.
                let (tp, c0p, c1p, c2p, dp) = unsafe {
                    (
                        t_ptr.add(o),
                        c0_ptr.add(o),
                        c1_ptr.add(o),
                        c2_ptr.add(o),
                        d_ptr.add(o),
                    )
                };
                let sigma = _mm512_add_ps(
                    _mm512_fmadd_ps(_mm512_set1_ps(bdy_rows[r]), dx, adx2),
                    _mm512_set1_ps(cdy2_rows[r]),
                );
                // exp(-sigma), exactly as exp_neg::<true>
                let sc = _mm512_min_ps(sigma, clamp);
                let tt = _mm512_fnmadd_ps(sc, _mm512_set1_ps(LOG2E), magic);
                let n = _mm512_sub_ps(tt, magic);
                let scale = _mm512_castsi512_ps(_mm512_slli_epi32::<23>(_mm512_castps_si512(tt)));
                let x = _mm512_xor_ps(sc, _mm512_set1_ps(-0.0));
                let rr = _mm512_fmadd_ps(n, _mm512_set1_ps(-LN2_HI), x);
                let rr = _mm512_fmadd_ps(n, _mm512_set1_ps(-LN2_LO), rr);
                let mut q = _mm512_set1_ps(1.987_569_1e-4);
                q = _mm512_fmadd_ps(q, rr, _mm512_set1_ps(1.398_199_9e-3));
                q = _mm512_fmadd_ps(q, rr, _mm512_set1_ps(8.333_452e-3));
                q = _mm512_fmadd_ps(q, rr, _mm512_set1_ps(4.166_579_6e-2));
                q = _mm512_fmadd_ps(q, rr, _mm512_set1_ps(1.666_666_5e-1));
                q = _mm512_fmadd_ps(q, rr, half);
                let y = _mm512_add_ps(_mm512_fmadd_ps(q, _mm512_mul_ps(rr, rr), rr), one);
                let e = _mm512_mul_ps(op, _mm512_mul_ps(y, scale));
                let alpha = _mm512_min_ps(e, max_alpha);
                // SAFETY: see above
                let t = unsafe { _mm512_loadu_ps(tp) };
                let valid = _mm512_cmp_ps_mask::<_CMP_GE_OQ>(sigma, zero);
                let valid = _mm512_mask_cmp_ps_mask::<_CMP_GE_OQ>(valid, alpha, thr);
                let valid = _mm512_mask_cmp_ps_mask::<_CMP_GT_OQ>(valid, t, zero);
                let tn = _mm512_mul_ps(t, _mm512_sub_ps(one, alpha));
                let contrib = _mm512_mask_cmp_ps_mask::<_CMP_GT_OQ>(valid, tn, t_min);
                let w = _mm512_mul_ps(alpha, t);
                // non-contributing lanes that were valid stop: T becomes -T
                let t_new = _mm512_mask_sub_ps(t, valid & !contrib, zero, t);
                let t_new = _mm512_mask_mov_ps(t_new, contrib, tn);
                // SAFETY: see above
                unsafe {
                    _mm512_storeu_ps(
                        c0p,
                        _mm512_mask3_fmadd_ps(w, cr, _mm512_loadu_ps(c0p), contrib),
                    );
                    _mm512_storeu_ps(
                        c1p,
                        _mm512_mask3_fmadd_ps(w, cg, _mm512_loadu_ps(c1p), contrib),
                    );
                    _mm512_storeu_ps(
                        c2p,
                        _mm512_mask3_fmadd_ps(w, cbl, _mm512_loadu_ps(c2p), contrib),
                    );
                    _mm512_storeu_ps(
                        dp,
                        _mm512_mask3_fmadd_ps(w, z, _mm512_loadu_ps(dp), contrib),
                    );
                    _mm512_storeu_ps(tp, t_new);
                }
                // a row is done when every lane's T is negative (sign bit set)
                if _mm512_movepi32_mask(_mm512_castps_si512(t_new)) == 0xFFFF {
                    alive &= !(1 << r);
                    if alive == 0 {
                        return evals;
                    }
                }
            }
        }
    }
    evals
}
