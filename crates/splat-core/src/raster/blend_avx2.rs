//! The AVX2 + FMA blend kernel, written with `core::arch` intrinsics: the organisation of the
//! AVX-512 kernel (see `blend_avx512.rs`) with each 16-pixel row handled as two 8-lane halves
//! and lane masks held in vectors instead of mask registers. The work unit is a half row (8x1
//! pixels): phase 1 tests the splat's contour range on each row against each half's columns,
//! so a half the footprint misses is skipped. Same formulas and operation order as
//! `blend_tile_impl::<true>`, so the same image bits (tested).
use super::blend::{
    prefetch, BlendParams, Counts, Slot, Stream, TileOut, CHUNK, EXP2_16THS, EXP_C_HI, EXP_C_LO,
    EXP_K16, EXP_MAGIC, LANES, SIGMA_CLAMP, T_MIN,
};
use super::project::{Splat, ALPHA_THRESHOLD};
use std::mem::MaybeUninit;
use std::ptr::addr_of_mut;

/// Lanes of one AVX2 vector: a row is two halves.
const HALF: usize = 8;

/// Blend one tile with AVX2 and FMA; returns the number of Gaussian-pixel evaluations (8 per
/// half row evaluated while the half has live pixels). `out` is reset first (T = 1, zero
/// sums); `DEPTH` false skips the depth sums and leaves `out.d` as it was.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
pub(super) fn blend_tile_avx2<'a, const COUNT: bool, const DEPTH: bool>(
    x0: u32,
    y0: u32,
    p: &BlendParams,
    splats: &[Splat],
    lists: impl Iterator<Item = &'a [u32]>,
    out: &mut TileOut,
) -> Counts {
    use std::arch::x86_64::*;

    out.t = [[1.0; LANES]; LANES];
    out.c = [[[0.0; LANES]; LANES]; 3];
    if DEPTH {
        out.d = [[0.0; LANES]; LANES];
    }
    // live lanes per row as 16 bits (low half: bits 0-7); rows and lanes outside the image
    // start done
    let mut live = [0u32; LANES];
    let mut alive: u32 = 0;
    let cols = p.width.saturating_sub(x0).min(LANES as u32);
    for (r, row) in live.iter_mut().enumerate() {
        if y0 + (r as u32) < p.height && cols > 0 {
            *row = (1u32 << cols) - 1;
            alive |= 1 << r;
        }
    }
    let lane_f = _mm256_setr_ps(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0);
    let eight = _mm256_set1_ps(8.0);
    let half = _mm256_set1_ps(0.5);
    // pixel centres (x0 + l) + 0.5 and (y0 + r) + 0.5 of both halves, rounded as in the
    // generic kernel (x0 + l is exact)
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
    // tile row indices of both halves
    let row_f = [lane_f, _mm256_add_ps(lane_f, eight)];
    // first and last pixel centres of each half of the columns (exact in float)
    let v_xl = [0, HALF].map(|c| _mm256_set1_ps((x0 + c as u32) as f32 + 0.5));
    let v_xh = [HALF - 1, LANES - 1].map(|c| _mm256_set1_ps((x0 + c as u32) as f32 + 0.5));
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
    // SAFETY: the table holds 16 u32.
    let (tab_lo, tab_hi) = unsafe {
        (
            _mm256_loadu_si256(EXP2_16THS.as_ptr() as *const _),
            _mm256_loadu_si256(EXP2_16THS.as_ptr().add(HALF) as *const _),
        )
    };
    // lane l of a half holds bit l: turns an 8-bit live mask into lane masks
    let lane_bits = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
    let mut evals = 0u64;
    let mut useful = 0u64;
    // written by phase 1 before phase 2 reads them: no clearing of the batch each tile
    let mut slots = [const { MaybeUninit::<Slot>::uninit() }; CHUNK];
    let t_ptr = out.t.as_mut_ptr() as *mut f32;
    let c0_ptr = out.c[0].as_mut_ptr() as *mut f32;
    let c1_ptr = out.c[1].as_mut_ptr() as *mut f32;
    let c2_ptr = out.c[2].as_mut_ptr() as *mut f32;
    let d_ptr = out.d.as_mut_ptr() as *mut f32;
    // the tile's lists as one stream of batches, the next batch's splats prefetched while
    // this one is blended (batches and prefetch run across the lists' ends)
    let mut stream = Stream::new(lists);
    // up to 16 entries by two masked moves (masked-off lanes are neither read nor written)
    let copy = |src: &[u32], dst: &mut [u32]| {
        let k = src.len().min(dst.len()).min(CHUNK) as i32;
        let idx = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        let m_lo = _mm256_cmpgt_epi32(_mm256_set1_epi32(k), idx);
        let m_hi = _mm256_cmpgt_epi32(_mm256_set1_epi32(k - HALF as i32), idx);
        // SAFETY: the masks cover the first k <= 16 entries of both slices only.
        unsafe {
            let (s, d) = (src.as_ptr() as *const i32, dst.as_mut_ptr() as *mut i32);
            _mm256_maskstore_epi32(d, m_lo, _mm256_maskload_epi32(s, m_lo));
            if k > HALF as i32 {
                let (s, d) = (s.add(HALF), d.add(HALF));
                _mm256_maskstore_epi32(d, m_hi, _mm256_maskload_epi32(s, m_hi));
            }
        }
    };
    let mut next = [0u32; CHUNK];
    let mut n_next = stream.fill(&mut next, copy);
    for &gi in &next[..n_next] {
        prefetch(splats, gi as usize);
    }
    while n_next != 0 {
        let (batch, n) = (next, n_next);
        n_next = stream.fill(&mut next, copy);
        {
            // phase 1, branch-free per splat: the row halves it reaches (bit r: columns 0-7 of
            // row r, bit 16 + r: columns 8-15) and its exponent's terms
            let mut masks = [0u32; CHUNK];
            for (k, &gi) in batch[..n].iter().enumerate() {
                if k < n_next {
                    prefetch(splats, next[k] as usize);
                }
                let s = &splats[gi as usize];
                let (mx, my) = (s.xy[0], s.xy[1]);
                let [ca, cb, cc] = s.conic;
                let ey = s.half_height;
                // rows r of `row_span`: ceil(my - ey - 0.5 - y0) <= r <= floor(my + ey - 0.5 -
                // y0), i.e. (r an integer, the splat finite) the two bounds compared with r
                let lo = _mm256_set1_ps(my - ey - 0.5 - y0f);
                let hi = _mm256_set1_ps(my + ey - 0.5 - y0f);
                let v_mx = _mm256_set1_ps(mx);
                let slot = slots[k].as_mut_ptr();
                // SAFETY: `slot` points to slots[k]; phase 1 writes all its fields.
                unsafe { addr_of_mut!((*slot).splat).write(*s) };
                let mut ok = 0u32;
                for h in 0..2 {
                    // the contour test of 8 rows at once (see the AVX-512 kernel)
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
                    let in_span = _mm256_and_ps(
                        _mm256_cmp_ps::<_CMP_GE_OQ>(row_f[h], lo),
                        _mm256_cmp_ps::<_CMP_LE_OQ>(row_f[h], hi),
                    );
                    let m = _mm256_and_ps(in_span, _mm256_cmp_ps::<_CMP_GE_OQ>(disc, zero));
                    // the rows' contour ranges meet the columns of half 0 and of half 1
                    for (c, (xl, xh)) in v_xl.iter().zip(&v_xh).enumerate() {
                        let mc = _mm256_and_ps(
                            m,
                            _mm256_and_ps(
                                _mm256_cmp_ps::<_CMP_NGT_UQ>(left, *xh),
                                _mm256_cmp_ps::<_CMP_NLT_UQ>(right, *xl),
                            ),
                        );
                        ok |= (_mm256_movemask_ps(mc) as u32) << (h * HALF + c * LANES);
                    }
                    let cdy2 = _mm256_mul_ps(_mm256_mul_ps(_mm256_set1_ps(0.5 * cc), dy), dy);
                    // per-lane terms of this half of the columns
                    let dx = _mm256_sub_ps(v_mx, px[h]);
                    let adx2 = _mm256_mul_ps(_mm256_mul_ps(_mm256_set1_ps(0.5 * ca), dx), dx);
                    // SAFETY: each array holds 16 floats, 32-byte aligned at h * 8.
                    unsafe {
                        let f = |a: *mut [f32; LANES]| (a as *mut f32).add(h * HALF);
                        _mm256_store_ps(f(addr_of_mut!((*slot).bdy)), bdy);
                        _mm256_store_ps(f(addr_of_mut!((*slot).cdy2)), cdy2);
                        _mm256_store_ps(f(addr_of_mut!((*slot).dx)), dx);
                        _mm256_store_ps(f(addr_of_mut!((*slot).adx2)), adx2);
                    }
                }
                masks[k] = (alive | alive << LANES) & ok;
            }
            // phase 2, row by row and half by half, state in registers
            // SAFETY: `masks` holds CHUNK = 16 u32.
            let (m_lo, m_hi) = unsafe {
                (
                    _mm256_loadu_si256(masks.as_ptr() as *const _),
                    _mm256_loadu_si256(masks.as_ptr().add(HALF) as *const _),
                )
            };
            let todo = masks.iter().fold(0, |a, &m| a | m);
            let mut todo = (todo | todo >> LANES) & 0xFFFF;
            while todo != 0 {
                let r = todo.trailing_zeros() as usize;
                todo &= todo - 1;
                let mut row_live = 0u32;
                for h in 0..2 {
                    // the batch's splats that reach half h of row r, as bits of their index
                    let bit = _mm256_set1_epi32(1 << (r + h * LANES));
                    let hit = |m| {
                        let z =
                            _mm256_cmpeq_epi32(_mm256_and_si256(m, bit), _mm256_setzero_si256());
                        !(_mm256_movemask_ps(_mm256_castsi256_ps(z)) as u32) & 0xFF
                    };
                    let mut ks = hit(m_lo) | hit(m_hi) << HALF;
                    let lbits = (live[r] >> (h * HALF)) & 0xFF;
                    if ks == 0 || lbits == 0 {
                        row_live |= lbits << (h * HALF);
                        continue;
                    }
                    let o = r * LANES + h * HALF;
                    // SAFETY: r < 16, h < 2: o..o + 8 lies inside each 256-float array.
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
                            _mm256_loadu_ps(tp),
                            _mm256_loadu_ps(c0p),
                            _mm256_loadu_ps(c1p),
                            _mm256_loadu_ps(c2p),
                            if DEPTH {
                                _mm256_loadu_ps(dp)
                            } else {
                                _mm256_setzero_ps()
                            },
                        )
                    };
                    let mut lv = _mm256_castsi256_ps(_mm256_cmpeq_epi32(
                        _mm256_and_si256(_mm256_set1_epi32(lbits as i32), lane_bits),
                        lane_bits,
                    ));
                    while ks != 0 {
                        let k = ks.trailing_zeros() as usize;
                        ks &= ks - 1;
                        // SAFETY: k is a splat of this batch (its mask bit is set), whose
                        // slot phase 1 wrote.
                        let slot = unsafe { slots[k].assume_init_ref() };
                        let s = &slot.splat;
                        let q = h * HALF;
                        // SAFETY: both arrays hold 16 floats, 32-byte aligned at q.
                        let (dx, adx2) = unsafe {
                            (
                                _mm256_load_ps(slot.dx.as_ptr().add(q)),
                                _mm256_load_ps(slot.adx2.as_ptr().add(q)),
                            )
                        };
                        let sigma = _mm256_add_ps(
                            _mm256_fmadd_ps(_mm256_set1_ps(slot.bdy[r]), dx, adx2),
                            _mm256_set1_ps(slot.cdy2[r]),
                        );
                        // alpha = exp(ln_op - sigma), exactly as blend::opacity_exp::<true>
                        let sg = _mm256_castsi256_ps(_mm256_min_epu32(
                            _mm256_castps_si256(sigma),
                            clamp,
                        ));
                        let u = _mm256_sub_ps(sg, _mm256_set1_ps(s.ln_opacity));
                        let tk = _mm256_fnmadd_ps(u, k16, magic);
                        let kf = _mm256_sub_ps(tk, magic);
                        let rr = _mm256_fmadd_ps(kf, c_hi, u);
                        let rr = _mm256_fmadd_ps(kf, c_lo, rr);
                        let y = _mm256_fmadd_ps(rr, sixth, half);
                        let y = _mm256_fmadd_ps(y, rr, minus_one);
                        let y = _mm256_fmadd_ps(y, rr, one);
                        let ti = _mm256_castps_si256(tk);
                        // 16-entry table: bit 3 of the index picks the upper 8 entries
                        let tab = _mm256_blendv_ps(
                            _mm256_castsi256_ps(_mm256_permutevar8x32_epi32(tab_lo, ti)),
                            _mm256_castsi256_ps(_mm256_permutevar8x32_epi32(tab_hi, ti)),
                            _mm256_castsi256_ps(_mm256_slli_epi32::<28>(ti)),
                        );
                        let scale = _mm256_add_epi32(
                            _mm256_castps_si256(tab),
                            _mm256_slli_epi32::<23>(_mm256_srli_epi32::<4>(ti)),
                        );
                        let ev = _mm256_mul_ps(y, _mm256_castsi256_ps(scale));
                        let alpha = _mm256_min_ps(ev, max_alpha);
                        let valid = _mm256_and_ps(lv, _mm256_cmp_ps::<_CMP_GE_OQ>(alpha, thr));
                        if COUNT {
                            useful += _mm256_movemask_ps(valid).count_ones() as u64;
                        }
                        let w = _mm256_mul_ps(alpha, t);
                        let tn = _mm256_sub_ps(t, w);
                        let contrib = _mm256_and_ps(valid, _mm256_cmp_ps::<_CMP_GT_OQ>(tn, t_min));
                        // w = 0 where a lane does not contribute: c + 0 col = c exactly
                        let wc = _mm256_and_ps(w, contrib);
                        c0 = _mm256_fmadd_ps(wc, _mm256_set1_ps(s.rgb[0]), c0);
                        c1 = _mm256_fmadd_ps(wc, _mm256_set1_ps(s.rgb[1]), c1);
                        c2 = _mm256_fmadd_ps(wc, _mm256_set1_ps(s.rgb[2]), c2);
                        if DEPTH {
                            d = _mm256_fmadd_ps(wc, _mm256_set1_ps(s.depth), d);
                        }
                        t = _mm256_blendv_ps(t, tn, contrib);
                        // every step runs on a half with live lanes: 8 evaluations each
                        evals += HALF as u64;
                        // valid lanes that do not contribute stop
                        lv = _mm256_or_ps(_mm256_andnot_ps(valid, lv), contrib);
                        // a half whose lanes all stopped takes no more splats
                        if _mm256_movemask_ps(lv) == 0 {
                            break;
                        }
                    }
                    // SAFETY: see above
                    unsafe {
                        _mm256_storeu_ps(tp, t);
                        _mm256_storeu_ps(c0p, c0);
                        _mm256_storeu_ps(c1p, c1);
                        _mm256_storeu_ps(c2p, c2);
                        if DEPTH {
                            _mm256_storeu_ps(dp, d);
                        }
                    }
                    row_live |= (_mm256_movemask_ps(lv) as u32) << (h * HALF);
                }
                live[r] = row_live;
                if row_live == 0 {
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
