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
//! Four passes, each parallel over image rows (all three channels of a row in one task): (1)
//! split the channels and blur x, y, x^2, y^2, xy horizontally; (2) blur them vertically, form
//! S and the three partials; (3) blur the partials horizontally; (4) blur them vertically and
//! combine into the gradient. Every value is computed in a fixed order with plain multiplies
//! and adds (no FMA contraction), so the AVX-512, AVX2 and plain builds of the row kernels, and
//! any thread count, give the same bits; the mean is summed per row in f64, rows in order.
use rayon::prelude::*;

use crate::raster::Simd;

/// Window radius (11 taps).
pub const RADIUS: usize = 5;
const TAPS: usize = 2 * RADIUS + 1;
pub const SIGMA: f64 = 1.5;
pub const C1: f32 = 0.01 * 0.01;
pub const C2: f32 = 0.03 * 0.03;

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
    /// Horizontal blurs of x, y, x^2, y^2, xy (pass 1), then of the partials (pass 3).
    h: [Vec<f32>; 5],
    /// The partials g dS/dmu_x, g dS/de_xx, g dS/de_xy (pass 2).
    p: [Vec<f32>; 3],
    row_sums: Vec<f64>,
    /// Which row kernels run (all give the same bits).
    pub simd: Simd,
}

/// Zero-padded 11-tap blur of one row: `out[i] = sum_t k[t] src[i + t - 5]`, summed in tap
/// order in a register per output value.
#[inline(always)]
fn hblur(src: &[f32], pad: &mut [f32], out: &mut [f32], k: &[f32; TAPS]) {
    let w = src.len();
    pad[..RADIUS].fill(0.0);
    pad[RADIUS..RADIUS + w].copy_from_slice(src);
    pad[RADIUS + w..RADIUS + w + RADIUS].fill(0.0);
    let pad = &pad[..w + 2 * RADIUS];
    for (i, o) in out[..w].iter_mut().enumerate() {
        let p = &pad[i..i + TAPS];
        let mut s = 0.0f32;
        for t in 0..TAPS {
            s += k[t] * p[t];
        }
        *o = s;
    }
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
) {
    let w = pred.len() / 3;
    let mut pad = vec![0.0f32; w + 2 * RADIUS];
    let mut tmp = vec![0.0f32; w];
    let [h0, h1, h2, h3, h4] = h;
    for c in 0..3 {
        let r = c * w..(c + 1) * w;
        let (xs, ys) = (&mut xr[r.clone()], &mut yr[r.clone()]);
        for i in 0..w {
            let v = pred[i * 3 + c];
            xs[i] = if clamp { v.clamp(0.0, 1.0) } else { v };
            ys[i] = target[i * 3 + c];
        }
        hblur(xs, &mut pad, &mut h0[r.clone()], k);
        hblur(ys, &mut pad, &mut h1[r.clone()], k);
        for i in 0..w {
            tmp[i] = xs[i] * xs[i];
        }
        hblur(&tmp, &mut pad, &mut h2[r.clone()], k);
        for i in 0..w {
            tmp[i] = ys[i] * ys[i];
        }
        hblur(&tmp, &mut pad, &mut h3[r.clone()], k);
        for i in 0..w {
            tmp[i] = xs[i] * ys[i];
        }
        hblur(&tmp, &mut pad, &mut h4[r], k);
    }
}

/// Pass 2 for image row `y`: vertical blurs, the SSIM map (returns its row sum) and, with `gs`,
/// the partials times gs into the row's blocks `p`.
#[inline(always)]
fn pass2_row(
    h: [&[f32]; 5],
    wh: (usize, usize),
    y: usize,
    gs: Option<f32>,
    p: [&mut [f32]; 3],
    k: &[f32; TAPS],
) -> f64 {
    let (w, hh) = wh;
    let mut v = [
        vec![0.0f32; w],
        vec![0.0f32; w],
        vec![0.0f32; w],
        vec![0.0f32; w],
        vec![0.0f32; w],
    ];
    let [pa, pb, pc] = p;
    let mut srow = vec![0.0f32; w];
    let zeros = vec![0.0f32; w];
    let mut sum = 0.0f64;
    for c in 0..3 {
        for (m, out) in v.iter_mut().enumerate() {
            vblur(h[m], w, hh, c, y, &zeros, out, k);
        }
        let [v0, v1, v2, v3, v4] = &v;
        let (v0, v1, v2, v3, v4) = (&v0[..w], &v1[..w], &v2[..w], &v3[..w], &v4[..w]);
        let (pa, pb, pc) = (
            &mut pa[c * w..(c + 1) * w],
            &mut pb[c * w..(c + 1) * w],
            &mut pc[c * w..(c + 1) * w],
        );
        let srow = &mut srow[..w];
        // the map into a row buffer (vectorised), the f64 row sum after it (in order)
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
                    let s = (a1 * a2) / (b1 * b2);
                    srow[i] = s;
                    let d_mu = s * (2.0 * uy / a1 - 2.0 * uy / a2 - 2.0 * ux / b1 + 2.0 * ux / b2);
                    pa[i] = g * d_mu;
                    pb[i] = g * (-s / b2);
                    pc[i] = g * (2.0 * s / a2);
                }
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
        let mut row = 0.0f64;
        for &s in srow.iter() {
            row += s as f64;
        }
        sum += row;
    }
    sum
}

/// Pass 3 for one image row: horizontal blurs of the partials (row blocks in, row blocks out).
#[inline(always)]
fn pass3_row(p: [&[f32]; 3], h: [&mut [f32]; 3], k: &[f32; TAPS]) {
    let w = p[0].len() / 3;
    let mut pad = vec![0.0f32; w + 2 * RADIUS];
    for (src, dst) in p.into_iter().zip(h) {
        for c in 0..3 {
            hblur(
                &src[c * w..(c + 1) * w],
                &mut pad,
                &mut dst[c * w..(c + 1) * w],
                k,
            );
        }
    }
}

/// Pass 4 for image row `y`: vertical blurs of the blurred partials, combined with the row's x
/// and y blocks into the gradient row (interleaved RGB).
#[inline(always)]
fn pass4_row(
    h: [&[f32]; 3],
    x: &[f32],
    yv: &[f32],
    wh: (usize, usize),
    y: usize,
    out: &mut [f32],
    k: &[f32; TAPS],
) {
    let (w, hh) = wh;
    let mut v = [vec![0.0f32; w], vec![0.0f32; w], vec![0.0f32; w]];
    let zeros = vec![0.0f32; w];
    for c in 0..3 {
        for (m, o) in v.iter_mut().enumerate() {
            vblur(h[m], w, hh, c, y, &zeros, o, k);
        }
        for i in 0..w {
            out[i * 3 + c] = v[0][i] + 2.0 * x[c * w + i] * v[1][i] + yv[c * w + i] * v[2][i];
        }
    }
}

/// The row kernels compiled for one instruction set (the same source, so the same bits).
macro_rules! kernels {
    ($name:ident $(, $feat:literal)?) => {
        mod $name {
            use super::*;
            $(#[target_feature(enable = $feat)])?
            pub(super) unsafe fn pass1(pred: &[f32], target: &[f32], clamp: bool, xr: &mut [f32], yr: &mut [f32], h: [&mut [f32]; 5], k: &[f32; TAPS]) {
                pass1_row(pred, target, clamp, xr, yr, h, k)
            }
            $(#[target_feature(enable = $feat)])?
            pub(super) unsafe fn pass2(h: [&[f32]; 5], wh: (usize, usize), y: usize, gs: Option<f32>, p: [&mut [f32]; 3], k: &[f32; TAPS]) -> f64 {
                pass2_row(h, wh, y, gs, p, k)
            }
            $(#[target_feature(enable = $feat)])?
            pub(super) unsafe fn pass3(p: [&[f32]; 3], h: [&mut [f32]; 3], k: &[f32; TAPS]) {
                pass3_row(p, h, k)
            }
            $(#[target_feature(enable = $feat)])?
            pub(super) unsafe fn pass4(h: [&[f32]; 3], x: &[f32], yv: &[f32], wh: (usize, usize), y: usize, out: &mut [f32], k: &[f32; TAPS]) {
                pass4_row(h, x, yv, wh, y, out, k)
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
        for v in [&mut self.x, &mut self.y]
            .into_iter()
            .chain(self.h.iter_mut())
            .chain(self.p.iter_mut())
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
                .for_each(|(p, t, xr, yr, a, b, c, d, e)| {
                    dispatch!(level, pass1(p, t, clamp, xr, yr, [a, b, c, d, e], &k))
                });
        }
        // pass 2
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
            let [p0, p1, p2] = &mut self.p;
            (
                p0.par_chunks_mut(row),
                p1.par_chunks_mut(row),
                p2.par_chunks_mut(row),
            )
                .into_par_iter()
                .enumerate()
                .with_min_len(4)
                .map(|(y, (a, b, c))| dispatch!(level, pass2(hv, (w, h), y, gs, [a, b, c], &k)))
                .collect_into_vec(&mut self.row_sums);
        }
        let total: f64 = self.row_sums.iter().sum();
        if let Some((out, _)) = grad {
            // pass 3: the partials' horizontal blurs into h[0..3]
            {
                let [h0, h1, h2, _, _] = &mut self.h;
                let [p0, p1, p2] = &self.p;
                (
                    p0.par_chunks(row),
                    p1.par_chunks(row),
                    p2.par_chunks(row),
                    h0.par_chunks_mut(row),
                    h1.par_chunks_mut(row),
                    h2.par_chunks_mut(row),
                )
                    .into_par_iter()
                    .with_min_len(4)
                    .for_each(|(a, b, c, d, e, f)| {
                        dispatch!(level, pass3([a, b, c], [d, e, f], &k))
                    });
            }
            // pass 4
            let hv = [&self.h[0][..], &self.h[1][..], &self.h[2][..]];
            (
                out.par_chunks_mut(row),
                self.x.par_chunks(row),
                self.y.par_chunks(row),
            )
                .into_par_iter()
                .enumerate()
                .with_min_len(4)
                .for_each(|(y, (o, xr, yr))| dispatch!(level, pass4(hv, xr, yr, (w, h), y, o, &k)));
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
}
