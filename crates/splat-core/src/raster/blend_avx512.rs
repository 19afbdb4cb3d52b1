//! The AVX-512 blend kernel, written with `core::arch` intrinsics (see `blend.rs` for the
//! generic kernel it mirrors operation for operation, so both give the same bits).
use super::blend::{
    prefetch, row_mask, BlendParams, Counts, Slot, TileOut, CHUNK, EXP2_16THS, EXP_C_HI, EXP_C_LO,
    EXP_K16, EXP_MAGIC, LANES, PREFETCH_AHEAD, SIGMA_CLAMP, T_MIN,
};
use super::project::{Splat, ALPHA_THRESHOLD};

/// Explicit AVX-512 kernel: the same formulas and operation order as `blend_tile_impl::<true>`,
/// so the same image bits, organised for the CPU rather than per splat. The tile's list is taken
/// in batches of `CHUNK` splats:
/// - phase 1, branch-free per splat: the contour test of all 16 rows at once (one mask of the
///   rows it reaches), and the per-row (b dy, 0.5 c dy^2) and per-lane (dx, 0.5 a dx^2) terms
///   of its exponent, kept in `slots`;
/// - phase 2, row by row: the row's transmittance, colour and depth stay in registers while the
///   batch's splats that reach the row (one mask test over the 16 row masks) are blended in
///   list order, with masked accumulations. Lanes that stop are dropped from the row's `live`
///   mask; a row with none left is done.
///
/// Keeping a row in registers takes the store-to-load round trip out of the per-splat
/// dependency chain on T, which (with the opacity folded into the exponential) is what lifts
/// the kernel from about 1.6 to about 2.9 G evaluations/s on 2 Zen 4 cores.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx2,fma")]
pub(super) fn blend_tile_avx512<'a, const COUNT: bool>(
    x0: u32,
    y0: u32,
    p: &BlendParams,
    splats: &[Splat],
    lists: impl Iterator<Item = &'a [u32]>,
    out: &mut TileOut,
) -> Counts {
    use std::arch::x86_64::*;

    // lanes and rows outside the image start done: `live` holds each row's lanes that may still
    // take splats (the generic kernel marks done lanes with a negative T instead; both write
    // |T| out, so the images agree)
    let mut live = [0u16; LANES];
    let mut alive: u32 = 0;
    let cols = p.width.saturating_sub(x0).min(LANES as u32);
    for (r, row) in live.iter_mut().enumerate() {
        if y0 + (r as u32) < p.height {
            *row = ((1u32 << cols) - 1) as u16;
            if cols > 0 {
                alive |= 1 << r;
            }
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
    let clamp = _mm512_set1_epi32(SIGMA_CLAMP.to_bits() as i32);
    let magic = _mm512_set1_ps(EXP_MAGIC);
    let k16 = _mm512_set1_ps(EXP_K16);
    let (c_hi, c_lo) = (_mm512_set1_ps(EXP_C_HI), _mm512_set1_ps(EXP_C_LO));
    let (sixth, half) = (_mm512_set1_ps(-1.0 / 6.0), _mm512_set1_ps(0.5));
    let minus_one = _mm512_set1_ps(-1.0);
    // SAFETY: the table holds 16 u32.
    let table = unsafe { _mm512_loadu_si512(EXP2_16THS.as_ptr() as *const _) };
    let mut evals = 0u64;
    let mut useful = 0u64;
    let mut slots = [Slot::default(); CHUNK];
    let t_ptr = out.t.as_mut_ptr() as *mut f32;
    let c0_ptr = out.c[0].as_mut_ptr() as *mut f32;
    let c1_ptr = out.c[1].as_mut_ptr() as *mut f32;
    let c2_ptr = out.c[2].as_mut_ptr() as *mut f32;
    let d_ptr = out.d.as_mut_ptr() as *mut f32;
    for list in lists {
        for (c, chunk) in list.chunks(CHUNK).enumerate() {
            // phase 1, branch-free per splat: which rows of the tile it reaches, and the
            // per-row and per-lane terms of its exponent
            let mut masks = [0u32; CHUNK];
            for (k, &gi) in chunk.iter().enumerate() {
                if let Some(&ahead) = list.get(c * CHUNK + k + PREFETCH_AHEAD) {
                    prefetch(splats, ahead as usize);
                }
                let s = &splats[gi as usize];
                let (mx, my) = (s.xy[0], s.xy[1]);
                let [ca, cb, cc] = s.conic;
                let ey = s.half_height;
                let range = row_mask(my, ey, y0f);
                // the contour test of every row at once: disc = 2 a level - dy^2 det >= 0 and
                // the contour's dx range [(-b dy - sq) / a, (-b dy + sq) / a] reaches the tile
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
                let rows = range & alive & ok as u32;
                let cdy2 = _mm512_mul_ps(_mm512_mul_ps(_mm512_set1_ps(0.5 * cc), dy), dy);
                // per-lane terms shared by every row: dx and 0.5 a dx^2
                let dx = _mm512_sub_ps(v_mx, px);
                let adx2 = _mm512_mul_ps(_mm512_mul_ps(_mm512_set1_ps(0.5 * ca), dx), dx);
                let slot = &mut slots[k];
                slot.splat = *s;
                masks[k] = rows;
                // SAFETY: each array holds 16 aligned floats.
                unsafe {
                    _mm512_store_ps(slot.bdy.as_mut_ptr(), bdy);
                    _mm512_store_ps(slot.cdy2.as_mut_ptr(), cdy2);
                    _mm512_store_ps(slot.dx.as_mut_ptr(), dx);
                    _mm512_store_ps(slot.adx2.as_mut_ptr(), adx2);
                }
            }
            // phase 2, row by row: the row's transmittance, colour and depth stay in registers
            // while the batch's splats that reach it are blended in list order
            // SAFETY: `masks` holds CHUNK = 16 u32.
            let m = unsafe { _mm512_loadu_si512(masks.as_ptr() as *const _) };
            let mut todo = _mm512_reduce_or_epi32(m) as u32;
            while todo != 0 {
                let r = todo.trailing_zeros() as usize;
                todo &= todo - 1;
                let mut ks = _mm512_test_epi32_mask(m, _mm512_set1_epi32(1 << r)) as u32;
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
                // SAFETY: see above
                let (mut t, mut c0, mut c1, mut c2, mut d) = unsafe {
                    (
                        _mm512_loadu_ps(tp),
                        _mm512_loadu_ps(c0p),
                        _mm512_loadu_ps(c1p),
                        _mm512_loadu_ps(c2p),
                        _mm512_loadu_ps(dp),
                    )
                };
                let mut lv = live[r];
                while ks != 0 {
                    let k = ks.trailing_zeros() as usize;
                    ks &= ks - 1;
                    let slot = &slots[k];
                    let s = &slot.splat;
                    // SAFETY: both arrays hold 16 aligned floats.
                    let (dx, adx2) = unsafe {
                        (
                            _mm512_load_ps(slot.dx.as_ptr()),
                            _mm512_load_ps(slot.adx2.as_ptr()),
                        )
                    };
                    let sigma = _mm512_add_ps(
                        _mm512_fmadd_ps(_mm512_set1_ps(slot.bdy[r]), dx, adx2),
                        _mm512_set1_ps(slot.cdy2[r]),
                    );
                    // alpha = exp(ln_op - sigma), exactly as blend::opacity_exp::<true>
                    let sg =
                        _mm512_castsi512_ps(_mm512_min_epu32(_mm512_castps_si512(sigma), clamp));
                    let u = _mm512_sub_ps(sg, _mm512_set1_ps(s.ln_opacity));
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
                    let ev = _mm512_mul_ps(y, _mm512_castsi512_ps(scale));
                    let alpha = _mm512_min_ps(ev, max_alpha);
                    let valid = _mm512_mask_cmp_ps_mask::<_CMP_GE_OQ>(lv, alpha, thr);
                    if COUNT {
                        useful += valid.count_ones() as u64;
                    }
                    let w = _mm512_mul_ps(alpha, t);
                    let tn = _mm512_sub_ps(t, w);
                    let contrib = _mm512_mask_cmp_ps_mask::<_CMP_GT_OQ>(valid, tn, t_min);
                    c0 = _mm512_mask3_fmadd_ps(w, _mm512_set1_ps(s.rgb[0]), c0, contrib);
                    c1 = _mm512_mask3_fmadd_ps(w, _mm512_set1_ps(s.rgb[1]), c1, contrib);
                    c2 = _mm512_mask3_fmadd_ps(w, _mm512_set1_ps(s.rgb[2]), c2, contrib);
                    d = _mm512_mask3_fmadd_ps(w, _mm512_set1_ps(s.depth), d, contrib);
                    t = _mm512_mask_mov_ps(t, contrib, tn);
                    // a row counts while alive; valid lanes that do not contribute stop
                    evals += LANES as u64 * (lv != 0) as u64;
                    lv = (lv & !valid) | contrib;
                }
                // SAFETY: see above
                unsafe {
                    _mm512_storeu_ps(tp, t);
                    _mm512_storeu_ps(c0p, c0);
                    _mm512_storeu_ps(c1p, c1);
                    _mm512_storeu_ps(c2p, c2);
                    _mm512_storeu_ps(dp, d);
                }
                live[r] = lv;
                if lv == 0 {
                    alive &= !(1 << r);
                }
            }
            if alive == 0 {
                return Counts { evals, useful };
            }
        }
    }
    Counts { evals, useful }
}
