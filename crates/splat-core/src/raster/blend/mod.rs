//! Per-pixel front-to-back alpha blending (SPEC §4 step 7), one 16x16 tile per work unit.
//!
//! A tile keeps its 256 pixels' state in fixed-size arrays, one row of 16 pixels per SIMD lane
//! group; for each splat of the tile's list only the rows its box reaches are evaluated. The
//! lane loop is branch-free (selects) and uses a polynomial `exp` built with `mul_add`, so LLVM
//! vectorises it; it is compiled three times (AVX-512, AVX2+FMA, plain) and picked at run time.
//!
//! A pixel that stopped (transmittance would fall to 1e-4 or below) keeps its transmittance
//! negated: `T < 0` means done, `|T|` is the final transmittance.
use super::project::{Splat, ALPHA_THRESHOLD};
use super::sort::TILE;
use super::Simd;

mod frame;
#[cfg(test)]
mod tests;

pub use frame::FrozenFrame;
pub(crate) use frame::{blend_frame, blend_frame_saving};

pub(super) const LANES: usize = TILE as usize;
pub(super) const T_MIN: f32 = 1e-4;

/// Output of one tile: transmittance, colour and depth sums per pixel (the depth sums are
/// left as they were by a blend without depth, [`DepthOut::Skip`]).
#[derive(Clone)]
#[repr(C, align(64))]
pub(crate) struct TileOut {
    pub(super) t: [[f32; LANES]; LANES],
    pub(super) c: [[[f32; LANES]; LANES]; 3],
    pub(super) d: [[f32; LANES]; LANES],
}

impl Default for TileOut {
    fn default() -> Self {
        TileOut {
            t: [[1.0; LANES]; LANES],
            c: [[[0.0; LANES]; LANES]; 3],
            d: [[0.0; LANES]; LANES],
        }
    }
}

/// What a tile's blend did: Gaussian-pixel evaluations (the lanes of each work unit evaluated:
/// 16 per row for the plain kernel, 8 per half row for AVX2, 16 per 4x4 block for AVX-512) and,
/// of those, the useful ones: alpha >= 1/255 on a pixel that had not stopped yet, the only ones
/// that can change (or stop) a pixel, the same for every kernel. Their ratio is the blend's
/// efficiency.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct Counts {
    pub evals: u64,
    pub useful: u64,
}

impl std::ops::Add for Counts {
    type Output = Counts;
    fn add(self, o: Counts) -> Counts {
        Counts {
            evals: self.evals + o.evals,
            useful: self.useful + o.useful,
        }
    }
}

impl std::iter::Sum for Counts {
    fn sum<I: Iterator<Item = Counts>>(it: I) -> Counts {
        it.fold(Counts::default(), |a, b| a + b)
    }
}

/// Blend parameters shared by every tile of a frame.
#[derive(Debug, Clone, Copy)]
pub(crate) struct BlendParams {
    pub width: u32,
    pub height: u32,
    pub max_alpha: f32,
    pub background: [f32; 3],
    pub simd: Simd,
    /// Count the useful evaluations ([`Counts::useful`]; 0 when false).
    pub count_useful: bool,
}

impl BlendParams {
    /// A frame of `cam` rendered with `opts`: its size, and the options' alpha cap,
    /// background, kernel level and useful-evaluation count.
    pub(crate) fn of(cam: &crate::camera::Camera, opts: &super::RenderOptions) -> Self {
        BlendParams {
            width: cam.width,
            height: cam.height,
            max_alpha: opts.max_alpha,
            background: opts.background,
            simd: opts.simd.resolve(),
            count_useful: opts.count_useful,
        }
    }
}

#[inline(always)]
fn fmadd<const FMA: bool>(a: f32, b: f32, c: f32) -> f32 {
    if FMA {
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}

#[inline(always)]
fn select(m: bool, a: f32, b: f32) -> f32 {
    if m {
        a
    } else {
        b
    }
}

/// 2^(j/16) for j = 0..15, correctly rounded to float32 (bit patterns).
pub(super) const EXP2_16THS: [u32; 16] = [
    0x3F80_0000,
    0x3F85_AAC3,
    0x3F8B_95C2,
    0x3F91_C3D3,
    0x3F98_37F0,
    0x3F9E_F532,
    0x3FA5_FED7,
    0x3FAD_583F,
    0x3FB5_04F3,
    0x3FBD_08A4,
    0x3FC5_672A,
    0x3FCE_248C,
    0x3FD7_44FD,
    0x3FE0_CCDF,
    0x3FEA_C0C7,
    0x3FF5_257D,
];
/// sigma is clamped to this (also negative and NaN sigma, whose bit patterns compare larger):
/// alpha = opacity e^-80 is far below 1/255, so such a lane never contributes.
pub(super) const SIGMA_CLAMP: f32 = 80.0;
/// 1.5 * 2^23: adding it rounds to an integer k, left in the low bits.
pub(super) const EXP_MAGIC: f32 = 12_582_912.0;
/// 16 / ln 2.
pub(super) const EXP_K16: f32 = 16.0 * std::f32::consts::LOG2_E;
/// ln 2 / 16 split in two (Cody-Waite): the high part has 9 significant bits, so k C_HI is exact.
pub(super) const EXP_C_HI: f32 = 0.693_359_4 / 16.0; // 0.693359375 exactly
pub(super) const EXP_C_LO: f32 = -2.121_944_4e-4 / 16.0;

/// Which depth a frame's blend writes (and so whether its kernels sum depth at all).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum DepthOut {
    /// D / max(1 - T, 1e-10): the expected camera z.
    Expected,
    /// D = sum of w_i z_i.
    Accumulated,
    /// No depth: the kernels skip the depth sums (leaving [`TileOut::d`] as it was) and the
    /// depth image is not written (the fit's forward, which has no depth loss). The colour
    /// and transmittance bits are those of a blend with depth.
    Skip,
}

/// Unclamped alpha = exp(ln_op - sigma) = opacity e^-sigma (relative error about 1.5e-7), the
/// same formula as the explicit SIMD kernels (which are checked to give the same bits).
///
/// With u = sigma - ln_op (0 <= u < 86, as opacities below 1/255 are culled), k = round(16 u /
/// ln 2) and r = u - k ln2/16 (|r| <= ln2/32): e^-u = 2^(-k/16) e^-r, where 2^(-k/16) is a table
/// entry times a power of two put straight into the exponent bits and e^-r a cubic.
/// Negative (or NaN) sigma, which the reference skips, is clamped to 80 like a large one, so it
/// gives an alpha below the threshold instead of needing its own test.
#[inline(always)]
pub(super) fn opacity_exp<const FMA: bool>(sigma: f32, ln_op: f32) -> f32 {
    opacity_exp_clamped::<FMA>(sigma, ln_op, SIGMA_CLAMP)
}

/// The plain forward kernel's sigma clamp: alpha = opacity e^-sigma >= e^-(64 + 5.55) = 6e-31
/// (opacities below 1/255 are culled), so alpha T (|T| >= 1e-4 in every lane) stays a normal
/// float. With the clamp at 80 alpha falls to about 4e-38 far from a footprint and alpha T is
/// then often subnormal, a microcode assist per multiply: 15% of this kernel's frame CPU on a
/// trained scene (docs/rendering.md, issue 21's fifth pass: subnormals). Same bits: at
/// sigma >= 64 alpha is below 1/255 with either clamp, and such a lane changes nothing. The
/// explicit kernels keep 80: their blocks and half rows stay near the footprint, and they
/// measured no subnormal cost.
const FWD_SIGMA_CLAMP: f32 = 64.0;

/// [`opacity_exp`] with sigma clamped to `clamp` (at most [`SIGMA_CLAMP`]).
#[inline(always)]
fn opacity_exp_clamped<const FMA: bool>(sigma: f32, ln_op: f32, clamp: f32) -> f32 {
    let sigma = if sigma.to_bits() < clamp.to_bits() {
        sigma
    } else {
        clamp
    };
    let u = sigma - ln_op;
    let t = fmadd::<FMA>(-u, EXP_K16, EXP_MAGIC);
    let k = t - EXP_MAGIC;
    let r = fmadd::<FMA>(k, EXP_C_HI, u);
    let r = fmadd::<FMA>(k, EXP_C_LO, r);
    let mut y = fmadd::<FMA>(r, -1.0 / 6.0, 0.5);
    y = fmadd::<FMA>(y, r, -1.0);
    y = fmadd::<FMA>(y, r, 1.0);
    // t's low bits hold k (k <= 0): table index k mod 16, power of two floor(k / 16)
    let bits = t.to_bits();
    let scale = f32::from_bits(EXP2_16THS[(bits & 15) as usize].wrapping_add((bits >> 4) << 23));
    y * scale
}

/// Tile rows `lo..hi` (each in 0..=16) that a splat's 1/255 contour can reach, from its
/// centre row `my` and half-height `ey`, for the tile whose top pixel row is `y0f`.
#[inline(always)]
pub(super) fn row_span(my: f32, ey: f32, y0f: f32) -> (u32, u32) {
    let lo = (my - ey - 0.5 - y0f).ceil().clamp(0.0, 16.0) as u32;
    let hi = (my + ey - 0.5 - y0f).floor().clamp(-1.0, 15.0) as i32 + 1;
    (lo, hi.max(0) as u32)
}

/// The same rows as a bit mask (bit r: row r).
#[inline(always)]
pub(super) fn row_mask(my: f32, ey: f32, y0f: f32) -> u32 {
    let (lo, hi) = row_span(my, ey, y0f);
    ((1u32 << hi) - 1) & !((1u32 << lo) - 1)
}

/// Splats per phase-1 batch of the explicit SIMD kernels.
#[cfg(target_arch = "x86_64")]
pub(super) const CHUNK: usize = 16;

/// Phase-1 results for one splat of a batch of the explicit SIMD kernels.
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy, Default)]
#[repr(C, align(64))]
pub(super) struct Slot {
    /// b dy and 0.5 c dy^2 per row
    pub bdy: [f32; LANES],
    pub cdy2: [f32; LANES],
    /// dx and 0.5 a dx^2 per lane
    pub dx: [f32; LANES],
    pub adx2: [f32; LANES],
    pub splat: Splat,
}

/// How many list entries ahead the plain kernels and the AVX2 backward kernel prefetch splats
/// (the lists jump through the sorted array; 16 measured 1.8% less frame CPU than 8 on garden,
/// 1 thread). The explicit forward kernels and the AVX-512 backward kernel prefetch their whole
/// next batch instead, across the lists' ends ([`Stream`]).
pub(super) const PREFETCH_AHEAD: usize = 16;

/// A tile's lists (one per binning chunk, in order) as one stream of list entries, taken in
/// batches that run across the lists' ends: a frame with many binning chunks (grid-5: 40) gives
/// each tile many short lists, and batching or prefetching per list left the explicit kernels
/// partial batches and no splat prefetched at all (the prefetch ran ahead inside a list only).
/// The entries come in the same order, so the blend is the same.
#[cfg(target_arch = "x86_64")]
pub(super) struct Stream<'a, I: Iterator<Item = &'a [u32]>> {
    lists: I,
    rest: &'a [u32],
}

#[cfg(target_arch = "x86_64")]
impl<'a, I: Iterator<Item = &'a [u32]>> Stream<'a, I> {
    pub(super) fn new(lists: I) -> Self {
        Stream { lists, rest: &[] }
    }

    /// Copy the next (up to) N entries into `buf`, each run of them by `copy(src, dst)` (equal
    /// lengths, at most N: the kernels copy with masked vector moves, where `copy_from_slice`
    /// of a variable length calls `memcpy`, a few percent of grid-5's blend); returns how many
    /// (fewer than N only at the stream's end).
    #[inline(always)]
    pub(super) fn fill<const N: usize>(
        &mut self,
        buf: &mut [u32; N],
        copy: impl Fn(&[u32], &mut [u32]),
    ) -> usize {
        let mut n = 0;
        while n < N {
            if self.rest.is_empty() {
                match self.lists.next() {
                    Some(l) => self.rest = l,
                    None => break,
                }
                continue;
            }
            let k = (N - n).min(self.rest.len());
            copy(&self.rest[..k], &mut buf[n..n + k]);
            self.rest = &self.rest[k..];
            n += k;
        }
        n
    }
}

/// Hint the CPU to load splat `i` (both cache lines it may span) into L1.
#[inline(always)]
pub(super) fn prefetch(splats: &[Splat], i: usize) {
    if let Some(s) = splats.get(i) {
        crate::mem::prefetch_ends(s);
    }
}

/// Blend one tile's list into `out` (which starts as `TileOut::default()`); returns the
/// Gaussian-pixel evaluations (16 per row evaluated) and the useful ones among them.
/// `DEPTH` false skips the depth sums (`out.d` is left as it was).
#[inline(always)]
fn blend_tile_impl<'a, const FMA: bool, const COUNT: bool, const DEPTH: bool>(
    x0: u32,
    y0: u32,
    p: &BlendParams,
    splats: &[Splat],
    lists: impl Iterator<Item = &'a [u32]>,
    out: &mut TileOut,
) -> Counts {
    out.t = [[1.0; LANES]; LANES];
    out.c = [[[0.0; LANES]; LANES]; 3];
    if DEPTH {
        out.d = [[0.0; LANES]; LANES];
    }
    let mut px = [0.0f32; LANES];
    for (l, v) in px.iter_mut().enumerate() {
        *v = (x0 + l as u32) as f32 + 0.5;
    }
    // lanes and rows outside the image start done
    let mut alive = [false; LANES];
    let mut alive_rows = 0;
    for r in 0..LANES {
        for l in 0..LANES {
            if x0 + l as u32 >= p.width || y0 + r as u32 >= p.height {
                out.t[r][l] = -1.0;
            }
        }
        alive[r] = y0 + (r as u32) < p.height;
        alive_rows += alive[r] as usize;
    }
    let max_alpha = p.max_alpha;
    let y0f = y0 as f32;
    let mut evals = 0u64;
    let mut useful = 0u64;
    for list in lists {
        for (k, &gi) in list.iter().enumerate() {
            if let Some(&ahead) = list.get(k + PREFETCH_AHEAD) {
                prefetch(splats, ahead as usize);
            }
            let s = &splats[gi as usize];
            let (mx, my) = (s.xy[0], s.xy[1]);
            let [ca, cb, cc] = s.conic;
            // Rows beyond the 1/255 contour's half-height, and rows where the contour misses
            // the tile's columns, are skipped: there every lane's alpha is below 1/255.
            let (two_a_level, det, inv_a) = (s.two_a_level, s.conic_det, s.inv_a);
            let ey = s.half_height;
            let (lo, hi) = row_span(my, ey, y0f);
            let (lo, hi) = (lo as usize, hi as usize);
            let half_a = 0.5 * ca;
            let ln_op = s.ln_opacity;
            let [cr, cg, cbl] = s.rgb;
            let z = s.depth;
            let (xl, xh) = (px[0], px[LANES - 1]);
            // per-lane terms shared by every row: dx and 0.5 a dx^2
            let mut dxs = [0.0f32; LANES];
            let mut adx2 = [0.0f32; LANES];
            for l in 0..LANES {
                dxs[l] = mx - px[l];
                adx2[l] = half_a * dxs[l] * dxs[l];
            }
            for r in lo..hi {
                if !alive[r] {
                    continue;
                }
                let dy = my - (y0f + r as f32 + 0.5);
                let bdy = cb * dy;
                // contour's dx range on this row: (-b dy +- sqrt(disc)) / a
                let disc = two_a_level - dy * dy * det;
                if disc.is_nan() || disc < 0.0 {
                    continue;
                }
                let sq = disc.sqrt();
                // pixels x = mx - dx; skip when [mx - dx_hi, mx - dx_lo] misses [xl, xh]
                if mx - (sq - bdy) * inv_a > xh || mx + (sq + bdy) * inv_a < xl {
                    continue;
                }
                evals += LANES as u64;
                let cdy2 = 0.5 * cc * dy * dy;
                let trow = &mut out.t[r];
                for l in 0..LANES {
                    // sigma = 0.5 a dx^2 + b dx dy + 0.5 c dy^2
                    let sigma = fmadd::<FMA>(bdy, dxs[l], adx2[l]) + cdy2;
                    // sigma clamped at 64, not 80 (same bits, see FWD_SIGMA_CLAMP)
                    let e = opacity_exp_clamped::<FMA>(sigma, ln_op, FWD_SIGMA_CLAMP);
                    let alpha = select(e < max_alpha, e, max_alpha);
                    let t = trow[l];
                    let valid = (alpha >= ALPHA_THRESHOLD) & (t > 0.0);
                    if COUNT {
                        useful += valid as u64;
                    }
                    let wt = alpha * t;
                    let tn = t - wt;
                    let contrib = valid & (tn > T_MIN);
                    let w = select(contrib, wt, 0.0);
                    out.c[0][r][l] = fmadd::<FMA>(w, cr, out.c[0][r][l]);
                    out.c[1][r][l] = fmadd::<FMA>(w, cg, out.c[1][r][l]);
                    out.c[2][r][l] = fmadd::<FMA>(w, cbl, out.c[2][r][l]);
                    if DEPTH {
                        out.d[r][l] = fmadd::<FMA>(w, z, out.d[r][l]);
                    }
                    let tt = select(contrib, tn, select(valid, -t, t));
                    trow[l] = tt;
                }
                // a row is done when every lane's T is negative (sign bit set)
                let mut all_done = u32::MAX;
                for &t in trow.iter() {
                    all_done &= t.to_bits();
                }
                if all_done >> 31 == 1 {
                    alive[r] = false;
                    alive_rows -= 1;
                    if alive_rows == 0 {
                        return Counts { evals, useful };
                    }
                }
            }
        }
    }
    Counts { evals, useful }
}

/// The generic kernel compiled for AVX2 + FMA: the reference the explicit kernels are tested
/// against bit for bit.
#[cfg(all(test, target_arch = "x86_64"))]
#[target_feature(enable = "avx2,fma")]
pub(super) fn blend_tile_generic_fma<'a>(
    x0: u32,
    y0: u32,
    p: &BlendParams,
    splats: &[Splat],
    lists: impl Iterator<Item = &'a [u32]>,
    out: &mut TileOut,
) -> Counts {
    blend_tile_impl::<true, true, true>(x0, y0, p, splats, lists, out)
}

fn blend_tile_scalar<'a, const COUNT: bool, const DEPTH: bool>(
    x0: u32,
    y0: u32,
    p: &BlendParams,
    splats: &[Splat],
    lists: impl Iterator<Item = &'a [u32]>,
    out: &mut TileOut,
) -> Counts {
    blend_tile_impl::<false, COUNT, DEPTH>(x0, y0, p, splats, lists, out)
}

/// Blend one tile's list into `out`, whose previous contents do not matter: every kernel
/// starts from T = 1 and zero sums itself (the depth sums only when `depth`; without it they
/// are left as they were).
pub(crate) fn blend_tile<'a>(
    x0: u32,
    y0: u32,
    p: &BlendParams,
    splats: &[Splat],
    lists: impl Iterator<Item = &'a [u32]>,
    out: &mut TileOut,
    depth: bool,
) -> Counts {
    match (p.count_useful, depth) {
        (true, true) => blend_tile_counting::<true, true>(x0, y0, p, splats, lists, out),
        (true, false) => blend_tile_counting::<true, false>(x0, y0, p, splats, lists, out),
        (false, true) => blend_tile_counting::<false, true>(x0, y0, p, splats, lists, out),
        (false, false) => blend_tile_counting::<false, false>(x0, y0, p, splats, lists, out),
    }
}

/// [`blend_tile`] with the useful evaluations counted (`COUNT`) or not (0): counting costs the
/// AVX-512 kernel about 15% of its time, so only benchmarks ask for it. `DEPTH` false skips
/// the depth sums.
#[inline(always)]
fn blend_tile_counting<'a, const COUNT: bool, const DEPTH: bool>(
    x0: u32,
    y0: u32,
    p: &BlendParams,
    splats: &[Splat],
    lists: impl Iterator<Item = &'a [u32]>,
    out: &mut TileOut,
) -> Counts {
    match p.simd {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `Simd::resolve` only yields Avx512 when the CPU reports these features.
        Simd::Avx512 => unsafe {
            super::blend_avx512::blend_tile_avx512::<COUNT, DEPTH>(x0, y0, p, splats, lists, out)
        },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `Simd::resolve` only yields Avx2 when the CPU reports AVX2 and FMA.
        Simd::Avx2 => unsafe {
            super::blend_avx2::blend_tile_avx2::<COUNT, DEPTH>(x0, y0, p, splats, lists, out)
        },
        _ => blend_tile_scalar::<COUNT, DEPTH>(x0, y0, p, splats, lists, out),
    }
}

/// What an explicit kernel whose work unit is a block of `W` x `H` pixels must count, from a
/// plain per-pixel model: the generic kernel's per-pixel blend (`blend_tile_impl::<true>`'s
/// arithmetic, its per-row contour test) with the blocks laid over the tile. A block takes a
/// step (W H evaluations) for a splat when the hull of the splat's contour ranges over the
/// block's rows meets the block's columns and the block still has a pixel that has not
/// stopped; useful evaluations as the generic kernel. The AVX-512 kernel's unit is 4 x 4, the
/// AVX2 kernel's 8 x 1.
#[cfg(test)]
pub(super) fn unit_model<'a, const W: usize, const H: usize>(
    x0: u32,
    y0: u32,
    p: &BlendParams,
    splats: &[Splat],
    lists: impl Iterator<Item = &'a [u32]>,
) -> Counts {
    let mut t = [[1.0f32; LANES]; LANES];
    let mut live = [[false; LANES]; LANES];
    for (r, row) in live.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = x0 + (c as u32) < p.width && y0 + (r as u32) < p.height;
        }
    }
    let y0f = y0 as f32;
    let px: Vec<f32> = (0..LANES).map(|c| (x0 + c as u32) as f32 + 0.5).collect();
    let mut n = Counts::default();
    for &gi in lists.flatten() {
        let s = &splats[gi as usize];
        let (mx, my) = (s.xy[0], s.xy[1]);
        let [ca, cb, cc] = s.conic;
        let (lo, hi) = row_span(my, s.half_height, y0f);
        // each reached row's contour range [left, right] (empty: +inf, -inf)
        let mut range = [(f32::INFINITY, f32::NEG_INFINITY); LANES];
        for r in lo as usize..hi as usize {
            let dy = my - (y0f + r as f32 + 0.5);
            let bdy = cb * dy;
            let disc = s.two_a_level - dy * dy * s.conic_det;
            if disc >= 0.0 {
                let sq = disc.sqrt();
                range[r] = (mx - (sq - bdy) * s.inv_a, mx + (sq + bdy) * s.inv_a);
            }
        }
        for r0 in (0..LANES).step_by(H) {
            let band = &range[r0..r0 + H];
            let l = band.iter().map(|v| v.0).fold(f32::INFINITY, f32::min);
            let r = band.iter().map(|v| v.1).fold(f32::NEG_INFINITY, f32::max);
            for c0 in (0..LANES).step_by(W) {
                let any_live = live[r0..r0 + H]
                    .iter()
                    .any(|row| row[c0..c0 + W].contains(&true));
                if any_live && l <= px[c0 + W - 1] && r >= px[c0] {
                    n.evals += (W * H) as u64;
                }
            }
        }
        // the per-pixel blend of the generic kernel, on the rows its own test keeps
        for (r, &(left, right)) in range.iter().enumerate() {
            if left > px[LANES - 1] || right < px[0] {
                continue;
            }
            let dy = my - (y0f + r as f32 + 0.5);
            let (bdy, cdy2) = (cb * dy, 0.5 * cc * dy * dy);
            for (c, &x) in px.iter().enumerate() {
                if !live[r][c] {
                    continue;
                }
                let dx = mx - x;
                let sigma = bdy.mul_add(dx, 0.5 * ca * dx * dx) + cdy2;
                let alpha = opacity_exp::<true>(sigma, s.ln_opacity).min(p.max_alpha);
                if alpha >= ALPHA_THRESHOLD {
                    n.useful += 1;
                    let tn = t[r][c] - alpha * t[r][c];
                    if tn > T_MIN {
                        t[r][c] = tn;
                    } else {
                        live[r][c] = false;
                    }
                }
            }
        }
        if !live.iter().flatten().any(|&v| v) {
            break;
        }
    }
    n
}
