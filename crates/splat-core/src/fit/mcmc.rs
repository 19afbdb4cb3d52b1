//! gsplat's `MCMCStrategy` (v1.5.3 `gsplat/strategy/mcmc.py`, `ops.py::relocate`,
//! `sample_add`, `inject_noise_to_position`, `RelocationCUDA.cu`; "3D Gaussian Splatting as
//! Markov Chain Monte Carlo", arXiv 2404.09591), run after the optimiser step of `step`:
//!
//! - when `refine_start < step < refine_stop` and `step % refine_every == 0`:
//!   **relocate**: dead Gaussians (sigmoid(logit) <= min_opacity) take the values of live ones
//!   drawn with replacement with probability proportional to opacity; each drawn source, drawn
//!   n - 1 times, gets (Eq. 9) o' = 1 - (1 - o)^(1/n) and
//!   s' = o / (sum_{i=1..n} sum_{k=0..i-1} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1)) * s, with
//!   n <= 51 and o' clamped to [min_opacity, 1 - eps]; the sources' moments are zeroed (the
//!   dead rows keep theirs, as in gsplat);
//!   **add**: min(cap_max, floor(1.05 N)) - N new Gaussians are drawn the same way from all
//!   Gaussians, their sources rewritten by Eq. 9 and copied to the end with zero moments;
//! - every step, **noise**: mu += Sigma (eps * sigmoid(100 ((1 - o) - 0.995)) * lr_means *
//!   noise_lr), eps ~ N(0, I), Sigma the full 3x3 covariance R S S R^T.
//!
//! Multinomial draws and the noise come from the counter-based generator keyed by (seed, step,
//! index), so the result does not depend on threads. The noise and the regularisers run every
//! step over every Gaussian: their kernels (`mcmc_kernels`) vectorise, with the same bits at every
//! SIMD level.
use rayon::prelude::*;

use crate::raster::Simd;

use super::config::McmcStrategy;
use super::densify::{logit, sigmoid, RefineReport};
use super::mcmc_kernels::{noise_chunk, opacity_reg_chunk, scale_reg_chunk};
use super::params::{Params, OPACITY, SCALES};
use super::rand::{key, multinomial, OP_ADD, OP_NOISE, OP_RELOCATE};

/// Largest number of draws Eq. 9 distinguishes (gsplat's binomial table is 51 x 51).
const N_MAX: usize = 51;

/// Eq. 9: the opacity and the scale factor of a Gaussian drawn `n - 1` times (n in 1..=51).
pub fn relocation(o: f32, n: usize) -> (f32, f32) {
    let n = n.clamp(1, N_MAX);
    let o = o as f64;
    let new_o = 1.0 - (1.0 - o).powf(1.0 / n as f64);
    let mut denom = 0.0f64;
    for i in 1..=n {
        let mut binom = 1.0f64; // C(i-1, k)
        for k in 0..i {
            if k > 0 {
                binom = binom * (i - k) as f64 / k as f64;
            }
            let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
            denom += binom * sign * new_o.powi(k as i32 + 1) / ((k + 1) as f64).sqrt();
        }
    }
    (new_o as f32, (o / denom) as f32)
}

/// Rewrite the drawn sources by Eq. 9 (each distinct source once; n = its draw count + 1).
fn rewrite_sources(p: &mut Params, draws: &[usize], min_opacity: f32) {
    let mut count = vec![0u32; p.len()];
    for &i in draws {
        count[i] += 1;
    }
    let eps = f32::EPSILON as f64;
    for (i, &c) in count.iter().enumerate() {
        if c == 0 {
            continue;
        }
        let o = sigmoid(p.groups[OPACITY].value[i]);
        let (new_o, factor) = relocation(o, c as usize + 1);
        let new_o = (new_o as f64).clamp(min_opacity as f64, 1.0 - eps);
        p.groups[OPACITY].value[i] = logit(new_o);
        for v in &mut p.groups[SCALES].value[i * 3..i * 3 + 3] {
            *v = (v.exp() * factor).ln();
        }
    }
}

/// Move dead Gaussians onto live ones; returns how many moved.
fn relocate(cfg: &McmcStrategy, p: &mut Params, step: u32, seed: u64) -> u32 {
    let n = p.len();
    let opac: Vec<f32> = p.groups[OPACITY]
        .value
        .iter()
        .map(|&l| sigmoid(l))
        .collect();
    let dead: Vec<usize> = (0..n).filter(|&i| opac[i] <= cfg.min_opacity).collect();
    let alive: Vec<usize> = (0..n).filter(|&i| opac[i] > cfg.min_opacity).collect();
    if dead.is_empty() || alive.is_empty() {
        return 0;
    }
    let w: Vec<f32> = alive.iter().map(|&i| opac[i]).collect();
    let src: Vec<usize> = multinomial(&w, dead.len(), seed, OP_RELOCATE, step as u64)
        .into_iter()
        .map(|j| alive[j])
        .collect();
    if src.is_empty() {
        return 0;
    }
    rewrite_sources(p, &src, cfg.min_opacity);
    for (&d, &s) in dead.iter().zip(&src) {
        for g in &mut p.groups {
            let w = g.width;
            g.value.copy_within(s * w..(s + 1) * w, d * w);
        }
    }
    p.zero_moments(&src);
    dead.len() as u32
}

/// Grow by 5% up to the cap; returns how many were added.
fn add(cfg: &McmcStrategy, p: &mut Params, step: u32, seed: u64) -> u32 {
    let n = p.len();
    let target = (cfg.cap_max as usize).min((1.05 * n as f64) as usize);
    if target <= n {
        return 0;
    }
    let opac: Vec<f32> = p.groups[OPACITY]
        .value
        .iter()
        .map(|&l| sigmoid(l))
        .collect();
    let src = multinomial(&opac, target - n, seed, OP_ADD, step as u64);
    if src.is_empty() {
        return 0;
    }
    rewrite_sources(p, &src, cfg.min_opacity);
    let mut copies = p.gather(&src);
    for g in &mut copies.groups {
        g.m.fill(0.0);
        g.v.fill(0.0);
    }
    p.append(&copies);
    src.len() as u32
}

/// Gaussians per parallel unit of the noise pass.
const NOISE_CHUNK: usize = 4096;

/// Add the MCMC position noise (scaler = lr_means * noise_lr).
fn inject_noise(p: &mut Params, scaler: f32, step: u32, seed: u64) {
    let k = key(seed, OP_NOISE, step as u64);
    let level = Simd::Auto.resolve();
    let [means, quats, scales, opac, ..] = &mut p.groups;
    let (quats, scales, opac) = (&quats.value, &scales.value, &opac.value);
    means
        .value
        .par_chunks_mut(3 * NOISE_CHUNK)
        .enumerate()
        .for_each(|(c, chunk)| {
            let (a, n) = (c * NOISE_CHUNK, chunk.len() / 3);
            noise_chunk(
                level,
                chunk,
                &quats[4 * a..4 * (a + n)],
                &scales[3 * a..3 * (a + n)],
                &opac[a..a + n],
                scaler,
                k,
                a,
            );
        });
}

/// The strategy's work after the optimiser step of `step`; `lr_means` is the position learning
/// rate after the step (gsplat passes the scheduler's next rate).
pub fn post_step(
    cfg: &McmcStrategy,
    p: &mut Params,
    step: u32,
    lr_means: f32,
    seed: u64,
) -> RefineReport {
    let mut rep = RefineReport::default();
    if step < cfg.refine_stop && step > cfg.refine_start && step.is_multiple_of(cfg.refine_every) {
        rep.relocated = relocate(cfg, p, step, seed);
        rep.added = add(cfg, p, step, seed);
    }
    inject_noise(p, lr_means * cfg.noise_lr, step, seed);
    rep
}

/// Gradients of the regularisers opacity_reg mean(sigmoid(logit)) + scale_reg mean(exp(s)),
/// added to `g_logits` and `g_log_scales`; returns their value.
pub fn add_regularisers(
    cfg: &McmcStrategy,
    p: &Params,
    g_logits: &mut [f32],
    g_log_scales: &mut [f32],
) -> f64 {
    let n = p.len();
    if n == 0 {
        return 0.0;
    }
    let (ro, rs) = (cfg.opacity_reg, cfg.scale_reg);
    let logits = &p.groups[OPACITY].value;
    let ls = &p.groups[SCALES].value;
    let co = ro / n as f32;
    let cs = rs / (3 * n) as f32;
    let level = Simd::Auto.resolve();
    let so: f64 = g_logits
        .par_chunks_mut(NOISE_CHUNK)
        .zip(logits.par_chunks(NOISE_CHUNK))
        .map(|(g, l)| {
            let mut o = vec![0.0f32; l.len()];
            opacity_reg_chunk(level, g, l, &mut o, co);
            o.iter().fold(0.0f64, |s, &o| s + o as f64)
        })
        .collect::<Vec<f64>>()
        .iter()
        .sum();
    let ss: f64 = g_log_scales
        .par_chunks_mut(3 * NOISE_CHUNK)
        .zip(ls.par_chunks(3 * NOISE_CHUNK))
        .map(|(g, l)| {
            let mut e = vec![0.0f32; l.len()];
            scale_reg_chunk(level, g, l, &mut e, cs);
            e.iter().fold(0.0f64, |s, &e| s + e as f64)
        })
        .collect::<Vec<f64>>()
        .iter()
        .sum();
    ro as f64 * so / n as f64 + rs as f64 * ss / (3 * n) as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::params::MEANS;
    use crate::Scene;

    #[test]
    fn relocation_of_a_single_draw_keeps_the_gaussian() {
        // n = 1: o' = o and the denominator is o' itself, so s' = s
        let (o, f) = relocation(0.3, 1);
        assert!((o - 0.3).abs() < 1e-7 && (f - 1.0).abs() < 1e-6);
        // n = 2: o' = 1 - sqrt(1 - o); denominator o' + (o' - o'^2 / sqrt 2)
        let (o2, f2) = relocation(0.5, 2);
        let op = 1.0 - (0.5f64).sqrt();
        let d = op + op - op * op / 2f64.sqrt();
        assert!((o2 as f64 - op).abs() < 1e-7);
        assert!((f2 as f64 - 0.5 / d).abs() < 1e-6);
    }

    fn scene(n: usize) -> Params {
        let mut s = Scene::zeroed(n, 0);
        for i in 0..n {
            s.quats[i * 4] = 1.0;
            s.means[i * 3..i * 3 + 3].copy_from_slice(&[i as f32, 1.0, 1.0]);
            s.opacity_logits[i] = if i % 4 == 0 { -10.0 } else { 1.0 };
        }
        s.log_scales.fill(-3.0);
        Params::from_view(&s.view())
    }

    #[test]
    fn refine_relocates_the_dead_and_grows_to_the_cap() {
        let mut p = scene(40);
        let cfg = McmcStrategy {
            cap_max: 41,
            ..McmcStrategy::default()
        };
        let rep = post_step(&cfg, &mut p, 600, 0.0, 1);
        assert_eq!(rep.relocated, 10);
        assert_eq!(rep.added, 1);
        assert_eq!(p.len(), 41);
        // nobody is dead any more: the dead rows copied live (rewritten) sources
        assert!(p.groups[OPACITY]
            .value
            .iter()
            .all(|&l| sigmoid(l) > cfg.min_opacity));
        // relocated rows sit on live Gaussians' positions (x = 1, 2, 3, 5, ...)
        for d in (0..40).step_by(4) {
            let x = p.groups[MEANS].value[d * 3];
            assert!(!(x as usize).is_multiple_of(4), "row {d} still at {x}");
        }
        // the cap holds
        let rep = post_step(&cfg, &mut p, 700, 0.0, 1);
        assert_eq!(rep.added, 0);
    }

    #[test]
    fn noise_moves_only_transparent_gaussians() {
        let mut p = scene(8);
        let before = p.groups[MEANS].value.clone();
        post_step(&McmcStrategy::default(), &mut p, 3, 1e-4, 2);
        for i in 0..8 {
            let moved = p.groups[MEANS].value[i * 3..i * 3 + 3] != before[i * 3..i * 3 + 3];
            assert_eq!(moved, i % 4 == 0, "gaussian {i}");
        }
    }
}
