//! The AVX-512 blend kernel, written with `core::arch` intrinsics (see `blend.rs` for the
//! generic kernel it mirrors operation for operation, so both give the same bits).
use super::blend::{
    prefetch, BlendParams, Counts, Slot, Stream, TileOut, EXP2_16THS, EXP_C_HI, EXP_C_LO, EXP_K16,
    EXP_MAGIC, LANES, SIGMA_CLAMP, T_MIN,
};
use super::project::{Splat, ALPHA_THRESHOLD};
use std::mem::MaybeUninit;
use std::ptr::addr_of_mut;

/// Splats per batch of this kernel (twice the AVX2 kernel's `CHUNK`): a block's state is
/// loaded and stored once per batch, so longer batches amortise that over more splats.
const BATCH: usize = 32;

/// The tile's state in block order: `t[b][i]` is the pixel of lane i of block b, at tile row
/// 4 (b / 4) + i / 4 and column 4 (b % 4) + i % 4 (see [`block_pixel`]).
#[repr(C, align(64))]
struct Blocks {
    t: [[f32; LANES]; LANES],
    c: [[[f32; LANES]; LANES]; 3],
    d: [[f32; LANES]; LANES],
}

/// Tile (row, column) of lane `i` of 4x4 block `b`: blocks are numbered row by row over the
/// tile (b = 4 block-row + block-column), lanes row by row inside a block.
#[inline(always)]
const fn block_pixel(b: usize, i: usize) -> (usize, usize) {
    (4 * (b / 4) + i / 4, 4 * (b % 4) + i % 4)
}

impl Blocks {
    /// Copy the state into `out`'s row order (the depth sums only when `DEPTH`).
    fn write_rows<const DEPTH: bool>(&self, out: &mut TileOut) {
        for b in 0..LANES {
            for q in 0..4 {
                let (r, c) = block_pixel(b, 4 * q);
                let lanes = 4 * q..4 * q + 4;
                out.t[r][c..c + 4].copy_from_slice(&self.t[b][lanes.clone()]);
                for ch in 0..3 {
                    out.c[ch][r][c..c + 4].copy_from_slice(&self.c[ch][b][lanes.clone()]);
                }
                if DEPTH {
                    out.d[r][c..c + 4].copy_from_slice(&self.d[b][lanes]);
                }
            }
        }
    }
}

/// The 4x4-pixel blocks of a 16x16 tile that splat `s`'s contour can reach, as a mask whose bit
/// 4 br + bc is block (br, bc): the contour on every row at once (disc = 2 a level - dy^2 det >=
/// 0, its dx range [(-b dy - sq) / a, (-b dy + sq) / a], pixels [left, right]) on the rows of
/// `range`, the hull of the reached rows' ranges over each band of 4 rows in every lane of the
/// band (rows not reached: an empty range), against each block's columns: block (br, bc) is
/// reached when its band's hull meets [x0 + 4 bc + 0.5, x0 + 4 bc + 3.5] (`cols`, lane
/// 4 br + bc). `dy` holds my - (y0 + r + 0.5) per row r and `bdy` b dy. The forward and the
/// backward AVX-512 kernels both take their blocks from here, so they reach the same ones.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx2,fma")]
pub(crate) fn reached_blocks(
    s: &Splat,
    range: u16,
    dy: std::arch::x86_64::__m512,
    bdy: std::arch::x86_64::__m512,
    cols: (std::arch::x86_64::__m512, std::arch::x86_64::__m512),
) -> u16 {
    use std::arch::x86_64::*;
    let (v_bxl, v_bxh) = cols;
    let v_mx = _mm512_set1_ps(s.xy[0]);
    let dy2 = _mm512_mul_ps(dy, dy);
    let disc = _mm512_sub_ps(
        _mm512_set1_ps(s.two_a_level),
        _mm512_mul_ps(dy2, _mm512_set1_ps(s.conic_det)),
    );
    let ok = _mm512_mask_cmp_ps_mask::<_CMP_GE_OQ>(range, disc, _mm512_setzero_ps());
    let sq = _mm512_sqrt_ps(disc);
    let inv_a = _mm512_set1_ps(s.inv_a);
    let left = _mm512_sub_ps(v_mx, _mm512_mul_ps(_mm512_sub_ps(sq, bdy), inv_a));
    let right = _mm512_add_ps(v_mx, _mm512_mul_ps(_mm512_add_ps(sq, bdy), inv_a));
    let l = _mm512_mask_mov_ps(_mm512_set1_ps(f32::INFINITY), ok, left);
    let r = _mm512_mask_mov_ps(_mm512_set1_ps(f32::NEG_INFINITY), ok, right);
    let l = _mm512_min_ps(l, _mm512_permute_ps::<0b10_11_00_01>(l));
    let r = _mm512_max_ps(r, _mm512_permute_ps::<0b10_11_00_01>(r));
    let l = _mm512_min_ps(l, _mm512_permute_ps::<0b01_00_11_10>(l));
    let r = _mm512_max_ps(r, _mm512_permute_ps::<0b01_00_11_10>(r));
    let blocks = _mm512_cmp_ps_mask::<_CMP_LE_OQ>(l, v_bxh);
    _mm512_mask_cmp_ps_mask::<_CMP_GE_OQ>(blocks, r, v_bxl)
}

/// [`Stream::fill`]'s copy for the AVX-512 kernels: the first min(len) entries of `src`, at most
/// 32, to the front of `dst` by two masked moves (masked-off lanes are neither read nor
/// written), where a `copy_from_slice` of a variable length calls `memcpy`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx2,fma")]
pub(crate) fn copy_entries(src: &[u32], dst: &mut [u32]) {
    use std::arch::x86_64::*;
    let k = src.len().min(dst.len()).min(32);
    let m = (u32::MAX as u64 >> (32 - k)) as u32;
    // SAFETY: the masks cover the first k <= 32 entries of both slices only.
    unsafe {
        let lo = _mm512_maskz_loadu_epi32(m as u16, src.as_ptr() as *const i32);
        _mm512_mask_storeu_epi32(dst.as_mut_ptr() as *mut i32, m as u16, lo);
        if k > 16 {
            let hi = _mm512_maskz_loadu_epi32((m >> 16) as u16, src.as_ptr().add(16) as _);
            _mm512_mask_storeu_epi32(dst.as_mut_ptr().add(16) as _, (m >> 16) as u16, hi);
        }
    }
}

/// Explicit AVX-512 kernel: per pixel the same formulas and operation order as
/// `blend_tile_impl::<true>`, so the same image bits, organised for the CPU rather than per
/// splat. The work unit is a 4x4-pixel block (one 16-lane vector): a splat's footprint of about
/// 9 pixels costs about 4 blocks of a tile where it cost about 9 rows of 16 pixels, most of
/// whose lanes lay outside it. The tile's list is taken in batches of `BATCH` splats:
/// - phase 1, branch-free per splat: the contour's x-range on each of the 16 rows (the rows
///   test of the generic kernel), its hull over each 4-row band, and from it one mask of the
///   blocks whose pixel centres it can reach; and the per-row (b dy, 0.5 c dy^2) and per-column
///   (dx, 0.5 a dx^2) terms of its exponent, kept in `slots`;
/// - phase 2, two blocks at a time in lockstep: each block's transmittance, colour and depth
///   stay in registers while the batch's splats that reach the block are blended in list order,
///   with masked accumulations; the block's lanes take their row terms by a permute and their
///   column terms by a 4-lane broadcast, the same values the generic kernel uses. Lanes that
///   stop are dropped from the block's `live` mask; a block with none left takes no more splats.
///
/// A skipped block, like a skipped row of the generic kernel, has every pixel outside the
/// splat's 1/255 contour (alpha below the threshold), so blending it would change nothing; a
/// block's lanes outside the contour are masked by the alpha test as a row's are.
///
/// `out` is overwritten (its previous contents do not matter); `DEPTH` false skips the depth
/// sums and leaves `out.d` as it was.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512dq,avx512bw,avx2,fma")]
pub(super) fn blend_tile_avx512<'a, const COUNT: bool, const DEPTH: bool>(
    x0: u32,
    y0: u32,
    p: &BlendParams,
    splats: &[Splat],
    lists: impl Iterator<Item = &'a [u32]>,
    out: &mut TileOut,
) -> Counts {
    use std::arch::x86_64::*;

    // lanes outside the image start done: `live` holds each block's lanes that may still take
    // splats (the generic kernel marks done lanes with a negative T instead; both write |T|
    // out, so the images agree); `alive` the blocks with live lanes
    let mut live = [0u16; LANES];
    let mut alive: u16 = 0;
    let cols = p.width.saturating_sub(x0).min(LANES as u32) as usize;
    let rows = p.height.saturating_sub(y0).min(LANES as u32) as usize;
    for (b, lv) in live.iter_mut().enumerate() {
        for i in 0..LANES {
            let (r, c) = block_pixel(b, i);
            if r < rows && c < cols {
                *lv |= 1 << i;
            }
        }
        if *lv != 0 {
            alive |= 1 << b;
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
    // lane i of a block takes the row terms of its row 4 br + i / 4
    let quarter = _mm512_setr_epi32(0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3);
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
    // written by phase 1 before phase 2 reads them: no clearing of the batch each tile
    let mut slots = [const { MaybeUninit::<Slot>::uninit() }; BATCH];
    let mut st = Blocks {
        t: [[1.0; LANES]; LANES],
        c: [[[0.0; LANES]; LANES]; 3],
        d: [[0.0; LANES]; LANES],
    };
    // a block's state in registers: transmittance, colour and depth sums, live lanes, and
    // where its lanes find their row terms (permute indices) and column terms (offset)
    struct Blk {
        t: __m512,
        c0: __m512,
        c1: __m512,
        c2: __m512,
        d: __m512,
        lv: u16,
        idx: __m512i,
        col: usize,
    }
    macro_rules! load_blk {
        ($b:expr) => {{
            let b: usize = $b;
            // SAFETY: b < 16: each array of `st` holds 16 aligned rows of 16 floats.
            unsafe {
                Blk {
                    t: _mm512_load_ps(st.t[b].as_ptr()),
                    c0: _mm512_load_ps(st.c[0][b].as_ptr()),
                    c1: _mm512_load_ps(st.c[1][b].as_ptr()),
                    c2: _mm512_load_ps(st.c[2][b].as_ptr()),
                    d: if DEPTH {
                        _mm512_load_ps(st.d[b].as_ptr())
                    } else {
                        _mm512_setzero_ps()
                    },
                    lv: live[b],
                    idx: _mm512_add_epi32(quarter, _mm512_set1_epi32(4 * (b / 4) as i32)),
                    col: 4 * (b % 4),
                }
            }
        }};
    }
    macro_rules! store_blk {
        ($blk:ident, $b:expr) => {{
            let b: usize = $b;
            // SAFETY: as in `load_blk`
            unsafe {
                _mm512_store_ps(st.t[b].as_mut_ptr(), $blk.t);
                _mm512_store_ps(st.c[0][b].as_mut_ptr(), $blk.c0);
                _mm512_store_ps(st.c[1][b].as_mut_ptr(), $blk.c1);
                _mm512_store_ps(st.c[2][b].as_mut_ptr(), $blk.c2);
                if DEPTH {
                    _mm512_store_ps(st.d[b].as_mut_ptr(), $blk.d);
                }
            }
            live[b] = $blk.lv;
            if $blk.lv == 0 {
                alive &= !(1 << b);
            }
        }};
    }
    // blend batch splat k into a block
    macro_rules! step {
        ($blk:ident, $k:expr) => {{
            // SAFETY: $k is a splat of this batch (its mask bit is set), whose slot phase 1
            // wrote.
            let slot = unsafe { slots[$k].assume_init_ref() };
            let s = &slot.splat;
            // SAFETY: each array holds 16 aligned floats and col + 4 <= 16.
            let (dx, adx2, bdy, cdy2) = unsafe {
                (
                    _mm512_broadcast_f32x4(_mm_load_ps(slot.dx.as_ptr().add($blk.col))),
                    _mm512_broadcast_f32x4(_mm_load_ps(slot.adx2.as_ptr().add($blk.col))),
                    _mm512_permutexvar_ps($blk.idx, _mm512_load_ps(slot.bdy.as_ptr())),
                    _mm512_permutexvar_ps($blk.idx, _mm512_load_ps(slot.cdy2.as_ptr())),
                )
            };
            let sigma = _mm512_add_ps(_mm512_fmadd_ps(bdy, dx, adx2), cdy2);
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
            let valid = _mm512_mask_cmp_ps_mask::<_CMP_GE_OQ>($blk.lv, alpha, thr);
            if COUNT {
                useful += valid.count_ones() as u64;
            }
            let w = _mm512_mul_ps(alpha, $blk.t);
            let tn = _mm512_sub_ps($blk.t, w);
            let contrib = _mm512_mask_cmp_ps_mask::<_CMP_GT_OQ>(valid, tn, t_min);
            $blk.c0 = _mm512_mask3_fmadd_ps(w, _mm512_set1_ps(s.rgb[0]), $blk.c0, contrib);
            $blk.c1 = _mm512_mask3_fmadd_ps(w, _mm512_set1_ps(s.rgb[1]), $blk.c1, contrib);
            $blk.c2 = _mm512_mask3_fmadd_ps(w, _mm512_set1_ps(s.rgb[2]), $blk.c2, contrib);
            if DEPTH {
                $blk.d = _mm512_mask3_fmadd_ps(w, _mm512_set1_ps(s.depth), $blk.d, contrib);
            }
            $blk.t = _mm512_mask_mov_ps($blk.t, contrib, tn);
            // valid lanes that do not contribute stop
            $blk.lv = _kor_mask16(_kandn_mask16(valid, $blk.lv), contrib);
        }};
    }
    // the tile's lists as one stream of batches, the next batch's splats prefetched while
    // this one is blended (batches and prefetch run across the lists' ends)
    let mut stream = Stream::new(lists);
    let copy = |src: &[u32], dst: &mut [u32]| copy_entries(src, dst);
    let mut next = [0u32; BATCH];
    let mut n_next = stream.fill(&mut next, copy);
    for &gi in &next[..n_next] {
        prefetch(splats, gi as usize);
    }
    while n_next != 0 {
        let (batch, n) = (next, n_next);
        n_next = stream.fill(&mut next, copy);
        {
            // phase 1, branch-free per splat: which blocks of the tile it reaches, and the
            // per-row and per-column terms of its exponent
            let mut masks = [0u32; BATCH];
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
                let lo = _mm512_set1_ps(my - ey - 0.5 - y0f);
                let hi = _mm512_set1_ps(my + ey - 0.5 - y0f);
                let range = _mm512_cmp_ps_mask::<_CMP_GE_OQ>(lane_f, lo);
                let range = _mm512_mask_cmp_ps_mask::<_CMP_LE_OQ>(range, lane_f, hi);
                let v_mx = _mm512_set1_ps(mx);
                let dy = _mm512_sub_ps(_mm512_set1_ps(my), py);
                let bdy = _mm512_mul_ps(_mm512_set1_ps(cb), dy);
                let blocks = reached_blocks(s, range, dy, bdy, (v_bxl, v_bxh)) & alive;
                let cdy2 = _mm512_mul_ps(_mm512_mul_ps(_mm512_set1_ps(0.5 * cc), dy), dy);
                // per-column terms: dx and 0.5 a dx^2
                let dx = _mm512_sub_ps(v_mx, px);
                let adx2 = _mm512_mul_ps(_mm512_mul_ps(_mm512_set1_ps(0.5 * ca), dx), dx);
                let slot = slots[k].as_mut_ptr();
                masks[k] = blocks as u32;
                // SAFETY: `slot` points to slots[k], whose fields are all written here; each
                // array holds 16 aligned floats.
                unsafe {
                    addr_of_mut!((*slot).splat).write(*s);
                    _mm512_store_ps(addr_of_mut!((*slot).bdy) as *mut f32, bdy);
                    _mm512_store_ps(addr_of_mut!((*slot).cdy2) as *mut f32, cdy2);
                    _mm512_store_ps(addr_of_mut!((*slot).dx) as *mut f32, dx);
                    _mm512_store_ps(addr_of_mut!((*slot).adx2) as *mut f32, adx2);
                }
            }
            // phase 2, blocks two at a time: each block's transmittance, colour and depth stay
            // in registers while the batch's splats that reach it are blended in list order;
            // the two blocks are independent, so their dependency chains on T overlap
            // SAFETY: `masks` holds BATCH = 32 u32.
            let (m0, m1) = unsafe {
                (
                    _mm512_loadu_si512(masks.as_ptr() as *const _),
                    _mm512_loadu_si512(masks.as_ptr().add(16) as *const _),
                )
            };
            let mut todo = _mm512_reduce_or_epi32(_mm512_or_si512(m0, m1)) as u32;
            // the batch's splats that reach block b, as bits of their batch index
            macro_rules! blk_splats {
                ($b:expr) => {{
                    let bit = _mm512_set1_epi32(1 << $b);
                    _mm512_test_epi32_mask(m0, bit) as u32
                        | (_mm512_test_epi32_mask(m1, bit) as u32) << 16
                }};
            }
            let mut steps = 0u64;
            while todo != 0 {
                let ba = todo.trailing_zeros() as usize;
                todo &= todo - 1;
                let mut ksa = blk_splats!(ba);
                let mut a = load_blk!(ba);
                if todo != 0 {
                    let bb = todo.trailing_zeros() as usize;
                    todo &= todo - 1;
                    let mut ksb = blk_splats!(bb);
                    let mut b = load_blk!(bb);
                    // both blocks in lockstep while both have splats and live lanes
                    while ksa != 0 && ksb != 0 {
                        let ka = ksa.trailing_zeros() as usize;
                        ksa &= ksa - 1;
                        let kb = ksb.trailing_zeros() as usize;
                        ksb &= ksb - 1;
                        step!(a, ka);
                        step!(b, kb);
                        steps += 2;
                        // a block whose lanes all stopped takes no more splats
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
                        step!(b, k);
                        steps += 1;
                        if b.lv == 0 {
                            break;
                        }
                    }
                    store_blk!(b, bb);
                }
                while ksa != 0 {
                    let k = ksa.trailing_zeros() as usize;
                    ksa &= ksa - 1;
                    step!(a, k);
                    steps += 1;
                    if a.lv == 0 {
                        break;
                    }
                }
                store_blk!(a, ba);
            }
            // every step ran on a block with live lanes: 16 evaluations each
            evals += LANES as u64 * steps;
            if alive == 0 {
                st.write_rows::<DEPTH>(out);
                return Counts { evals, useful };
            }
        }
    }
    st.write_rows::<DEPTH>(out);
    Counts { evals, useful }
}
