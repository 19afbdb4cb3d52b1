//! SSIM and its gradient, INRIA 3DGS's variant (`utils/loss_utils.py::ssim`): an 11x11 Gaussian
//! window of sigma 1.5 (normalised to sum 1), C1 = 0.01^2, C2 = 0.03^2, each channel on its own,
//! and **'same' zero padding**: the local statistics are taken with `conv2d(padding=5)`, so every
//! pixel has an SSIM value and the score is the mean over H x W x 3. (gsplat's trainer uses
//! fused-ssim with 'valid' padding, the mean over the (H-10) x (W-10) interior; see docs/fit.md.)
//!
//! The window is separable, so each local mean is a horizontal then a vertical 11-tap pass. With
//! mu_x = G*x, e_xx = G*(x^2), e_xy = G*(xy) and S the SSIM map, the gradient of sum_p g S(p)
//! with respect to the prediction x is
//!
//! ```text
//! dL/dx = G*(g dS/dmu_x) + 2 x G*(g dS/de_xx) + y G*(g dS/de_xy)
//! dS/dmu_x = S (2 mu_y / A1 - 2 mu_y / A2 - 2 mu_x / B1 + 2 mu_x / B2)
//! dS/de_xx = -S / B2,   dS/de_xy = 2 S / A2
//! ```
//!
//! (A1 = 2 mu_x mu_y + C1, A2 = 2 s_xy + C2, B1 = mu_x^2 + mu_y^2 + C1, B2 = s_xx + s_yy + C2;
//! the zero-padded blur is its own adjoint because the window is symmetric).
//!
//! With inv = 1 / (B1 B2) the map and the partials take one division per value instead of
//! seven: S = A1 A2 inv, S / A1 = A2 inv, S / A2 = A1 inv, S / B1 = S B2 inv, S / B2 = S B1 inv,
//! so dS/dmu_x = 2 inv (mu_y (A2 - A1) - mu_x S (B2 - B1)), dS/de_xx = -S B1 inv and
//! dS/de_xy = 2 A1 inv.
//!
//! Three passes, each parallel over image rows (all three channels of a row in one task): (1)
//! split the channels and blur x, y, x^2, y^2, xy horizontally; (2) blur them vertically, form
//! S and the three partials, and blur the partials horizontally (row-local, so in the same
//! task); (3) blur those vertically and combine into the gradient. Every value is computed in a
//! fixed order with plain IEEE multiplies, adds and divisions (no FMA contraction, no
//! approximate reciprocals), so the AVX-512, AVX2 and plain builds of the row kernels, and any
//! thread count, give the same bits. The mean is summed per channel row into 16 float64 lane
//! accumulators (value i into lane i % 16, lanes combined pairwise in a fixed order), the same
//! arithmetic in every kernel, and the rows are added in order.
use rayon::prelude::*;

use crate::raster::Simd;

/// Window radius (11 taps).
pub const RADIUS: usize = 5;
const TAPS: usize = 2 * RADIUS + 1;
pub const SIGMA: f64 = 1.5;
pub const C1: f32 = 0.01 * 0.01;
pub const C2: f32 = 0.03 * 0.03;

/// Lanes of the map's row sums.
pub(crate) const LANES: usize = 16;

/// The normalised 1D Gaussian window (INRIA `gaussian(11, 1.5)`).
pub fn window() -> [f32; TAPS] {
    let mut w = [0.0f64; TAPS];
    for (i, v) in w.iter_mut().enumerate() {
        let d = i as f64 - RADIUS as f64;
        *v = (-(d * d) / (2.0 * SIGMA * SIGMA)).exp();
    }
    let s: f64 = w.iter().sum();
    w.map(|v| (v / s) as f32)
}

/// Scratch planes of the SSIM passes, reused. Layout "row-planar": image row y holds its three
/// channel rows one after another, value (y, c, x) at (3 y + c) W + x, so every pass splits its
/// outputs into disjoint per-row blocks.
#[derive(Default)]
pub struct SsimWorkspace {
    /// The prediction and the target, split into channel rows.
    x: Vec<f32>,
    y: Vec<f32>,
    /// Horizontal blurs of x, y, x^2, y^2, xy (pass 1).
    h: [Vec<f32>; 5],
    /// Horizontal blurs of the partials g dS/dmu_x, g dS/de_xx, g dS/de_xy (pass 2).
    hp: [Vec<f32>; 3],
    row_sums: Vec<f64>,
    /// Which row kernels run (all give the same bits).
    pub simd: Simd,
}

/// `out[i] = sum_t k[t] src[i + t]`, summed in tap order in a register per output value.
#[inline(always)]
fn taps(src: &[f32], out: &mut [f32], k: &[f32; TAPS]) {
    for (i, o) in out.iter_mut().enumerate() {
        let p = &src[i..i + TAPS];
        let mut s = 0.0f32;
        for t in 0..TAPS {
            s += k[t] * p[t];
        }
        *o = s;
    }
}

/// Zero-padded 11-tap blur of one row: `out[i] = sum_t k[t] src[i + t - 5]`, summed in tap
/// order in a register per output value. The interior reads the row in place; only the edges
/// go through a zero-padded copy (`pad`, at least W + 10 values), with the same sums.
#[inline(always)]
fn hblur(src: &[f32], pad: &mut [f32], out: &mut [f32], k: &[f32; TAPS]) {
    let w = src.len();
    if w < 2 * RADIUS {
        pad[..RADIUS].fill(0.0);
        pad[RADIUS..RADIUS + w].copy_from_slice(src);
        pad[RADIUS + w..RADIUS + w + RADIUS].fill(0.0);
        taps(&pad[..w + 2 * RADIUS], &mut out[..w], k);
        return;
    }
    taps(src, &mut out[RADIUS..w - RADIUS], k);
    let e = &mut pad[..3 * RADIUS];
    e[..RADIUS].fill(0.0);
    e[RADIUS..].copy_from_slice(&src[..2 * RADIUS]);
    taps(e, &mut out[..RADIUS], k);
    e[..2 * RADIUS].copy_from_slice(&src[w - 2 * RADIUS..]);
    e[2 * RADIUS..].fill(0.0);
    taps(e, &mut out[w - RADIUS..w], k);
}

/// Vertical 11-tap blur of channel `c` at image row `y` of a row-planar buffer (rows outside
/// the image are zeros), summed in tap order in a register per output value.
#[inline(always)]
fn vblur(
    plane: &[f32],
    w: usize,
    h: usize,
    c: usize,
    y: usize,
    zeros: &[f32],
    out: &mut [f32],
    k: &[f32; TAPS],
) {
    let rows: [&[f32]; TAPS] = std::array::from_fn(|t| {
        let yy = y as isize + t as isize - RADIUS as isize;
        if yy < 0 || yy >= h as isize {
            &zeros[..w]
        } else {
            let at = (yy as usize * 3 + c) * w;
            &plane[at..at + w]
        }
    });
    for (i, o) in out[..w].iter_mut().enumerate() {
        let mut s = 0.0f32;
        for t in 0..TAPS {
            s += k[t] * rows[t][i];
        }
        *o = s;
    }
}

/// Row buffers of one task, reused across the rows it runs.
struct Scratch {
    pad: Vec<f32>,
    tmp: Vec<f32>,
    v: [Vec<f32>; 5],
    p: [Vec<f32>; 3],
    zeros: Vec<f32>,
}

impl Scratch {
    fn new(w: usize) -> Self {
        Scratch {
            pad: vec![0.0; w + 2 * RADIUS],
            tmp: vec![0.0; w],
            v: std::array::from_fn(|_| vec![0.0; w]),
            p: std::array::from_fn(|_| vec![0.0; w]),
            zeros: vec![0.0; w],
        }
    }
}

/// Sum of a row in float64: value i into lane i % 16, then the lanes pairwise (8 + 8, 4 + 4,
/// 2 + 2, 1 + 1). Every kernel does these adds in this order, so the bits are the kernels'.
#[inline(always)]
pub(crate) fn lane_sum(v: &[f32]) -> f64 {
    let mut acc = [0.0f64; LANES];
    let mut chunks = v.chunks_exact(LANES);
    for c in &mut chunks {
        for j in 0..LANES {
            acc[j] += c[j] as f64;
        }
    }
    for (a, &x) in acc.iter_mut().zip(chunks.remainder()) {
        *a += x as f64;
    }
    fold_lanes(acc)
}

/// The lanes of a lane sum added pairwise in a fixed order.
#[inline(always)]
pub(crate) fn fold_lanes(mut acc: [f64; LANES]) -> f64 {
    let mut n = LANES;
    while n > 1 {
        n /= 2;
        for j in 0..n {
            acc[j] += acc[j + n];
        }
    }
    acc[0]
}

/// Pass 1 for one image row: split the channels (clamping the prediction when asked) and blur
/// x, y, x^2, y^2, xy horizontally. Slices are the row's blocks (3W values).
#[inline(always)]
fn pass1_row(
    pred: &[f32],
    target: &[f32],
    clamp: bool,
    xr: &mut [f32],
    yr: &mut [f32],
    h: [&mut [f32]; 5],
    k: &[f32; TAPS],
    sc: &mut Scratch,
) {
    let w = pred.len() / 3;
    let (pad, tmp) = (&mut sc.pad, &mut sc.tmp[..w]);
    let [h0, h1, h2, h3, h4] = h;
    for c in 0..3 {
        let r = c * w..(c + 1) * w;
        let (xs, ys) = (&mut xr[r.clone()], &mut yr[r.clone()]);
        for i in 0..w {
            xs[i] = pred[i * 3 + c];
            ys[i] = target[i * 3 + c];
        }
        if clamp {
            for v in xs.iter_mut() {
                *v = v.clamp(0.0, 1.0);
            }
        }
        hblur(xs, pad, &mut h0[r.clone()], k);
        hblur(ys, pad, &mut h1[r.clone()], k);
        for i in 0..w {
            tmp[i] = xs[i] * xs[i];
        }
        hblur(tmp, pad, &mut h2[r.clone()], k);
        for i in 0..w {
            tmp[i] = ys[i] * ys[i];
        }
        hblur(tmp, pad, &mut h3[r.clone()], k);
        for i in 0..w {
            tmp[i] = xs[i] * ys[i];
        }
        hblur(tmp, pad, &mut h4[r], k);
    }
}

/// Pass 2 for image row `y`: vertical blurs, the SSIM map (returns its row sum) and, with `gs`,
/// the partials times gs, blurred horizontally into the row's blocks `hp`.
#[inline(always)]
fn pass2_row(
    h: [&[f32]; 5],
    wh: (usize, usize),
    y: usize,
    gs: Option<f32>,
    hp: [&mut [f32]; 3],
    k: &[f32; TAPS],
    sc: &mut Scratch,
) -> f64 {
    let (w, hh) = wh;
    let [ha, hb, hc] = hp;
    let Scratch {
        pad,
        tmp,
        v,
        p,
        zeros,
    } = sc;
    let [pa, pb, pc] = p;
    let (pa, pb, pc) = (&mut pa[..w], &mut pb[..w], &mut pc[..w]);
    let srow = &mut tmp[..w];
    let mut sum = 0.0f64;
    for c in 0..3 {
        for (m, out) in v.iter_mut().enumerate() {
            vblur(h[m], w, hh, c, y, zeros, out, k);
        }
        let [v0, v1, v2, v3, v4] = &*v;
        let (v0, v1, v2, v3, v4) = (&v0[..w], &v1[..w], &v2[..w], &v3[..w], &v4[..w]);
        match gs {
            Some(g) => {
                for i in 0..w {
                    let (ux, uy) = (v0[i], v1[i]);
                    let sxx = v2[i] - ux * ux;
                    let syy = v3[i] - uy * uy;
                    let sxy = v4[i] - ux * uy;
                    let a1 = 2.0 * ux * uy + C1;
                    let a2 = 2.0 * sxy + C2;
                    let b1 = ux * ux + uy * uy + C1;
                    let b2 = sxx + syy + C2;
                    let inv = 1.0 / (b1 * b2);
                    let s = a1 * a2 * inv;
                    srow[i] = s;
                    let gi = g * inv;
                    pa[i] = 2.0 * gi * (uy * (a2 - a1) - ux * s * (b2 - b1));
                    pb[i] = -(gi * s * b1);
                    pc[i] = 2.0 * gi * a1;
                }
                let r = c * w..(c + 1) * w;
                hblur(pa, pad, &mut ha[r.clone()], k);
                hblur(pb, pad, &mut hb[r.clone()], k);
                hblur(pc, pad, &mut hc[r], k);
            }
            None => {
                for i in 0..w {
                    let (ux, uy) = (v0[i], v1[i]);
                    let a1 = 2.0 * ux * uy + C1;
                    let a2 = 2.0 * (v4[i] - ux * uy) + C2;
                    let b1 = ux * ux + uy * uy + C1;
                    let b2 = (v2[i] - ux * ux) + (v3[i] - uy * uy) + C2;
                    srow[i] = (a1 * a2) / (b1 * b2);
                }
            }
        }
        sum += lane_sum(srow);
    }
    sum
}

/// Pass 3 for image row `y`: vertical blurs of the blurred partials, combined with the row's x
/// and y blocks into the gradient row (interleaved RGB).
#[inline(always)]
fn pass3_row(
    hp: [&[f32]; 3],
    x: &[f32],
    yv: &[f32],
    wh: (usize, usize),
    y: usize,
    out: &mut [f32],
    k: &[f32; TAPS],
    sc: &mut Scratch,
) {
    let (w, hh) = wh;
    let (v, rows, zeros) = (&mut sc.v, &mut sc.p, &sc.zeros);
    for (c, r) in rows.iter_mut().enumerate() {
        for (m, o) in v[..3].iter_mut().enumerate() {
            vblur(hp[m], w, hh, c, y, zeros, o, k);
        }
        let (v0, v1, v2) = (&v[0][..w], &v[1][..w], &v[2][..w]);
        let (xc, yc) = (&x[c * w..(c + 1) * w], &yv[c * w..(c + 1) * w]);
        for i in 0..w {
            r[i] = v0[i] + 2.0 * xc[i] * v1[i] + yc[i] * v2[i];
        }
    }
    let [r0, r1, r2] = &*rows;
    for (i, o) in out[..3 * w].chunks_exact_mut(3).enumerate() {
        o[0] = r0[i];
        o[1] = r1[i];
        o[2] = r2[i];
    }
}

/// One row of the L1 term: adds `gl1` sign(p - t) (0 where equal, like torch) to the gradient
/// and returns the row's sums of |p - t| and (p - t)^2 in float64, each in 16 lanes (value i
/// into lane i % 16) added pairwise in a fixed order, like the map's.
#[inline(always)]
fn l1_row(g: &mut [f32], p: &[f32], t: &[f32], gl1: f32) -> (f64, f64) {
    let (mut l1, mut se) = ([0.0f64; LANES], [0.0f64; LANES]);
    let n = g.len().min(p.len()).min(t.len());
    let full = n / LANES * LANES;
    for ((g, p), t) in g[..full]
        .chunks_exact_mut(LANES)
        .zip(p[..full].chunks_exact(LANES))
        .zip(t[..full].chunks_exact(LANES))
    {
        for j in 0..LANES {
            let d = p[j] - t[j];
            l1[j] += d.abs() as f64;
            se[j] += (d * d) as f64;
            let s = ((d > 0.0) as i32 - (d < 0.0) as i32) as f32;
            g[j] += gl1 * s;
        }
    }
    for j in 0..n - full {
        let d = p[full + j] - t[full + j];
        l1[j] += d.abs() as f64;
        se[j] += (d * d) as f64;
        let s = ((d > 0.0) as i32 - (d < 0.0) as i32) as f32;
        g[full + j] += gl1 * s;
    }
    (fold_lanes(l1), fold_lanes(se))
}

/// The row kernels compiled for one instruction set (the same source, so the same bits).
macro_rules! kernels {
    ($name:ident $(, $feat:literal)?) => {
        mod $name {
            use super::*;
            $(#[target_feature(enable = $feat)])?
            pub(super) unsafe fn pass1(pred: &[f32], target: &[f32], clamp: bool, xr: &mut [f32], yr: &mut [f32], h: [&mut [f32]; 5], k: &[f32; TAPS], sc: &mut Scratch) {
                pass1_row(pred, target, clamp, xr, yr, h, k, sc)
            }
            $(#[target_feature(enable = $feat)])?
            pub(super) unsafe fn pass2(h: [&[f32]; 5], wh: (usize, usize), y: usize, gs: Option<f32>, hp: [&mut [f32]; 3], k: &[f32; TAPS], sc: &mut Scratch) -> f64 {
                pass2_row(h, wh, y, gs, hp, k, sc)
            }
            $(#[target_feature(enable = $feat)])?
            pub(super) unsafe fn l1(g: &mut [f32], p: &[f32], t: &[f32], gl1: f32) -> (f64, f64) {
                l1_row(g, p, t, gl1)
            }
            $(#[target_feature(enable = $feat)])?
            pub(super) unsafe fn pass3(hp: [&[f32]; 3], x: &[f32], yv: &[f32], wh: (usize, usize), y: usize, out: &mut [f32], k: &[f32; TAPS], sc: &mut Scratch) {
                pass3_row(hp, x, yv, wh, y, out, k, sc)
            }
        }
    };
}

kernels!(plain);
#[cfg(target_arch = "x86_64")]
kernels!(avx2, "avx2,fma");
#[cfg(target_arch = "x86_64")]
kernels!(avx512, "avx512f,avx512vl,avx512dq,avx512bw,avx2,fma");

/// Call kernel `$f` of the resolved level.
macro_rules! dispatch {
    ($level:expr, $f:ident($($a:expr),*)) => {
        // SAFETY: a kernel runs only when the CPU has its features (`Simd::resolve` checked).
        unsafe {
            match $level {
                #[cfg(target_arch = "x86_64")]
                Simd::Avx512 => avx512::$f($($a),*),
                #[cfg(target_arch = "x86_64")]
                Simd::Avx2 => avx2::$f($($a),*),
                _ => plain::$f($($a),*),
            }
        }
    };
}

/// The L1 term over whole rows (`row` values each, in parallel): adds `gl1` sign(p - t) to
/// `g` and returns the sums of |p - t| and (p - t)^2 in float64, rows added in order.
pub(crate) fn l1_term(
    simd: Simd,
    g: &mut [f32],
    p: &[f32],
    t: &[f32],
    row: usize,
    gl1: f32,
    sums: &mut Vec<(f64, f64)>,
) -> (f64, f64) {
    let level = simd.resolve();
    g.par_chunks_mut(row.max(1))
        .zip(p.par_chunks(row.max(1)))
        .zip(t.par_chunks(row.max(1)))
        .with_min_len(4)
        .map(|((g, p), t)| dispatch!(level, l1(g, p, t, gl1)))
        .collect_into_vec(sums);
    sums.iter().fold((0.0, 0.0), |a, r| (a.0 + r.0, a.1 + r.1))
}

impl SsimWorkspace {
    /// Mean SSIM of `pred` against `target` (both H*W*3 interleaved RGB). With `grad`, also
    /// write `scale` times dSSIM_mean/d(pred) into it (H*W*3). `clamp` clamps the prediction to
    /// [0, 1] first (evaluation); the gradient is only defined without it.
    pub fn ssim(
        &mut self,
        pred: &[f32],
        target: &[f32],
        width: usize,
        height: usize,
        clamp: bool,
        grad: Option<(&mut [f32], f32)>,
    ) -> f64 {
        let (w, h) = (width, height);
        let n = w * h;
        debug_assert_eq!(pred.len(), n * 3);
        debug_assert_eq!(target.len(), n * 3);
        if n == 0 {
            return 1.0;
        }
        let k = window();
        let level = self.simd.resolve();
        let row = 3 * w;
        let scratch = || Scratch::new(w);
        for v in [&mut self.x, &mut self.y]
            .into_iter()
            .chain(self.h.iter_mut())
            .chain(self.hp.iter_mut())
        {
            v.resize(3 * n, 0.0);
        }
        // pass 1
        {
            let [h0, h1, h2, h3, h4] = &mut self.h;
            (
                pred.par_chunks(row),
                target.par_chunks(row),
                self.x.par_chunks_mut(row),
                self.y.par_chunks_mut(row),
                h0.par_chunks_mut(row),
                h1.par_chunks_mut(row),
                h2.par_chunks_mut(row),
                h3.par_chunks_mut(row),
                h4.par_chunks_mut(row),
            )
                .into_par_iter()
                .with_min_len(4)
                .for_each_init(scratch, |sc, (p, t, xr, yr, a, b, c, d, e)| {
                    dispatch!(level, pass1(p, t, clamp, xr, yr, [a, b, c, d, e], &k, sc))
                });
        }
        // pass 2 (the partials' planes are written only with a gradient)
        let g = 1.0 / (3.0 * n as f64);
        let gs = grad.as_ref().map(|(_, s)| (g * *s as f64) as f32);
        {
            let hv = [
                &self.h[0][..],
                &self.h[1][..],
                &self.h[2][..],
                &self.h[3][..],
                &self.h[4][..],
            ];
            let [p0, p1, p2] = &mut self.hp;
            (
                p0.par_chunks_mut(row),
                p1.par_chunks_mut(row),
                p2.par_chunks_mut(row),
            )
                .into_par_iter()
                .enumerate()
                .with_min_len(4)
                .map_init(scratch, |sc, (y, (a, b, c))| {
                    dispatch!(level, pass2(hv, (w, h), y, gs, [a, b, c], &k, sc))
                })
                .collect_into_vec(&mut self.row_sums);
        }
        let total: f64 = self.row_sums.iter().sum();
        if let Some((out, _)) = grad {
            // pass 3
            let hv = [&self.hp[0][..], &self.hp[1][..], &self.hp[2][..]];
            (
                out.par_chunks_mut(row),
                self.x.par_chunks(row),
                self.y.par_chunks(row),
            )
                .into_par_iter()
                .enumerate()
                .with_min_len(4)
                .for_each_init(scratch, |sc, (y, (o, xr, yr))| {
                    dispatch!(level, pass3(hv, xr, yr, (w, h), y, o, &k, sc))
                });
        }
        total / (3 * n) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(w: usize, h: usize, seed: u64) -> Vec<f32> {
        let mut s = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        (0..w * h * 3)
            .map(|i| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                let smooth = ((i / 3 % w) as f32 * 0.15).sin() * 0.3 + 0.5;
                smooth + ((s >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 0.2
            })
            .collect()
    }

    #[test]
    fn identical_images_score_one_and_window_sums_to_one() {
        let k = window();
        assert!((k.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        let a = image(23, 17, 1);
        let mut ws = SsimWorkspace::default();
        let s = ws.ssim(&a, &a, 23, 17, false, None);
        assert!((s - 1.0).abs() < 1e-6, "{s}");
        let b = image(23, 17, 2);
        assert!(ws.ssim(&a, &b, 23, 17, false, None) < 0.9);
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let (w, h) = (19, 13);
        let x = image(w, h, 3);
        let y = image(w, h, 4);
        let mut ws = SsimWorkspace::default();
        let mut g = vec![0.0f32; w * h * 3];
        ws.ssim(&x, &y, w, h, false, Some((&mut g, 1.0)));
        // probe pixels at the border and inside
        for &i in &[0usize, 5, 3 * w + 1, 3 * (6 * w + 9) + 2, w * h * 3 - 1] {
            let eps = 1e-2f32;
            let mut xp = x.clone();
            xp[i] += eps;
            let mut xm = x.clone();
            xm[i] -= eps;
            let fd = (ws.ssim(&xp, &y, w, h, false, None) - ws.ssim(&xm, &y, w, h, false, None))
                / (2.0 * eps as f64);
            let tol = 2e-3 * fd.abs().max(1e-4) + 1e-6;
            assert!(
                (fd - g[i] as f64).abs() < tol.max(2e-6),
                "value {i}: finite difference {fd}, analytic {}",
                g[i]
            );
        }
    }

    #[test]
    fn same_bits_for_any_thread_count_and_kernel() {
        let (w, h) = (67, 45);
        let x = image(w, h, 5);
        let y = image(w, h, 6);
        let run = |t: usize, simd: Simd| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(t)
                .build()
                .expect("pool")
                .install(|| {
                    let mut ws = SsimWorkspace {
                        simd,
                        ..SsimWorkspace::default()
                    };
                    let mut g = vec![0.0f32; w * h * 3];
                    let s = ws.ssim(&x, &y, w, h, false, Some((&mut g, 1.0)));
                    (
                        s.to_bits(),
                        g.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    )
                })
        };
        let base = run(1, Simd::Scalar);
        assert_eq!(base, run(3, Simd::Auto));
        assert_eq!(base, run(2, Simd::Avx2));
    }

    #[test]
    fn row_blur_in_place_matches_the_padded_copy_at_every_width() {
        let k = window();
        for w in 1..40 {
            let src: Vec<f32> = image(w, 1, w as u64)
                .iter()
                .step_by(3)
                .map(|v| v - 0.5)
                .collect();
            let mut padded = vec![0.0f32; w + 2 * RADIUS];
            padded[RADIUS..RADIUS + w].copy_from_slice(&src);
            let mut want = vec![0.0f32; w];
            taps(&padded, &mut want, &k);
            let mut got = vec![0.0f32; w];
            hblur(&src, &mut vec![1.0f32; w + 2 * RADIUS], &mut got, &k);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&got), bits(&want), "width {w}");
        }
    }

    #[test]
    fn l1_term_has_the_same_bits_for_any_thread_count_and_kernel() {
        // 37 values a row: two full lanes of 16 and a remainder of 5
        let (p, t) = (image(37, 9, 7), image(37, 9, 8));
        let mut p = p;
        p[4] = t[4]; // a zero difference: zero sign
        let run = |threads: usize, simd: Simd| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("pool")
                .install(|| {
                    let mut g = vec![0.5f32; p.len()];
                    let (l1, se) = l1_term(simd, &mut g, &p, &t, 37, 0.25, &mut Vec::new());
                    let gb: Vec<u32> = g.iter().map(|v| v.to_bits()).collect();
                    (l1.to_bits(), se.to_bits(), gb)
                })
        };
        let base = run(1, Simd::Scalar);
        assert_eq!(base, run(3, Simd::Auto));
        assert_eq!(base, run(2, Simd::Avx2));
        let (l1, se, g) = base;
        let want_l1: f64 = p.iter().zip(&t).map(|(a, b)| (a - b).abs() as f64).sum();
        let want_se: f64 = p
            .iter()
            .zip(&t)
            .map(|(a, b)| ((a - b) * (a - b)) as f64)
            .sum();
        assert!((f64::from_bits(l1) - want_l1).abs() < 1e-12 * want_l1.max(1.0));
        assert!((f64::from_bits(se) - want_se).abs() < 1e-12 * want_se.max(1.0));
        for (i, &gb) in g.iter().enumerate() {
            let d = p[i] - t[i];
            let want = 0.5
                + if d > 0.0 {
                    0.25
                } else if d < 0.0 {
                    -0.25
                } else {
                    0.0
                };
            assert_eq!(f32::from_bits(gb), want, "value {i}");
        }
    }
}
