//! gsplat's `DefaultStrategy` (v1.5.3 `gsplat/strategy/default.py`, `ops.py`), run after the
//! optimiser step of step `step` (0-based, gsplat's order; INRIA densifies before its step):
//!
//! - while `step < refine_stop` the backward adds each visible Gaussian's screen-space gradient
//!   norm (NDC units) and a view count to the statistics;
//! - when `step > refine_start` and `step % refine_every == 0`: with g = grad2d / max(count, 1),
//!   Gaussians with g > grow_grad2d are **duplicated** (exact copies appended, zero moments) when
//!   their largest scale is <= grow_scale3d * scene_scale, else **split**: the parent is removed
//!   and two children appended at mu + R (s * eps), eps ~ N(0, I), with scales s / 1.6 (the
//!   other values copied, zero moments); then Gaussians with sigmoid(logit) < prune_opa, and
//!   after `reset_every` steps those larger than prune_scale3d * scene_scale, are **pruned**; the
//!   statistics restart at zero;
//! - when `step % reset_every == 0` and `step > 0` (and `opacity_reset`): opacities are clamped
//!   to 2 * prune_opa and their moments zeroed. gsplat 1.5.3 never does this (a precedence bug,
//!   `step % n == 0 & step > 0`); `opacity_reset = false` reproduces it.
//!
//! The split draws are keyed by (seed, step, parent index), so the result does not depend on
//! threads.
use rayon::prelude::*;

use crate::raster::diff::DensifyStats;
use crate::rng::Stream;

use super::config::DefaultStrategy;
use super::params::{Params, MEANS, OPACITY, QUATS, SCALES};
use super::rand::{key, OP_SPLIT};

/// What a refinement did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RefineReport {
    pub duplicated: u32,
    pub split: u32,
    pub pruned: u32,
    /// Opacities were reset.
    pub reset: bool,
    /// MCMC: dead Gaussians moved onto live ones.
    pub relocated: u32,
    /// MCMC: Gaussians added.
    pub added: u32,
}

impl RefineReport {
    pub fn changed(&self) -> bool {
        *self != RefineReport::default()
    }
}

pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

pub fn logit(p: f64) -> f32 {
    (p / (1.0 - p)).ln() as f32
}

/// Largest axis scale of Gaussian i.
fn max_scale(p: &Params, i: usize) -> f32 {
    let s = &p.groups[SCALES].value[i * 3..i * 3 + 3];
    s[0].max(s[1]).max(s[2]).exp()
}

/// Rotation matrix of a (w, x, y, z) quaternion, normalised first.
pub fn rotmat(q: &[f32]) -> [[f32; 3]; 3] {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    let (w, x, y, z) = if n > 0.0 {
        (q[0] / n, q[1] / n, q[2] / n, q[3] / n)
    } else {
        (1.0, 0.0, 0.0, 0.0)
    };
    crate::raster::project::quat_rotation(w, x, y, z)
}

/// The strategy's work after the optimiser step of `step`.
pub fn post_step(
    cfg: &DefaultStrategy,
    p: &mut Params,
    stats: &mut DensifyStats,
    step: u32,
    scene_scale: f32,
    seed: u64,
) -> RefineReport {
    let mut rep = RefineReport::default();
    if step >= cfg.refine_stop {
        return rep;
    }
    if step > cfg.refine_start && step.is_multiple_of(cfg.refine_every) {
        let (d, s) = grow(cfg, p, stats, step, scene_scale, seed);
        rep.duplicated = d;
        rep.split = s;
        rep.pruned = prune(cfg, p, step, scene_scale);
        stats.reset(p.len());
    }
    if cfg.opacity_reset && step.is_multiple_of(cfg.reset_every) && step > 0 {
        reset_opacity(p, 2.0 * cfg.prune_opa as f64);
        rep.reset = true;
    }
    rep
}

/// Duplicate and split (returns the counts).
fn grow(
    cfg: &DefaultStrategy,
    p: &mut Params,
    stats: &DensifyStats,
    step: u32,
    scene_scale: f32,
    seed: u64,
) -> (u32, u32) {
    let n = p.len();
    let sums = if cfg.absgrad {
        &stats.grad2d_abs
    } else {
        &stats.grad2d
    };
    let small_limit = cfg.grow_scale3d * scene_scale;
    let mut dupli = Vec::new();
    let mut split = vec![false; n];
    for i in 0..n {
        let g = sums[i] / stats.count[i].max(1.0);
        if g > cfg.grow_grad2d {
            if max_scale(p, i) <= small_limit {
                dupli.push(i);
            } else {
                split[i] = true;
            }
        }
    }
    if !dupli.is_empty() {
        let mut copies = p.gather(&dupli);
        for g in &mut copies.groups {
            g.m.fill(0.0);
            g.v.fill(0.0);
        }
        p.append(&copies);
    }
    split.resize(p.len(), false);
    let sel: Vec<usize> = (0..split.len()).filter(|&i| split[i]).collect();
    if !sel.is_empty() {
        let children = split_children(cfg, p, &sel, step, seed);
        let keep: Vec<bool> = split.iter().map(|s| !s).collect();
        p.retain(&keep);
        p.append(&children);
    }
    (dupli.len() as u32, sel.len() as u32)
}

/// The two children of each selected parent: all first children, then all second ones
/// (gsplat's order), moments zero.
fn split_children(
    cfg: &DefaultStrategy,
    p: &Params,
    sel: &[usize],
    step: u32,
    seed: u64,
) -> Params {
    let one = p.gather(sel);
    let mut kids = one.clone();
    kids.append(&one);
    for g in &mut kids.groups {
        g.m.fill(0.0);
        g.v.fill(0.0);
    }
    let k = key(seed, OP_SPLIT, step as u64);
    let m = sel.len();
    let quats = &one.groups[QUATS].value;
    let scales = &one.groups[SCALES].value;
    let logits = &one.groups[OPACITY].value;
    let mut means = std::mem::take(&mut kids.groups[MEANS].value);
    means
        .par_chunks_mut(3)
        .enumerate()
        .with_min_len(1024)
        .for_each(|(c, mu)| {
            let (b, j) = (c / m, c % m);
            let r = rotmat(&quats[j * 4..j * 4 + 4]);
            let eps: [f32; 3] = Stream::new(k, 2 * sel[j] as u64 + b as u64).normals();
            let s = [
                scales[j * 3].exp() * eps[0],
                scales[j * 3 + 1].exp() * eps[1],
                scales[j * 3 + 2].exp() * eps[2],
            ];
            for (a, row) in mu.iter_mut().zip(&r) {
                *a += row[0] * s[0] + row[1] * s[1] + row[2] * s[2];
            }
        });
    kids.groups[MEANS].value = means;
    for (c, v) in kids.groups[SCALES].value.iter_mut().enumerate() {
        let j = (c / 3) % m;
        // log(exp(s) / 1.6), as gsplat computes it
        *v = (scales[j * 3 + c % 3].exp() / 1.6).ln();
    }
    if cfg.revised_opacity {
        for (c, v) in kids.groups[OPACITY].value.iter_mut().enumerate() {
            let o = sigmoid(logits[c % m]) as f64;
            *v = logit(1.0 - (1.0 - o).sqrt());
        }
    }
    kids
}

/// Remove transparent (and, after the first reset period, too large) Gaussians.
fn prune(cfg: &DefaultStrategy, p: &mut Params, step: u32, scene_scale: f32) -> u32 {
    let n = p.len();
    let big = cfg.prune_scale3d * scene_scale;
    let keep: Vec<bool> = (0..n)
        .map(|i| {
            let transparent = sigmoid(p.groups[OPACITY].value[i]) < cfg.prune_opa;
            let too_big = step > cfg.reset_every && max_scale(p, i) > big;
            !(transparent || too_big)
        })
        .collect();
    let pruned = keep.iter().filter(|k| !**k).count();
    if pruned > 0 {
        p.retain(&keep);
    }
    pruned as u32
}

/// Clamp opacities to `value` (post-sigmoid) and zero their moments.
pub fn reset_opacity(p: &mut Params, value: f64) {
    let cap = logit(value);
    let g = &mut p.groups[OPACITY];
    for v in &mut g.value {
        *v = v.min(cap);
    }
    g.m.fill(0.0);
    g.v.fill(0.0);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Scene;

    /// Gaussian 0: small, high gradient (duplicate); 1: large, high gradient (split); 2: low
    /// gradient, transparent (prune); 3: low gradient, kept.
    fn setup() -> (Params, DensifyStats) {
        let mut s = Scene::zeroed(4, 0);
        for i in 0..4 {
            s.quats[i * 4] = 1.0;
            s.means[i * 3] = i as f32;
        }
        s.log_scales[..3].fill((0.005f32).ln());
        s.log_scales[3..6].fill((0.5f32).ln());
        s.log_scales[6..].fill((0.001f32).ln());
        s.opacity_logits = vec![2.0, 2.0, -8.0, 2.0];
        let mut p = Params::from_view(&s.view());
        p.groups[MEANS].m.fill(1.0);
        let mut st = DensifyStats::default();
        st.reset(4);
        st.grad2d = vec![3e-3, 3e-3, 1e-5, 1e-5];
        st.count = vec![2.0, 2.0, 2.0, 2.0];
        (p, st)
    }

    #[test]
    fn refine_duplicates_splits_and_prunes_like_gsplat() {
        let (mut p, mut st) = setup();
        let cfg = DefaultStrategy::default();
        let rep = post_step(&cfg, &mut p, &mut st, 600, 1.0, 0);
        assert_eq!(
            (rep.duplicated, rep.split, rep.pruned, rep.reset),
            (1, 1, 1, false)
        );
        // order: rest [0, 2, 3, dup(0)] minus pruned 2 -> [0, 3, dup0], then the two children of 1
        assert_eq!(p.len(), 5);
        let xs: Vec<f32> = (0..5).map(|i| p.groups[MEANS].value[i * 3]).collect();
        assert_eq!(&xs[..3], &[0.0, 3.0, 0.0]);
        // children near parent 1, scales / 1.6, zero moments
        for c in 3..5 {
            assert!((xs[c] - 1.0).abs() < 0.5 * 6.0, "{xs:?}");
            let ls = p.groups[SCALES].value[c * 3];
            assert!((ls.exp() - 0.5 / 1.6).abs() < 1e-6);
            assert_eq!(p.groups[MEANS].m[c * 3], 0.0);
        }
        assert_eq!(p.groups[MEANS].m[0], 1.0); // the original keeps its moments
        assert_eq!(p.groups[MEANS].m[2 * 3], 0.0); // the duplicate starts at zero
        assert!(st.count.iter().all(|&c| c == 0.0) && st.count.len() == 5);
        // the two children differ (independent draws)
        assert_ne!(p.groups[MEANS].value[9..12], p.groups[MEANS].value[12..15]);
    }

    #[test]
    fn no_refine_before_start_or_off_cadence_and_reset_follows_the_flag() {
        let cfg = DefaultStrategy::default();
        for step in [500, 650] {
            let (mut p, mut st) = setup();
            assert!(!post_step(&cfg, &mut p, &mut st, step, 1.0, 0).changed());
            assert_eq!(p.len(), 4);
        }
        let (mut p, mut st) = setup();
        let rep = post_step(&cfg, &mut p, &mut st, 3000, 1.0, 0);
        assert!(rep.reset);
        let cap = logit(0.01);
        assert!(p.groups[OPACITY].value.iter().all(|&v| v <= cap));
        let gs153 = DefaultStrategy {
            opacity_reset: false,
            ..cfg
        };
        let (mut p, mut st) = setup();
        assert!(!post_step(&gs153, &mut p, &mut st, 3000, 1.0, 0).reset);
        assert!(p.groups[OPACITY].value.iter().any(|&v| v > cap));
    }

    #[test]
    fn split_draws_do_not_depend_on_threads() {
        let run = |t: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(t)
                .build()
                .expect("pool")
                .install(|| {
                    let (mut p, mut st) = setup();
                    post_step(&DefaultStrategy::default(), &mut p, &mut st, 700, 1.0, 9);
                    p
                })
        };
        assert_eq!(run(1), run(4));
    }
}
