//! The 3DGS photometric loss, (1 - lambda) L1 + lambda (1 - SSIM) with lambda = 0.2, its
//! gradient with respect to the rendered image, and the image metrics (PSNR, SSIM).
//!
//! The rendered colours are compared as they come out of the rasterizer (no clamp), as INRIA and
//! gsplat train; evaluation clamps the render to [0, 1] first, as both evaluate. L1 is the mean
//! over H x W x 3, whose gradient is sign(x - y) / (3 H W) (zero where they are equal, like
//! torch). Sums are taken per row in f64 lanes and added in row order: the same bits for any
//! thread count.
use rayon::prelude::*;

use super::ssim::{l1_term, SsimWorkspace};

/// One image's loss terms.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LossTerms {
    /// (1 - lambda) l1 + lambda (1 - ssim).
    pub loss: f64,
    pub l1: f64,
    pub ssim: f64,
    /// Mean squared error (for the training PSNR), unclamped.
    pub mse: f64,
}

/// Buffers of the loss, reused across steps.
#[derive(Default)]
pub struct LossWorkspace {
    pub ssim: SsimWorkspace,
    rows: Vec<(f64, f64)>,
}

/// PSNR in dB of a mean squared error for values in [0, 1].
pub fn psnr(mse: f64) -> f64 {
    if mse <= 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    }
}

impl LossWorkspace {
    /// Loss terms of `pred` against `target` (H*W*3 interleaved); writes dL/d(pred) into `grad`.
    pub fn loss_and_grad(
        &mut self,
        pred: &[f32],
        target: &[f32],
        width: usize,
        height: usize,
        ssim_lambda: f32,
        grad: &mut [f32],
    ) -> LossTerms {
        let n = width * height * 3;
        let gl1 = (1.0 - ssim_lambda) / n as f32;
        // SSIM and L1 in one pass: each gradient value is the SSIM part (times -lambda), the
        // L1 part added after.
        let (ssim, l1, se) = if ssim_lambda != 0.0 {
            self.ssim
                .ssim_l1(pred, target, width, height, grad, -ssim_lambda, gl1)
        } else {
            grad.fill(0.0);
            let row = width * 3;
            let (l1, se) = l1_term(self.ssim.simd, grad, pred, target, row, gl1, &mut self.rows);
            (1.0, l1, se)
        };
        let l1 = l1 / n as f64;
        let lam = ssim_lambda as f64;
        LossTerms {
            loss: (1.0 - lam) * l1 + lam * (1.0 - ssim),
            l1,
            ssim,
            mse: se / n as f64,
        }
    }

    /// Evaluation metrics of a render against its target: (PSNR dB, SSIM), the render clamped to
    /// [0, 1].
    pub fn metrics(
        &mut self,
        pred: &[f32],
        target: &[f32],
        width: usize,
        height: usize,
    ) -> (f64, f64) {
        let row = width * 3;
        let se: f64 = pred
            .par_chunks(row)
            .zip(target.par_chunks(row))
            .map(|(p, t)| {
                p.iter()
                    .zip(t)
                    .map(|(&p, &t)| {
                        let d = p.clamp(0.0, 1.0) - t;
                        (d * d) as f64
                    })
                    .sum::<f64>()
            })
            .collect::<Vec<f64>>()
            .iter()
            .sum();
        let mse = se / (width * height * 3).max(1) as f64;
        let ssim = self.ssim.ssim(pred, target, width, height, true, None);
        (psnr(mse), ssim)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loss_gradient_matches_finite_differences() {
        let (w, h) = (16, 12);
        let n = w * h * 3;
        let pred: Vec<f32> = (0..n).map(|i| ((i * 37 % 101) as f32) / 101.0).collect();
        let target: Vec<f32> = (0..n).map(|i| ((i * 53 % 97) as f32) / 97.0).collect();
        let mut ws = LossWorkspace::default();
        let mut g = vec![0.0; n];
        let base = ws.loss_and_grad(&pred, &target, w, h, 0.2, &mut g);
        assert!(base.loss > 0.0 && base.l1 > 0.0);
        let mut scratch = vec![0.0; n];
        for &i in &[0usize, 17, 200, n - 1] {
            let eps = 1e-3f32;
            let mut p = pred.clone();
            p[i] += eps;
            let up = ws.loss_and_grad(&p, &target, w, h, 0.2, &mut scratch).loss;
            p[i] -= 2.0 * eps;
            let dn = ws.loss_and_grad(&p, &target, w, h, 0.2, &mut scratch).loss;
            let fd = (up - dn) / (2.0 * eps as f64);
            assert!((fd - g[i] as f64).abs() < 1e-5, "{i}: fd {fd} vs {}", g[i]);
        }
    }

    #[test]
    fn psnr_of_known_error() {
        assert!((psnr(1e-3) - 30.0).abs() < 1e-12);
        let mut ws = LossWorkspace::default();
        let a = vec![0.5f32; 8 * 8 * 3];
        let b = vec![0.6f32; 8 * 8 * 3];
        let (p, s) = ws.metrics(&a, &b, 8, 8);
        assert!((p - 20.0).abs() < 1e-4, "{p}");
        assert!(s < 1.0 && s > 0.9);
    }
}
