//! The per-Gaussian passes MCMC runs at every step, written to vectorise: the position noise
//! (`mu += Sigma (eps f)`, f = sigmoid(100 ((1 - o) - 0.995)) * scaler) and the regularisers'
//! gradients (opacity_reg mean(sigmoid(logit)) + scale_reg mean(exp(s))).
//!
//! Exponentials are [`crate::fastmath::exp`] (libm's `expf` is a call per value and does not
//! vectorise), the normals the counter-based draws of [`crate::rng::Stream`]; plain `+ - * /`,
//! square roots and selects otherwise, with no fused multiply-add, so the AVX-512, AVX2 and
//! scalar builds of each pass give the same bits, whatever the chunking.
use crate::fastmath;
use crate::raster::project::quat_rotation;
use crate::raster::Simd;
use crate::rng::{normal_pair, Stream};

#[inline(always)]
fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + fastmath::exp(-x))
}

/// Lanes of the noise pass: Gaussians moved together, component by component.
const W: usize = 16;

/// The noise over a chunk of Gaussians: `means` (3 per Gaussian) of the Gaussians from `first`
/// on, with their `quats` (4), `log_scales` (3) and opacity `logits`. The interleaved rows are
/// taken apart into lanes of [`W`] Gaussians so that each line below runs as one vector
/// operation.
#[inline(always)]
fn noise(
    means: &mut [f32],
    quats: &[f32],
    log_scales: &[f32],
    logits: &[f32],
    scaler: f32,
    key: u64,
    first: usize,
) {
    let n = logits.len();
    let mut b = 0;
    while b < n {
        let w = W.min(n - b);
        noise_lanes(
            &mut means[3 * b..3 * (b + w)],
            &quats[4 * b..4 * (b + w)],
            &log_scales[3 * b..3 * (b + w)],
            &logits[b..b + w],
            scaler,
            key,
            first + b,
        );
        b += w;
    }
}

/// [`noise`] for at most [`W`] Gaussians (a short tail is padded with lanes never written back).
#[inline(always)]
fn noise_lanes(
    means: &mut [f32],
    quats: &[f32],
    log_scales: &[f32],
    logits: &[f32],
    scaler: f32,
    key: u64,
    first: usize,
) {
    let n = logits.len();
    let mut m = [[0.0f32; W]; 3];
    let mut q = [[0.0f32; W]; 4];
    let mut ls = [[0.0f32; W]; 3];
    let mut l = [0.0f32; W];
    for j in 0..n {
        for a in 0..3 {
            m[a][j] = means[3 * j + a];
            ls[a][j] = log_scales[3 * j + a];
        }
        for a in 0..4 {
            q[a][j] = quats[4 * j + a];
        }
        l[j] = logits[j];
    }
    let mut f = [0.0f32; W];
    for j in 0..W {
        let o = sigmoid(l[j]);
        let gate = 1.0 / (1.0 + fastmath::exp(-100.0 * ((1.0 - o) - 0.995)));
        f[j] = gate * scaler;
    }
    let mut eps = [[0.0f32; W]; 3];
    for j in 0..W {
        let st = Stream::new(key, (first + j) as u64);
        let (e0, e1) = normal_pair(st.word(0));
        let (e2, _) = normal_pair(st.word(1));
        eps[0][j] = e0;
        eps[1][j] = e1;
        eps[2][j] = e2;
    }
    let mut out = [[0.0f32; W]; 3];
    for j in 0..W {
        let (qw, qx, qy, qz) = (q[0][j], q[1][j], q[2][j], q[3][j]);
        let nq = (qw * qw + qx * qx + qy * qy + qz * qz).sqrt();
        let unit = nq > 0.0;
        let d = if unit { nq } else { 1.0 };
        let r = quat_rotation(
            if unit { qw / d } else { 1.0 },
            if unit { qx / d } else { 0.0 },
            if unit { qy / d } else { 0.0 },
            if unit { qz / d } else { 0.0 },
        );
        let s2 = [
            fastmath::exp(2.0 * ls[0][j]),
            fastmath::exp(2.0 * ls[1][j]),
            fastmath::exp(2.0 * ls[2][j]),
        ];
        // Sigma e = R (S^2 (R^T e))
        let fj = f[j];
        let e = [eps[0][j] * fj, eps[1][j] * fj, eps[2][j] * fj];
        let mut t = [0.0f32; 3];
        for a in 0..3 {
            t[a] = (r[0][a] * e[0] + r[1][a] * e[1] + r[2][a] * e[2]) * s2[a];
        }
        let moved = fj != 0.0; // a Gaussian whose gate is 0 keeps its bits (a -0.0 too)
        for a in 0..3 {
            let v = m[a][j] + (r[a][0] * t[0] + r[a][1] * t[1] + r[a][2] * t[2]);
            out[a][j] = if moved { v } else { m[a][j] };
        }
    }
    for j in 0..n {
        for a in 0..3 {
            means[3 * j + a] = out[a][j];
        }
    }
}

/// sigmoid(logit) into `o` and `g += c o (1 - o)` (the opacity regulariser's gradient).
#[inline(always)]
fn opacity_reg(g: &mut [f32], logits: &[f32], o: &mut [f32], c: f32) {
    for ((g, &l), o) in g.iter_mut().zip(logits).zip(o.iter_mut()) {
        let s = sigmoid(l);
        *o = s;
        *g += c * s * (1.0 - s);
    }
}

/// exp(log_scale) into `e` and `g += c e` (the scale regulariser's gradient).
#[inline(always)]
fn scale_reg(g: &mut [f32], log_scales: &[f32], e: &mut [f32], c: f32) {
    for ((g, &l), e) in g.iter_mut().zip(log_scales).zip(e.iter_mut()) {
        let x = fastmath::exp(l);
        *e = x;
        *g += c * x;
    }
}

macro_rules! dispatch {
    ($(#[$doc:meta])* $name:ident => $kernel:ident ( $($arg:ident : $ty:ty),* )) => {
        $(#[$doc])*
        pub(crate) fn $name(level: Simd, $($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
            unsafe fn avx512($($arg: $ty),*) {
                $kernel($($arg),*)
            }
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2,fma")]
            unsafe fn avx2($($arg: $ty),*) {
                $kernel($($arg),*)
            }
            match level {
                // SAFETY: `Simd::resolve` checked the CPU has these features.
                #[cfg(target_arch = "x86_64")]
                Simd::Avx512 => unsafe { avx512($($arg),*) },
                // SAFETY: as above
                #[cfg(target_arch = "x86_64")]
                Simd::Avx2 => unsafe { avx2($($arg),*) },
                _ => $kernel($($arg),*),
            }
        }
    };
}

dispatch!(
    /// The position noise over a chunk (see [`noise`]) with the widest kernel `level` allows.
    noise_chunk => noise(means: &mut [f32], quats: &[f32], log_scales: &[f32], logits: &[f32],
                         scaler: f32, key: u64, first: usize)
);
dispatch!(
    /// The opacity regulariser over a chunk, sigmoids into `o`.
    opacity_reg_chunk => opacity_reg(g: &mut [f32], logits: &[f32], o: &mut [f32], c: f32)
);
dispatch!(
    /// The scale regulariser over a chunk, exponentials into `e`.
    scale_reg_chunk => scale_reg(g: &mut [f32], log_scales: &[f32], e: &mut [f32], c: f32)
);

#[cfg(test)]
mod tests {
    use super::*;

    fn inputs(n: usize) -> (Vec<f32>, Vec<f32>, Vec<f32>, Vec<f32>) {
        let u = |i: usize, salt: u64| Stream::new(salt, i as u64).uniform();
        let means: Vec<f32> = (0..3 * n).map(|i| 4.0 * u(i, 1) - 2.0).collect();
        let quats: Vec<f32> = (0..4 * n)
            .map(|i| {
                if i % 97 == 0 {
                    0.0
                } else {
                    2.0 * u(i, 2) - 1.0
                }
            })
            .collect();
        let scales: Vec<f32> = (0..3 * n).map(|i| -6.0 + 5.0 * u(i, 3)).collect();
        // opacities from fully transparent to opaque: the gate spans 0 to 1
        let logits: Vec<f32> = (0..n).map(|i| -12.0 + 16.0 * u(i, 4)).collect();
        (means, quats, scales, logits)
    }

    #[test]
    fn every_simd_level_gives_the_same_bits() {
        let n = 1000;
        let (means, quats, scales, logits) = inputs(n);
        let mut out = Vec::new();
        for level in [Simd::Scalar, Simd::Avx2, Simd::Avx512] {
            if level.resolve() != level {
                continue; // this CPU lacks it
            }
            let mut m = means.clone();
            noise_chunk(level, &mut m, &quats, &scales, &logits, 80.0, 7, 0);
            let (mut go, mut o) = (vec![0.5f32; n], vec![0.0f32; n]);
            opacity_reg_chunk(level, &mut go, &logits, &mut o, 0.01);
            let (mut gs, mut e) = (vec![0.25f32; 3 * n], vec![0.0f32; 3 * n]);
            scale_reg_chunk(level, &mut gs, &scales, &mut e, 0.01);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            out.push([bits(&m), bits(&go), bits(&o), bits(&gs), bits(&e)]);
        }
        assert!(!out.is_empty());
        for o in &out[1..] {
            assert_eq!(o, &out[0]);
        }
    }

    #[test]
    fn the_noise_moves_transparent_gaussians_by_their_covariance_and_spares_opaque_ones() {
        let n = 1000;
        let (means, quats, scales, logits) = inputs(n);
        let mut m = means.clone();
        noise_chunk(
            Simd::Auto.resolve(),
            &mut m,
            &quats,
            &scales,
            &logits,
            80.0,
            7,
            0,
        );
        let mut moved_transparent = 0;
        for i in 0..n {
            let d: f32 = (0..3)
                .map(|a| (m[3 * i + a] - means[3 * i + a]).abs())
                .sum();
            let o = 1.0 / (1.0 + (-logits[i]).exp());
            if o > 0.3 {
                // the gate is below 1e-12 there: a step far under the coordinates' spacing
                assert_eq!(d, 0.0, "opaque Gaussian {i} (o = {o}) moved by {d}");
            } else if o < 0.001 {
                let smax = (0..3)
                    .map(|a| (2.0 * scales[3 * i + a]).exp())
                    .fold(0.0, f32::max);
                assert!(
                    d <= 3.0 * 9.0 * 6.6 * 80.0 * smax,
                    "Gaussian {i} moved by {d}"
                );
                moved_transparent += (d > 0.0) as usize;
            }
        }
        assert!(moved_transparent > 50, "{moved_transparent}");
    }
}
