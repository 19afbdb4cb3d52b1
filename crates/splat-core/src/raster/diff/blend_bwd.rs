//! Backward of the per-pixel blend, one 16x16 tile per work unit.
//!
//! The tile's list is replayed front to back with the forward's own arithmetic (same alpha,
//! same transmittance bits, same skip and stop decisions), so no per-pixel "last index" is
//! needed and no threshold can flip between the passes. For Gaussian i of a pixel with colour
//! gradient g (rgb and the depth channel), T_i the transmittance before it and
//! S_i = sum_{j <= i} (g . c_j) alpha_j T_j the running weighted colour:
//!
//!   dL/dalpha_i = (g . c_i) T_i - (Q - S_i) / (1 - alpha_i),
//!   Q = g . C_final + T_final (g . background - dL/dA),
//!
//! (gsplat's back-to-front `v_alpha` rewritten with the colour behind i as C_final - C_i).
//! Per (tile, Gaussian) the kernel sums over the tile's pixels in 16 lanes, the lanes of a 4x4
//! pixel block: lane (y % 4) * 4 + x % 4 adds its 16 pixels' terms in row-major pixel order
//! (band y / 4, then block column x / 4), every term per pixel (u dx, u dx^2, u dx dy as well as
//! u dy, u dy^2); then the 16 lanes are summed with a fixed halving tree into one [`slot`] of
//! the intersection. Every kernel (generic, AVX2, AVX-512) performs the same operations in the
//! same order: the generic one pixel by pixel in row-major order, AVX-512 one 4x4 block (16
//! lanes) at a time in block order, AVX2 the two 4x2 halves of each block (issue 21, fifth pass:
//! until then a lane was a tile column and the sums ran row by row).
use super::slots::slot;
use crate::raster::blend::{
    opacity_exp, prefetch, row_span, BlendParams, TileOut, LANES, PREFETCH_AHEAD, T_MIN,
};
use crate::raster::project::{Splat, ALPHA_THRESHOLD};
use crate::raster::Simd;

/// Per-pixel inputs of a tile's backward: the colour gradients g (r, g, b, depth channel) and
/// Q (see the module docs), in block order (`[b][i]`: lane i of 4x4 block b, see
/// [`block_lane`]); pixels outside the image hold zeros.
#[derive(Clone)]
#[repr(C, align(64))]
pub(crate) struct PixIn {
    pub g: [[[f32; LANES]; LANES]; 4],
    pub q: [[f32; LANES]; LANES],
}

impl Default for PixIn {
    fn default() -> Self {
        PixIn {
            g: [[[0.0; LANES]; LANES]; 4],
            q: [[0.0; LANES]; LANES],
        }
    }
}

/// Where a tile kernel puts the slot of list entry `pos` (a sorted-splat position). Kernels
/// call `put` or `zero` exactly once per entry of the tile's list, in list order.
pub(crate) trait SlotSink {
    fn put(&mut self, pos: u32, vals: &[f32; slot::LEN]);
    /// `put` with the values in lanes 0..12 of an AVX-512 vector (the AVX-512 kernel's sums),
    /// so a sink may store them without a trip through an array.
    ///
    /// # Safety
    /// The CPU has AVX-512F.
    #[cfg(target_arch = "x86_64")]
    #[inline]
    unsafe fn put_m512(&mut self, pos: u32, v: std::arch::x86_64::__m512) {
        let mut lanes = [0.0f32; 16];
        // SAFETY: `lanes` holds 16 floats; AVX-512F is present (the caller's contract).
        unsafe { std::arch::x86_64::_mm512_storeu_ps(lanes.as_mut_ptr(), v) };
        self.put(pos, &std::array::from_fn(|i| lanes[i]));
    }
    /// Entry `pos` has no slot to add: it comes after the tile finished. Its sums would be
    /// +0.0 zeros, which leave any running sum unchanged, so a sink may skip it; by default it
    /// puts them. (Splats none of whose rows passes the contour test still put their zero sums:
    /// skipping them was measured slower, a branch that mispredicts in the kernel and in the
    /// reduction.)
    #[inline]
    fn zero(&mut self, pos: u32) {
        self.put(pos, &[0.0; slot::LEN]);
    }
    /// Called for every (pixel, Gaussian) pair that contributes, in blend order, when
    /// `RECORD` is true (tests and the reference check): row r, lane l, sorted position, and
    /// whether alpha was clamped at max_alpha.
    const RECORD: bool = false;
    fn contrib(&mut self, _r: usize, _l: usize, _pos: u32, _clamped: bool) {}
}

/// Block and lane of tile pixel (row r, column l): blocks of 4x4 pixels numbered row by row
/// over the tile (b = 4 (r / 4) + l / 4), lanes row by row inside a block.
#[inline(always)]
pub(crate) const fn block_lane(r: usize, l: usize) -> (usize, usize) {
    (4 * (r / 4) + l / 4, 4 * (r % 4) + l % 4)
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

/// The canonical sum of 16 lanes: halving tree (i + 8, then i + 4, i + 2, i + 1), which the SIMD
/// kernels reproduce exactly.
#[inline(always)]
pub(crate) fn hsum16(v: &[f32; LANES]) -> f32 {
    let mut h = [0.0f32; 8];
    for i in 0..8 {
        h[i] = v[i] + v[i + 8];
    }
    let h4 = [h[0] + h[4], h[1] + h[5], h[2] + h[6], h[3] + h[7]];
    let h2 = [h4[0] + h4[2], h4[1] + h4[3]];
    h2[0] + h2[1]
}

/// The slot of one (tile, Gaussian) pair from its 12 per-lane accumulators, in slot order
/// ([c0..c3, V0, u dx, u dy, u dx^2, u dx dy, u dy^2, |x|, |y|]): each lane's 16-lane sum.
#[inline(always)]
pub(crate) fn finish_slot(acc: &[[f32; LANES]; slot::LEN]) -> [f32; slot::LEN] {
    acc.map(|a| hsum16(&a))
}

/// Replay one tile's list and emit the slot of every entry (`SlotSink::zero` for entries after
/// the tile finished). `t_final` is the forward's state (for the live pixels).
/// Returns the Gaussian-pixel evaluations (as the forward counts them).
#[inline(always)]
fn bwd_tile_impl<'a, const FMA: bool, const ABS: bool, const DEPTH: bool, S: SlotSink>(
    x0: u32,
    y0: u32,
    p: &BlendParams,
    splats: &[Splat],
    lists: impl Iterator<Item = &'a [u32]>,
    pix: &PixIn,
    sink: &mut S,
) -> u64 {
    let mut px = [0.0f32; LANES];
    for (l, v) in px.iter_mut().enumerate() {
        *v = (x0 + l as u32) as f32 + 0.5;
    }
    // the forward's state: T per pixel (negative = done; outside the image starts done) and
    // the backward's running weighted colour S
    let mut tt = [[1.0f32; LANES]; LANES];
    let mut ss = [[0.0f32; LANES]; LANES];
    let mut alive = [false; LANES];
    let mut alive_rows = 0;
    for r in 0..LANES {
        for l in 0..LANES {
            if x0 + l as u32 >= p.width || y0 + r as u32 >= p.height {
                tt[r][l] = -1.0;
            }
        }
        alive[r] = y0 + (r as u32) < p.height;
        alive_rows += alive[r] as usize;
    }
    // the inputs in row order, for the per-pixel loop over a row
    let mut rows = PixIn::default();
    for b in 0..LANES {
        for i in 0..LANES {
            let (r, l) = (4 * (b / 4) + i / 4, 4 * (b % 4) + i % 4);
            for c in 0..4 {
                rows.g[c][r][l] = pix.g[c][b][i];
            }
            rows.q[r][l] = pix.q[b][i];
        }
    }
    let max_alpha = p.max_alpha;
    let y0f = y0 as f32;
    let mut evals = 0u64;
    let mut done = alive_rows == 0;
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
            let (two_a_level, det, inv_a) = (s.two_a_level, s.conic_det, s.inv_a);
            let (lo, hi) = row_span(my, s.half_height, y0f);
            let (lo, hi) = (lo as usize, hi as usize);
            let half_a = 0.5 * ca;
            let ln_op = s.ln_opacity;
            let col = [s.rgb[0], s.rgb[1], s.rgb[2], s.depth];
            let (xl, xh) = (px[0], px[LANES - 1]);
            let mut dxs = [0.0f32; LANES];
            let mut adx2 = [0.0f32; LANES];
            let mut dx2 = [0.0f32; LANES];
            let mut adx = [0.0f32; LANES];
            let mut bdx = [0.0f32; LANES];
            for l in 0..LANES {
                dxs[l] = mx - px[l];
                adx2[l] = half_a * dxs[l] * dxs[l];
                dx2[l] = dxs[l] * dxs[l];
                adx[l] = ca * dxs[l];
                bdx[l] = cb * dxs[l];
            }
            // per lane of a 4x4 block, in slot order
            let mut acc = [[0.0f32; LANES]; slot::LEN];
            for r in lo..hi {
                if !alive[r] {
                    continue;
                }
                let dy = my - (y0f + r as f32 + 0.5);
                let bdy = cb * dy;
                let disc = two_a_level - dy * dy * det;
                if disc.is_nan() || disc < 0.0 {
                    continue;
                }
                let sq = disc.sqrt();
                if mx - (sq - bdy) * inv_a > xh || mx + (sq + bdy) * inv_a < xl {
                    continue;
                }
                evals += LANES as u64;
                let cdy2 = 0.5 * cc * dy * dy;
                let dy2 = dy * dy;
                let cdy = cc * dy;
                let (trow, srow) = (&mut tt[r], &mut ss[r]);
                let (g0, g1, g2, g3) = (&rows.g[0][r], &rows.g[1][r], &rows.g[2][r], &rows.g[3][r]);
                let qrow = &rows.q[r];
                // the row's per-pixel values, then their sums in block-lane order (below)
                let mut wts = [0.0f32; LANES];
                let mut us = [0.0f32; LANES];
                let mut cs = [false; LANES];
                let mut m2s = [false; LANES];
                for l in 0..LANES {
                    let sigma = fmadd::<FMA>(bdy, dxs[l], adx2[l]) + cdy2;
                    let e = opacity_exp::<FMA>(sigma, ln_op);
                    let alpha = select(e < max_alpha, e, max_alpha);
                    let t = trow[l];
                    let valid = (alpha >= ALPHA_THRESHOLD) & (t > 0.0);
                    let wt = alpha * t;
                    let tn = t - wt;
                    let contrib = valid & (tn > T_MIN);
                    // gradient of the pixel's loss through this Gaussian's alpha
                    let mut gc = g0[l] * col[0];
                    gc = fmadd::<FMA>(g1[l], col[1], gc);
                    gc = fmadd::<FMA>(g2[l], col[2], gc);
                    if DEPTH {
                        gc = fmadd::<FMA>(g3[l], col[3], gc);
                    }
                    let s_new = fmadd::<FMA>(gc, wt, srow[l]);
                    let ra = 1.0 / (1.0 - alpha);
                    let tq = (qrow[l] - s_new) * ra;
                    let va = fmadd::<FMA>(gc, t, -tq);
                    wts[l] = wt;
                    us[l] = e * va;
                    cs[l] = contrib;
                    m2s[l] = contrib & (e < max_alpha);
                    srow[l] = select(contrib, s_new, srow[l]);
                    trow[l] = select(contrib, tn, select(valid, -t, t));
                    if S::RECORD && contrib {
                        sink.contrib(r, l, gi, e >= max_alpha);
                    }
                }
                // lane rl + j of the block lanes takes columns j, 4 + j, 8 + j, 12 + j in turn
                let rl = 4 * (r % 4);
                for bc in 0..4 {
                    for j in 0..4 {
                        let (l, i) = (4 * bc + j, rl + j);
                        let (wt, u, contrib, m2) = (wts[l], us[l], cs[l], m2s[l]);
                        let a = &mut acc;
                        a[0][i] = select(contrib, fmadd::<FMA>(wt, g0[l], a[0][i]), a[0][i]);
                        a[1][i] = select(contrib, fmadd::<FMA>(wt, g1[l], a[1][i]), a[1][i]);
                        a[2][i] = select(contrib, fmadd::<FMA>(wt, g2[l], a[2][i]), a[2][i]);
                        if DEPTH {
                            a[3][i] = select(contrib, fmadd::<FMA>(wt, g3[l], a[3][i]), a[3][i]);
                        }
                        a[slot::V0][i] = select(m2, a[slot::V0][i] + u, a[slot::V0][i]);
                        let dx = dxs[l];
                        let dxdy = dx * dy;
                        for (k, term) in [
                            (slot::VDX, dx),
                            (slot::VDY, dy),
                            (slot::VDX2, dx2[l]),
                            (slot::VDXDY, dxdy),
                            (slot::VDY2, dy2),
                        ] {
                            a[k][i] = select(m2, fmadd::<FMA>(u, term, a[k][i]), a[k][i]);
                        }
                        if ABS {
                            let ax = (u * (adx[l] + bdy)).abs();
                            let ay = (u * (bdx[l] + cdy)).abs();
                            let (x, y) = (a[slot::ABSX][i], a[slot::ABSY][i]);
                            a[slot::ABSX][i] = select(m2, x + ax, x);
                            a[slot::ABSY][i] = select(m2, y + ay, y);
                        }
                    }
                }
                let mut all_done = u32::MAX;
                for &t in trow.iter() {
                    all_done &= t.to_bits();
                }
                if all_done >> 31 == 1 {
                    alive[r] = false;
                    alive_rows -= 1;
                    if alive_rows == 0 {
                        done = true;
                        break;
                    }
                }
            }
            sink.put(gi, &finish_slot(&acc));
        }
    }
    evals
}

/// The generic kernel compiled for AVX2 + FMA: the reference the explicit kernels are tested
/// against bit for bit.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
pub(crate) fn bwd_tile_generic_fma<'a, const ABS: bool, const DEPTH: bool, S: SlotSink>(
    x0: u32,
    y0: u32,
    p: &BlendParams,
    splats: &[Splat],
    lists: impl Iterator<Item = &'a [u32]>,
    pix: &PixIn,
    sink: &mut S,
) -> u64 {
    bwd_tile_impl::<true, ABS, DEPTH, _>(x0, y0, p, splats, lists, pix, sink)
}

fn bwd_tile_scalar<'a, const ABS: bool, const DEPTH: bool, S: SlotSink>(
    x0: u32,
    y0: u32,
    p: &BlendParams,
    splats: &[Splat],
    lists: impl Iterator<Item = &'a [u32]>,
    pix: &PixIn,
    sink: &mut S,
) -> u64 {
    bwd_tile_impl::<false, ABS, DEPTH, _>(x0, y0, p, splats, lists, pix, sink)
}

/// The backward kernel matching the forward kernel `p.simd` (so the replay gives the forward's
/// bits): AVX-512, AVX2 + FMA or plain; `absgrad` also sums |dL/dmean2d| per pixel.
///
/// `depth` false (no depth-image gradient: `pix.g[3]` must then be +0.0 in every lane, as
/// `tile_inputs` leaves it) runs the kernels without the depth channel's terms, with the same
/// slot bits: with g3 = +0.0 the channel's accumulator would stay +0.0 (+0.0 + w * 0), and
/// g . c only differs in the sign of a zero (-0.0 + +0.0 = +0.0), which the running colour S,
/// the accumulators and the slot sums all absorb, as none of them is ever -0.0 (each starts at
/// +0.0, and a rounded-to-nearest sum is -0.0 only when both terms are).
#[allow(clippy::too_many_arguments)]
pub(crate) fn bwd_tile<'a>(
    x0: u32,
    y0: u32,
    p: &BlendParams,
    splats: &[Splat],
    lists: impl Iterator<Item = &'a [u32]>,
    pix: &PixIn,
    sink: &mut impl SlotSink,
    absgrad: bool,
    depth: bool,
) -> u64 {
    macro_rules! run {
        ($abs:literal, $depth:literal) => {
            match p.simd {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: `Simd::resolve` only yields Avx512 when the CPU has these features.
                Simd::Avx512 => unsafe {
                    super::blend_bwd_avx512::bwd_tile_avx512::<$abs, $depth, _>(
                        x0, y0, p, splats, lists, pix, sink,
                    )
                },
                #[cfg(target_arch = "x86_64")]
                // SAFETY: `Simd::resolve` only yields Avx2 when the CPU has AVX2 and FMA.
                Simd::Avx2 => unsafe {
                    super::blend_bwd_avx2::bwd_tile_avx2::<$abs, $depth, _>(
                        x0, y0, p, splats, lists, pix, sink,
                    )
                },
                _ => bwd_tile_scalar::<$abs, $depth, _>(x0, y0, p, splats, lists, pix, sink),
            }
        };
    }
    match (absgrad, depth) {
        (true, true) => run!(true, true),
        (true, false) => run!(true, false),
        (false, true) => run!(false, true),
        (false, false) => run!(false, false),
    }
}

/// The generic kernel of the same rounding as `p.simd`'s (with FMA for the AVX kernels):
/// the same results as [`bwd_tile`], one pair at a time (it can record contributions).
pub(crate) fn bwd_tile_generic<'a>(
    x0: u32,
    y0: u32,
    p: &BlendParams,
    splats: &[Splat],
    lists: impl Iterator<Item = &'a [u32]>,
    pix: &PixIn,
    sink: &mut impl SlotSink,
) -> u64 {
    match p.simd {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `Simd::resolve` only yields Avx512 / Avx2 when the CPU has AVX2 and FMA.
        Simd::Avx512 | Simd::Avx2 => unsafe {
            bwd_tile_generic_fma::<true, true, _>(x0, y0, p, splats, lists, pix, sink)
        },
        _ => bwd_tile_scalar::<true, true, _>(x0, y0, p, splats, lists, pix, sink),
    }
}

/// Fill a tile's [`PixIn`] from the image gradients and the forward's saved tile state, and
/// return the tile's share of dL/d(background) (in float64, summed over its pixels in row-major
/// order; zeros without `want_bg`, which skips that serial sum).
///
/// `depth_grad` is dL/d(depth image); with `expected_depth` it refers to D / max(A, 1e-10)
/// and is turned into gradients of the accumulated depth D and of the alpha A here. Without
/// a depth gradient the saved depth sums are not read (the same bits as a zero gradient).
///
/// A row's 16 pixels are computed as lanes (the same operations, in the same order, as one
/// pixel at a time), by the build `simd` names.
#[allow(clippy::too_many_arguments)]
pub(crate) fn tile_inputs(
    x0: usize,
    y0: usize,
    width: usize,
    height: usize,
    saved: &TileOut,
    grads: &super::ImageGrads<'_>,
    background: [f32; 3],
    expected_depth: bool,
    want_bg: bool,
    simd: Simd,
    pix: &mut PixIn,
) -> [f64; 3] {
    let args = (x0, y0, width, height);
    let isa = crate::raster::footprint::Isa::of(simd);
    tile_inputs_isa(
        isa,
        args,
        saved,
        grads,
        (background, expected_depth, want_bg),
        pix,
    )
}

crate::raster::footprint::per_isa! {
    /// [`tile_inputs`] compiled for `isa`.
    fn tile_inputs_isa(
        args: (usize, usize, usize, usize),
        saved: &TileOut,
        grads: &super::ImageGrads<'_>,
        opts: ([f32; 3], bool, bool),
        pix: &mut PixIn,
    ) -> [f64; 3] => tile_inputs_impl
}

#[inline(always)]
fn tile_inputs_impl(
    (x0, y0, width, height): (usize, usize, usize, usize),
    saved: &TileOut,
    grads: &super::ImageGrads<'_>,
    (background, expected_depth, want_bg): ([f32; 3], bool, bool),
    pix: &mut PixIn,
) -> [f64; 3] {
    let cols = LANES.min(width - x0);
    let rows = LANES.min(height - y0);
    if cols < LANES || rows < LANES {
        // pixels outside the image keep zero inputs
        *pix = PixIn::default();
    }
    let mut v_bg = [0.0f64; 3];
    for r in 0..rows {
        let row = (y0 + r) * width + x0;
        let mut g = [[0.0f32; LANES]; 4];
        let mut ga = [0.0f32; LANES];
        let mut gd = [0.0f32; LANES];
        if let Some(v) = grads.rgb {
            for (l, p) in v[row * 3..(row + cols) * 3].chunks_exact(3).enumerate() {
                g[0][l] = p[0];
                g[1][l] = p[1];
                g[2][l] = p[2];
            }
        }
        if let Some(v) = grads.alpha {
            ga[..cols].copy_from_slice(&v[row..row + cols]);
        }
        if let Some(v) = grads.depth {
            gd[..cols].copy_from_slice(&v[row..row + cols]);
        }
        let st = &saved.t[r];
        let mut t = [0.0f32; LANES];
        for l in 0..LANES {
            t[l] = st[l].abs();
        }
        let Some(sd) = grads.depth.map(|_| &saved.d[r]) else {
            // no depth gradient: the depth sums are not read (a forward without depth leaves
            // them stale). With gd = +0 the depth terms below are +0 (g[3] = +0 / am, and
            // +0 (sd / am) / am subtracted from ga changes nothing: sd >= 0 is a sum of
            // w z, finite), and v + g[3] sd is v + (+0): adding +0.0 keeps its bits (it turns
            // -0 into +0 as that add did)
            let mut q = [0.0f32; LANES];
            for l in 0..LANES {
                let gbg =
                    g[0][l] * background[0] + g[1][l] * background[1] + g[2][l] * background[2];
                let mut v = t[l] * (gbg - ga[l]);
                v += g[0][l] * saved.c[0][r][l];
                v += g[1][l] * saved.c[1][r][l];
                v += g[2][l] * saved.c[2][r][l];
                v += 0.0;
                q[l] = v;
            }
            put_row(pix, r, cols, &g, &q);
            if want_bg {
                add_bg(&mut v_bg, &g, &t, cols);
            }
            continue;
        };
        if expected_depth {
            // depth = D / max(A, 1e-10)
            for l in 0..LANES {
                let a = 1.0 - t[l];
                let am = a.max(1e-10);
                g[3][l] = gd[l] / am;
                let less = ga[l] - gd[l] * (sd[l] / am) / am;
                ga[l] = if a > 1e-10 { less } else { ga[l] };
            }
        } else {
            g[3] = gd;
        }
        let mut q = [0.0f32; LANES];
        for l in 0..LANES {
            let gbg = g[0][l] * background[0] + g[1][l] * background[1] + g[2][l] * background[2];
            let mut v = t[l] * (gbg - ga[l]);
            v += g[0][l] * saved.c[0][r][l];
            v += g[1][l] * saved.c[1][r][l];
            v += g[2][l] * saved.c[2][r][l];
            v += g[3][l] * sd[l];
            q[l] = v;
        }
        put_row(pix, r, cols, &g, &q);
        if want_bg {
            add_bg(&mut v_bg, &g, &t, cols);
        }
    }
    v_bg
}

/// Store tile row `r`'s inputs into `pix`'s block order: lanes (r, 4k..4k + 4) are lanes
/// 4 (r % 4).. of block 4 (r / 4) + k (`block_lane`).
#[inline(always)]
fn put_row(pix: &mut PixIn, r: usize, cols: usize, g: &[[f32; LANES]; 4], q: &[f32; LANES]) {
    let j = 4 * (r % 4);
    for k in 0..cols.div_ceil(4) {
        let (b, n) = (4 * (r / 4) + k, (cols - 4 * k).min(4));
        for c in 0..4 {
            pix.g[c][b][j..j + n].copy_from_slice(&g[c][4 * k..4 * k + n]);
        }
        pix.q[b][j..j + n].copy_from_slice(&q[4 * k..4 * k + n]);
    }
}

/// Add row's share of dL/d(background): sum of g_c T over its pixels.
#[inline(always)]
fn add_bg(v_bg: &mut [f64; 3], g: &[[f32; LANES]; 4], t: &[f32; LANES], cols: usize) {
    for l in 0..cols {
        for c in 0..3 {
            v_bg[c] += g[c][l] as f64 * t[l] as f64;
        }
    }
}
