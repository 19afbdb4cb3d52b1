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
//! the zero-padded blur is its own adjoint because the window is symmetric). Rows are processed
//! in parallel and every output value is computed in a fixed order, so results are the same bits
//! for any thread count; the mean is summed per row in f64, rows in order.
use rayon::prelude::*;

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

/// Rows per parallel work unit of the passes.
const ROWS: usize = 8;

/// Scratch planes of the SSIM passes, reused across calls.
#[derive(Default)]
pub struct SsimWorkspace {
    x: Vec<f32>,
    y: Vec<f32>,
    tmp: Vec<f32>,
    mu_x: Vec<f32>,
    mu_y: Vec<f32>,
    e_xx: Vec<f32>,
    e_yy: Vec<f32>,
    e_xy: Vec<f32>,
    a: Vec<f32>,
    b: Vec<f32>,
    c: Vec<f32>,
    row_sums: Vec<f64>,
}

/// Zero-padded separable blur of a `w` x `h` plane: horizontal into `tmp`, vertical into `dst`.
fn blur(src: &[f32], dst: &mut [f32], tmp: &mut [f32], w: usize, h: usize, k: &[f32; TAPS]) {
    tmp.par_chunks_mut(w * ROWS)
        .enumerate()
        .for_each(|(c, out)| {
            let mut pad = vec![0.0f32; w + 2 * RADIUS];
            for (r, orow) in out.chunks_mut(w).enumerate() {
                let y = c * ROWS + r;
                pad[RADIUS..RADIUS + w].copy_from_slice(&src[y * w..(y + 1) * w]);
                orow.fill(0.0);
                for (t, &kt) in k.iter().enumerate() {
                    for (o, p) in orow.iter_mut().zip(&pad[t..t + w]) {
                        *o += kt * p;
                    }
                }
            }
        });
    let tmp = &*tmp;
    dst.par_chunks_mut(w * ROWS)
        .enumerate()
        .for_each(|(c, out)| {
            for (r, orow) in out.chunks_mut(w).enumerate() {
                let y = c * ROWS + r;
                orow.fill(0.0);
                for (t, &kt) in k.iter().enumerate() {
                    let yy = y as isize + t as isize - RADIUS as isize;
                    if yy < 0 || yy >= h as isize {
                        continue;
                    }
                    let irow = &tmp[yy as usize * w..(yy as usize + 1) * w];
                    for (o, p) in orow.iter_mut().zip(irow) {
                        *o += kt * p;
                    }
                }
            }
        });
}

fn resize(v: &mut Vec<f32>, n: usize) {
    v.clear();
    v.resize(n, 0.0);
}

/// `src` (H*W*3 interleaved) channel `ch` into the plane `dst`, optionally clamped to [0, 1].
fn plane(src: &[f32], ch: usize, dst: &mut Vec<f32>, clamp: bool) {
    dst.clear();
    dst.extend(src.iter().skip(ch).step_by(3).map(|&v| {
        if clamp {
            v.clamp(0.0, 1.0)
        } else {
            v
        }
    }));
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
        mut grad: Option<(&mut [f32], f32)>,
    ) -> f64 {
        let (w, h) = (width, height);
        let n = w * h;
        debug_assert_eq!(pred.len(), n * 3);
        debug_assert_eq!(target.len(), n * 3);
        if n == 0 {
            return 1.0;
        }
        let k = window();
        for v in [
            &mut self.tmp,
            &mut self.mu_x,
            &mut self.mu_y,
            &mut self.e_xx,
            &mut self.e_yy,
            &mut self.e_xy,
            &mut self.a,
            &mut self.b,
            &mut self.c,
        ] {
            resize(v, n);
        }
        let mut total = 0.0f64;
        // d(mean SSIM)/dS(p) for one pixel of one channel
        let g = 1.0 / (3.0 * n as f64);
        for ch in 0..3 {
            plane(pred, ch, &mut self.x, clamp);
            plane(target, ch, &mut self.y, false);
            blur(&self.x, &mut self.mu_x, &mut self.tmp, w, h, &k);
            blur(&self.y, &mut self.mu_y, &mut self.tmp, w, h, &k);
            let sq: Vec<f32> = self.x.par_iter().map(|v| v * v).collect();
            blur(&sq, &mut self.e_xx, &mut self.tmp, w, h, &k);
            let sq: Vec<f32> = self.y.par_iter().map(|v| v * v).collect();
            blur(&sq, &mut self.e_yy, &mut self.tmp, w, h, &k);
            let xy: Vec<f32> = self
                .x
                .par_iter()
                .zip(self.y.par_iter())
                .map(|(a, b)| a * b)
                .collect();
            blur(&xy, &mut self.e_xy, &mut self.tmp, w, h, &k);
            let want = grad.is_some();
            let (mx, my, exx, eyy, exy) = (&self.mu_x, &self.mu_y, &self.e_xx, &self.e_yy, &self.e_xy);
            let gs = (g * grad.as_ref().map_or(0.0, |g| g.1 as f64)) as f32;
            self.row_sums.clear();
            self.a
                .par_chunks_mut(w)
                .zip(self.b.par_chunks_mut(w))
                .zip(self.c.par_chunks_mut(w))
                .enumerate()
                .map(|(y, ((ra, rb), rc))| {
                    let mut sum = 0.0f64;
                    for x in 0..w {
                        let i = y * w + x;
                        let (ux, uy) = (mx[i], my[i]);
                        let sxx = exx[i] - ux * ux;
                        let syy = eyy[i] - uy * uy;
                        let sxy = exy[i] - ux * uy;
                        let a1 = 2.0 * ux * uy + C1;
                        let a2 = 2.0 * sxy + C2;
                        let b1 = ux * ux + uy * uy + C1;
                        let b2 = sxx + syy + C2;
                        let s = (a1 * a2) / (b1 * b2);
                        sum += s as f64;
                        if want {
                            let d_mu = s
                                * (2.0 * uy / a1 - 2.0 * uy / a2 - 2.0 * ux / b1 + 2.0 * ux / b2);
                            ra[x] = gs * d_mu;
                            rb[x] = gs * (-s / b2);
                            rc[x] = gs * (2.0 * s / a2);
                        }
                    }
                    sum
                })
                .collect_into_vec(&mut self.row_sums);
            total += self.row_sums.iter().sum::<f64>();
            if let Some((out, _)) = grad.as_mut() {
                // reuse the statistics planes for the blurred partials
                blur(&self.a, &mut self.mu_x, &mut self.tmp, w, h, &k);
                blur(&self.b, &mut self.e_xx, &mut self.tmp, w, h, &k);
                blur(&self.c, &mut self.e_xy, &mut self.tmp, w, h, &k);
                let (ga, gb, gc, xs, ys) = (&self.mu_x, &self.e_xx, &self.e_xy, &self.x, &self.y);
                out.par_chunks_mut(3 * w).enumerate().for_each(|(y, row)| {
                    for x in 0..w {
                        let i = y * w + x;
                        row[x * 3 + ch] = ga[i] + 2.0 * xs[i] * gb[i] + ys[i] * gc[i];
                    }
                });
            }
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
    fn same_bits_for_any_thread_count() {
        let (w, h) = (67, 45);
        let x = image(w, h, 5);
        let y = image(w, h, 6);
        let run = |t: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(t)
                .build()
                .expect("pool")
                .install(|| {
                    let mut ws = SsimWorkspace::default();
                    let mut g = vec![0.0f32; w * h * 3];
                    let s = ws.ssim(&x, &y, w, h, false, Some((&mut g, 1.0)));
                    (s.to_bits(), g.iter().map(|v| v.to_bits()).collect::<Vec<_>>())
                })
        };
        assert_eq!(run(1), run(3));
    }
}
