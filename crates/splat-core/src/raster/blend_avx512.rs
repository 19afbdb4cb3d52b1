//! The AVX-512 blend kernel, written with `core::arch` intrinsics (see `blend.rs` for the
//! generic kernel it mirrors operation for operation, so both give the same bits).
use super::blend::{
    prefetch, BlendParams, Counts, Slot, TileOut, EXP2_16THS, EXP_C_HI, EXP_C_LO, EXP_K16,
    EXP_MAGIC, LANES, PREFETCH_AHEAD, SIGMA_CLAMP, T_MIN,
};
use super::project::{Splat, ALPHA_THRESHOLD};

/// Splats per batch of this kernel (twice the AVX2 kernel's `CHUNK`): a row's state is loaded
/// and stored once per batch, so longer batches amortise that over more splats.
const BATCH: usize = 32;

/// Explicit AVX-512 kernel: the same formulas and operation order as `blend_tile_impl::<true>`,
/// so the same image bits, organised for the CPU rather than per splat. The tile's list is taken
/// in batches of `BATCH` splats:
/// - phase 1, branch-free per splat: the contour test of all 16 rows at once (one mask of the
///   rows it reaches), and the per-row (b dy, 0.5 c dy^2) and per-lane (dx, 0.5 a dx^2) terms
///   of its exponent, kept in `slots`;
/// - phase 2, two rows at a time in lockstep: each row's transmittance, colour and depth stay
///   in registers while the batch's splats that reach the row (one mask test over the 16 row
///   masks) are blended in list order, with masked accumulations. Lanes that stop are dropped
///   from the row's `live` mask; a row with none left takes no more splats and is done.
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
    let table = unsafe { _mm512_loadu_ps(EXP2_16THS.as_ptr() as *const f32) };
    let sixteenth = _mm512_set1_ps(1.0 / 16.0);
    let mut evals = 0u64;
    let mut useful = 0u64;
    let mut slots = [Slot::default(); BATCH];
    let t_ptr = out.t.as_mut_ptr() as *mut f32;
    let c0_ptr = out.c[0].as_mut_ptr() as *mut f32;
    let c1_ptr = out.c[1].as_mut_ptr() as *mut f32;
    let c2_ptr = out.c[2].as_mut_ptr() as *mut f32;
    let d_ptr = out.d.as_mut_ptr() as *mut f32;
    // a row's state in registers: transmittance, colour and depth sums, live lanes
    struct Row {
        t: __m512,
        c0: __m512,
        c1: __m512,
        c2: __m512,
        d: __m512,
        lv: u16,
    }
    macro_rules! load_row {
        ($r:expr) => {{
            let o = $r * LANES;
            // SAFETY: r < 16, so o..o + 16 lies inside each 256-float array of `out`.
            unsafe {
                Row {
                    t: _mm512_loadu_ps(t_ptr.add(o)),
                    c0: _mm512_loadu_ps(c0_ptr.add(o)),
                    c1: _mm512_loadu_ps(c1_ptr.add(o)),
                    c2: _mm512_loadu_ps(c2_ptr.add(o)),
                    d: _mm512_loadu_ps(d_ptr.add(o)),
                    lv: live[$r],
                }
            }
        }};
    }
    macro_rules! store_row {
        ($row:ident, $r:expr) => {{
            let o = $r * LANES;
            // SAFETY: as in `load_row`
            unsafe {
                _mm512_storeu_ps(t_ptr.add(o), $row.t);
                _mm512_storeu_ps(c0_ptr.add(o), $row.c0);
                _mm512_storeu_ps(c1_ptr.add(o), $row.c1);
                _mm512_storeu_ps(c2_ptr.add(o), $row.c2);
                _mm512_storeu_ps(d_ptr.add(o), $row.d);
            }
            live[$r] = $row.lv;
            if $row.lv == 0 {
                alive &= !(1 << $r);
            }
        }};
    }
    // blend batch splat k into row r
    macro_rules! step {
        ($row:ident, $r:expr, $k:expr) => {{
            let slot = &slots[$k];
            let s = &slot.splat;
            // SAFETY: both arrays hold 16 aligned floats.
            let (dx, adx2) = unsafe {
                (
                    _mm512_load_ps(slot.dx.as_ptr()),
                    _mm512_load_ps(slot.adx2.as_ptr()),
                )
            };
            let sigma = _mm512_add_ps(
                _mm512_fmadd_ps(_mm512_set1_ps(slot.bdy[$r]), dx, adx2),
                _mm512_set1_ps(slot.cdy2[$r]),
            );
            // alpha = exp(ln_op - sigma), exactly as blend::opacity_exp::<true>
            let sg = _mm512_castsi512_ps(_mm512_min_epu32(_mm512_castps_si512(sigma), clamp));
            let u = _mm512_sub_ps(sg, _mm512_set1_ps(s.ln_opacity));
            let tk = _mm512_fnmadd_ps(u, k16, magic);
            let kf = _mm512_sub_ps(tk, magic);
            let rr = _mm512_fmadd_ps(kf, c_hi, u);
            let rr = _mm512_fmadd_ps(kf, c_lo, rr);
            let y = _mm512_fmadd_ps(rr, sixth, half);
            let y = _mm512_fmadd_ps(y, rr, minus_one);
            let y = _mm512_fmadd_ps(y, rr, one);
            // y 2^(k/16) = (y table[k mod 16]) 2^floor(k / 16): scalef takes the floor of
            // k / 16 (exact in float) itself, and scaling by a power of two rounds as the
            // generic kernel's exponent-bits add does (the result stays normal: u < 86)
            let tab = _mm512_permutexvar_ps(_mm512_castps_si512(tk), table);
            let ev = _mm512_scalef_ps(_mm512_mul_ps(y, tab), _mm512_mul_ps(kf, sixteenth));
            let alpha = _mm512_min_ps(ev, max_alpha);
            let valid = _mm512_mask_cmp_ps_mask::<_CMP_GE_OQ>($row.lv, alpha, thr);
            if COUNT {
                useful += valid.count_ones() as u64;
            }
            let w = _mm512_mul_ps(alpha, $row.t);
            let tn = _mm512_sub_ps($row.t, w);
            let contrib = _mm512_mask_cmp_ps_mask::<_CMP_GT_OQ>(valid, tn, t_min);
            $row.c0 = _mm512_mask3_fmadd_ps(w, _mm512_set1_ps(s.rgb[0]), $row.c0, contrib);
            $row.c1 = _mm512_mask3_fmadd_ps(w, _mm512_set1_ps(s.rgb[1]), $row.c1, contrib);
            $row.c2 = _mm512_mask3_fmadd_ps(w, _mm512_set1_ps(s.rgb[2]), $row.c2, contrib);
            $row.d = _mm512_mask3_fmadd_ps(w, _mm512_set1_ps(s.depth), $row.d, contrib);
            $row.t = _mm512_mask_mov_ps($row.t, contrib, tn);
            // valid lanes that do not contribute stop
            $row.lv = _kor_mask16(_kandn_mask16(valid, $row.lv), contrib);
        }};
    }
    for list in lists {
        for (c, chunk) in list.chunks(BATCH).enumerate() {
            // phase 1, branch-free per splat: which rows of the tile it reaches, and the
            // per-row and per-lane terms of its exponent
            let mut masks = [0u32; BATCH];
            for (k, &gi) in chunk.iter().enumerate() {
                if let Some(&ahead) = list.get(c * BATCH + k + PREFETCH_AHEAD) {
                    prefetch(splats, ahead as usize);
                }
                let s = &splats[gi as usize];
                let (mx, my) = (s.xy[0], s.xy[1]);
                let [ca, cb, cc] = s.conic;
                let ey = s.half_height;
                // rows r of `row_span`: ceil(my - ey - 0.5 - y0) <= r <= floor(my + ey - 0.5 -
                // y0), i.e. (r an integer, the splat finite) the two bounds compared with r
                let lo = _mm512_set1_ps(my - ey - 0.5 - y0f);
                let hi = _mm512_set1_ps(my + ey - 0.5 - y0f);
                let range = _mm512_mask_cmp_ps_mask::<_CMP_GE_OQ>(alive as u16, lane_f, lo);
                let range = _mm512_mask_cmp_ps_mask::<_CMP_LE_OQ>(range, lane_f, hi);
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
                let ok = _mm512_mask_cmp_ps_mask::<_CMP_GE_OQ>(range, disc, zero);
                let sq = _mm512_sqrt_ps(disc);
                let inv_a = _mm512_set1_ps(s.inv_a);
                let left = _mm512_sub_ps(v_mx, _mm512_mul_ps(_mm512_sub_ps(sq, bdy), inv_a));
                let right = _mm512_add_ps(v_mx, _mm512_mul_ps(_mm512_add_ps(sq, bdy), inv_a));
                let ok = _mm512_mask_cmp_ps_mask::<_CMP_NGT_UQ>(ok, left, v_xh);
                let ok = _mm512_mask_cmp_ps_mask::<_CMP_NLT_UQ>(ok, right, v_xl);
                let rows = ok as u32;
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
            // phase 2, rows two at a time: each row's transmittance, colour and depth stay in
            // registers while the batch's splats that reach it are blended in list order; the
            // two rows are independent, so their dependency chains on T overlap
            // SAFETY: `masks` holds BATCH = 32 u32.
            let (m0, m1) = unsafe {
                (
                    _mm512_loadu_si512(masks.as_ptr() as *const _),
                    _mm512_loadu_si512(masks.as_ptr().add(16) as *const _),
                )
            };
            let mut todo = _mm512_reduce_or_epi32(_mm512_or_si512(m0, m1)) as u32;
            // the batch's splats that reach row r, as bits of their batch index
            macro_rules! row_splats {
                ($r:expr) => {{
                    let bit = _mm512_set1_epi32(1 << $r);
                    _mm512_test_epi32_mask(m0, bit) as u32
                        | (_mm512_test_epi32_mask(m1, bit) as u32) << 16
                }};
            }
            let mut steps = 0u64;
            while todo != 0 {
                let ra = todo.trailing_zeros() as usize;
                todo &= todo - 1;
                let mut ksa = row_splats!(ra);
                let mut a = load_row!(ra);
                if todo != 0 {
                    let rb = todo.trailing_zeros() as usize;
                    todo &= todo - 1;
                    let mut ksb = row_splats!(rb);
                    let mut b = load_row!(rb);
                    // both rows in lockstep while both have splats and live lanes
                    while ksa != 0 && ksb != 0 {
                        let ka = ksa.trailing_zeros() as usize;
                        ksa &= ksa - 1;
                        let kb = ksb.trailing_zeros() as usize;
                        ksb &= ksb - 1;
                        step!(a, ra, ka);
                        step!(b, rb, kb);
                        steps += 2;
                        // a row whose lanes all stopped takes no more splats
                        if a.lv == 0 {
                            ksa = 0;
                        }
                        if b.lv == 0 {
                            ksb = 0;
                        }
                    }
                    while ksb != 0 {
                        let k = ksb.trailing_zeros() as usize;
                        ksb &= ksb - 1;
                        step!(b, rb, k);
                        steps += 1;
                        if b.lv == 0 {
                            break;
                        }
                    }
                    store_row!(b, rb);
                }
                while ksa != 0 {
                    let k = ksa.trailing_zeros() as usize;
                    ksa &= ksa - 1;
                    step!(a, ra, k);
                    steps += 1;
                    if a.lv == 0 {
                        break;
                    }
                }
                store_row!(a, ra);
            }
            // every step ran on a row with live lanes: 16 evaluations each
            evals += LANES as u64 * steps;
            if alive == 0 {
                return Counts { evals, useful };
            }
        }
    }
    Counts { evals, useful }
}
