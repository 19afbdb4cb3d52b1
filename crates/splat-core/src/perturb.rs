//! The paper's six perturbation operations (SPEC §2), seeded and parallel.
//!
//! [`perturb`] reads a scene, decides which Gaussians survive pruning, allocates the output arrays
//! once for the survivors and fills them in parallel over fixed-size chunks of the input: every
//! surviving Gaussian is copied and perturbed in one pass, so the only extra memory is the one
//! output scene. Every random draw comes from [`crate::rng`] keyed by `(seed, op, index)`, which
//! makes the output bit-identical for any thread count and gives Gaussian `i` the same noise in
//! an op whichever other ops run.
//!
//! A noise scale of zero (or `None`) leaves its field untouched, bit for bit, and a pruning
//! probability of zero (or `None`) keeps every Gaussian: `scaled(0)` configs are the identity.
use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::rng::{
    op_key, Stream, OP_COLOR, OP_OPACITY, OP_POSITION, OP_PRUNE, OP_ROTATION, OP_SCALE,
};
use crate::scene::{Scene, SceneView, SH_C0};

/// Gaussians per parallel work item (fixed, never derived from the thread count).
pub const CHUNK: usize = 4096;
/// Opacity clamp after opacity noise (activated space).
pub const OPACITY_MIN: f32 = 1e-4;
/// Opacity clamp after opacity noise (activated space).
pub const OPACITY_MAX: f32 = 1.0 - 1e-4;
/// Floor of the linear scales after scale noise.
pub const SCALE_MIN: f32 = 1e-6;

/// Parameters of the six operations; `None` disables an operation.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PerturbParams {
    /// gamma_xyz: position jitter sigma as a fraction of the mean scene extent E_avg.
    pub position_jitter: Option<f32>,
    /// sigma_color: noise on the DC colour c = 0.5 + C0 * sh0.
    pub color_noise: Option<f32>,
    /// sigma_opac: noise on the activated opacity.
    pub opacity_noise: Option<f32>,
    /// p_prune: probability of removing each Gaussian.
    pub prune: Option<f32>,
    /// sigma_scale: noise on the linear axis scales.
    pub scale_noise: Option<f32>,
    /// sigma_rot: noise on the normalised quaternion.
    pub rotation_noise: Option<f32>,
}

impl PerturbParams {
    /// Every operation at the paper's default.
    pub const PAPER: PerturbParams = PerturbParams {
        position_jitter: Some(0.002),
        color_noise: Some(0.05),
        opacity_noise: Some(0.05),
        prune: Some(0.5),
        scale_noise: Some(0.01),
        rotation_noise: Some(0.01),
    };

    /// Names accepted by [`PerturbParams::preset`].
    pub const PRESETS: [&'static str; 4] = ["spatial", "radiometric", "morphological", "naive"];

    /// The paper's presets: `spatial` (position jitter), `radiometric` (colour + opacity),
    /// `morphological` (pruning + scale + rotation), `naive` (all six); paper defaults.
    pub fn preset(name: &str) -> Result<Self> {
        let p = Self::PAPER;
        let none = PerturbParams::default();
        Ok(match name {
            "spatial" => PerturbParams {
                position_jitter: p.position_jitter,
                ..none
            },
            "radiometric" => PerturbParams {
                color_noise: p.color_noise,
                opacity_noise: p.opacity_noise,
                ..none
            },
            "morphological" => PerturbParams {
                prune: p.prune,
                scale_noise: p.scale_noise,
                rotation_noise: p.rotation_noise,
                ..none
            },
            "naive" => p,
            other => {
                return Err(Error::InvalidArgument(format!(
                    "unknown preset '{other}'; valid presets: {}",
                    Self::PRESETS.join(", ")
                )))
            }
        })
    }

    /// Check every field: noise scales finite and >= 0, prune in [0, 1].
    pub fn validate(&self) -> Result<()> {
        let noises = [
            ("position_jitter", self.position_jitter),
            ("color_noise", self.color_noise),
            ("opacity_noise", self.opacity_noise),
            ("scale_noise", self.scale_noise),
            ("rotation_noise", self.rotation_noise),
        ];
        for (name, v) in noises {
            if let Some(v) = v {
                if !(v.is_finite() && v >= 0.0) {
                    return Err(Error::InvalidArgument(format!(
                        "{name} must be a finite number >= 0, got {v}"
                    )));
                }
            }
        }
        if let Some(p) = self.prune {
            if !(0.0..=1.0).contains(&p) {
                return Err(Error::InvalidArgument(format!(
                    "prune must be a probability in [0, 1], got {p}"
                )));
            }
        }
        Ok(())
    }
}

/// E_avg = mean over x, y, z of (max - min) of the finite centres; 0 for an empty scene.
pub fn mean_extent(view: &SceneView<'_>) -> f64 {
    let init = || ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    let (lo, hi) = view
        .means
        .par_chunks(CHUNK * 3)
        .map(|c| {
            let (mut lo, mut hi) = init();
            for p in c.chunks_exact(3) {
                if p.iter().all(|v| v.is_finite()) {
                    for d in 0..3 {
                        lo[d] = lo[d].min(p[d]);
                        hi[d] = hi[d].max(p[d]);
                    }
                }
            }
            (lo, hi)
        })
        // min/max are exact and associative: any reduction order gives the same bits
        .reduce(init, |(a, b), (c, d)| {
            (
                [a[0].min(c[0]), a[1].min(c[1]), a[2].min(c[2])],
                [b[0].max(d[0]), b[1].max(d[1]), b[2].max(d[2])],
            )
        });
    if lo[0] > hi[0] {
        return 0.0;
    }
    (0..3)
        .map(|d| f64::from(hi[d]) - f64::from(lo[d]))
        .sum::<f64>()
        / 3.0
}

/// The keep mask of random pruning with probability `p`: Gaussian `i` survives iff its uniform
/// draw in op [`OP_PRUNE`] is >= p (so p = 0 keeps all and p = 1 removes all).
pub fn prune_mask(n: usize, p: Option<f32>, seed: u64) -> Vec<bool> {
    let mut keep = vec![true; n];
    if let Some(p) = p.filter(|&p| p > 0.0) {
        let key = op_key(seed, OP_PRUNE);
        keep.par_chunks_mut(CHUNK).enumerate().for_each(|(c, ks)| {
            let i0 = (c * CHUNK) as u64;
            for (l, k) in ks.iter_mut().enumerate() {
                *k = Stream::new(key, i0 + l as u64).uniform() >= p;
            }
        });
    }
    keep
}

/// Perturb a scene. Returns the new scene (extras follow the survivors, `sh_rest` is copied
/// unchanged) and the keep mask of length `view.len()` (all true without pruning).
///
/// Errors: [`Error::InvalidArgument`] naming the field for invalid parameters, inconsistent
/// array lengths or an extra of the wrong length.
pub fn perturb(
    view: &SceneView<'_>,
    extras: &[(&str, &[f32])],
    params: &PerturbParams,
    seed: u64,
) -> Result<(Scene, Vec<bool>)> {
    view.validate()?;
    params.validate()?;
    let n = view.len();
    for (name, v) in extras {
        if v.len() != n {
            return Err(Error::InvalidArgument(format!(
                "extra property '{name}' holds {} values, expected {n}",
                v.len()
            )));
        }
    }
    let keep = prune_mask(n, params.prune, seed);
    let counts: Vec<usize> = keep
        .par_chunks(CHUNK)
        .map(|c| c.iter().filter(|&&k| k).count())
        .collect();
    let m: usize = counts.iter().sum();
    let k3 = view.sh_rest_k() * 3;

    let active = |v: Option<f32>| v.filter(|&s| s > 0.0);
    let ops = Ops {
        position: active(params.position_jitter).map(|g| {
            let sigma = (f64::from(g) * mean_extent(view)) as f32;
            (op_key(seed, OP_POSITION), sigma)
        }),
        color: active(params.color_noise).map(|s| (op_key(seed, OP_COLOR), s)),
        opacity: active(params.opacity_noise).map(|s| (op_key(seed, OP_OPACITY), s)),
        scale: active(params.scale_noise).map(|s| (op_key(seed, OP_SCALE), s)),
        rotation: active(params.rotation_noise).map(|s| (op_key(seed, OP_ROTATION), s)),
    };

    let mut out = Scene {
        means: vec![0.0; m * 3],
        quats: vec![0.0; m * 4],
        log_scales: vec![0.0; m * 3],
        opacity_logits: vec![0.0; m],
        sh0: vec![0.0; m * 3],
        sh_rest: vec![0.0; m * k3],
        sh_degree: view.sh_degree,
        extras: extras
            .iter()
            .map(|(name, _)| ((*name).to_owned(), vec![0.0; m]))
            .collect(),
    };
    let mut rest = Rows {
        means: &mut out.means,
        quats: &mut out.quats,
        log_scales: &mut out.log_scales,
        opacity_logits: &mut out.opacity_logits,
        sh0: &mut out.sh0,
        sh_rest: &mut out.sh_rest,
        extras: out
            .extras
            .iter_mut()
            .map(|(_, v)| v.as_mut_slice())
            .collect(),
    };
    let mut parts = Vec::with_capacity(counts.len());
    for &c in &counts {
        let (head, tail) = rest.split(c, k3);
        parts.push(head);
        rest = tail;
    }
    parts.into_par_iter().enumerate().for_each(|(c, rows)| {
        let i0 = c * CHUNK;
        let i1 = (i0 + CHUNK).min(n);
        let idx: Vec<usize> = (i0..i1).filter(|&i| keep[i]).collect();
        copy_rows(view, extras, k3, &idx, i1 - i0 == idx.len(), rows, &ops);
    });
    Ok((out, keep))
}

/// Enabled ops with their stream key and sigma (position: sigma already times E_avg).
struct Ops {
    position: Option<(u64, f32)>,
    color: Option<(u64, f32)>,
    opacity: Option<(u64, f32)>,
    scale: Option<(u64, f32)>,
    rotation: Option<(u64, f32)>,
}

/// Mutable output rows of one chunk.
struct Rows<'a> {
    means: &'a mut [f32],
    quats: &'a mut [f32],
    log_scales: &'a mut [f32],
    opacity_logits: &'a mut [f32],
    sh0: &'a mut [f32],
    sh_rest: &'a mut [f32],
    extras: Vec<&'a mut [f32]>,
}

impl<'a> Rows<'a> {
    /// The first `rows` rows and the rest.
    fn split(self, rows: usize, k3: usize) -> (Rows<'a>, Rows<'a>) {
        let (means, means_t) = self.means.split_at_mut(rows * 3);
        let (quats, quats_t) = self.quats.split_at_mut(rows * 4);
        let (log_scales, log_scales_t) = self.log_scales.split_at_mut(rows * 3);
        let (opacity_logits, opacity_t) = self.opacity_logits.split_at_mut(rows);
        let (sh0, sh0_t) = self.sh0.split_at_mut(rows * 3);
        let (sh_rest, sh_rest_t) = self.sh_rest.split_at_mut(rows * k3);
        let (extras, extras_t) = self
            .extras
            .into_iter()
            .map(|e| e.split_at_mut(rows))
            .unzip();
        (
            Rows {
                means,
                quats,
                log_scales,
                opacity_logits,
                sh0,
                sh_rest,
                extras,
            },
            Rows {
                means: means_t,
                quats: quats_t,
                log_scales: log_scales_t,
                opacity_logits: opacity_t,
                sh0: sh0_t,
                sh_rest: sh_rest_t,
                extras: extras_t,
            },
        )
    }
}

/// Copy the rows `idx` (global indices, ascending; `contiguous` when they are a whole range)
/// into `out`, then apply the enabled ops in place.
fn copy_rows(
    view: &SceneView<'_>,
    extras: &[(&str, &[f32])],
    k3: usize,
    idx: &[usize],
    contiguous: bool,
    out: Rows<'_>,
    ops: &Ops,
) {
    let gather = |dst: &mut [f32], src: &[f32], w: usize| {
        if w == 0 {
            return;
        }
        if contiguous {
            if let Some(&first) = idx.first() {
                dst.copy_from_slice(&src[first * w..(first + idx.len()) * w]);
            }
        } else {
            for (d, &i) in dst.chunks_exact_mut(w).zip(idx) {
                d.copy_from_slice(&src[i * w..(i + 1) * w]);
            }
        }
    };
    gather(out.means, view.means, 3);
    gather(out.quats, view.quats, 4);
    gather(out.log_scales, view.log_scales, 3);
    gather(out.opacity_logits, view.opacity_logits, 1);
    gather(out.sh0, view.sh0, 3);
    gather(out.sh_rest, view.sh_rest, k3);
    for (dst, (_, src)) in out.extras.into_iter().zip(extras) {
        gather(dst, src, 1);
    }

    if let Some((key, sigma)) = ops.position {
        for (row, &i) in out.means.chunks_exact_mut(3).zip(idx) {
            let z: [f32; 3] = Stream::new(key, i as u64).normals();
            for d in 0..3 {
                row[d] += sigma * z[d];
            }
        }
    }
    if let Some((key, sigma)) = ops.color {
        for (row, &i) in out.sh0.chunks_exact_mut(3).zip(idx) {
            let z: [f32; 3] = Stream::new(key, i as u64).normals();
            for d in 0..3 {
                let c = 0.5 + SH_C0 * row[d];
                row[d] = sh0_from_color((c + sigma * z[d]).clamp(0.0, 1.0));
            }
        }
    }
    if let Some((key, sigma)) = ops.opacity {
        for (x, &i) in out.opacity_logits.iter_mut().zip(idx) {
            let [z]: [f32; 1] = Stream::new(key, i as u64).normals();
            let a = (sigmoid(*x) + sigma * z).clamp(OPACITY_MIN, OPACITY_MAX);
            *x = logit_in_range(a);
        }
    }
    if let Some((key, sigma)) = ops.scale {
        for (row, &i) in out.log_scales.chunks_exact_mut(3).zip(idx) {
            let z: [f32; 3] = Stream::new(key, i as u64).normals();
            for d in 0..3 {
                let s = row[d].exp() + sigma * z[d];
                row[d] = log_scale_floored(s);
            }
        }
    }
    if let Some((key, sigma)) = ops.rotation {
        for (q, &i) in out.quats.chunks_exact_mut(4).zip(idx) {
            let z: [f32; 4] = Stream::new(key, i as u64).normals();
            let u = unit(q);
            let w = [
                u[0] + sigma * z[0],
                u[1] + sigma * z[1],
                u[2] + sigma * z[2],
                u[3] + sigma * z[3],
            ];
            let n2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2] + w[3] * w[3];
            if n2 > 0.0 && n2.is_finite() {
                let norm = n2.sqrt();
                for d in 0..4 {
                    q[d] = w[d] / norm;
                }
            } else {
                q.copy_from_slice(&u);
            }
        }
    }
}

/// q / |q|; a zero quaternion becomes the identity, a non-finite one is returned as is.
#[inline]
fn unit(q: &[f32]) -> [f32; 4] {
    let n2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
    if n2 > 0.0 && n2.is_finite() {
        let norm = n2.sqrt();
        [q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm]
    } else if n2 == 0.0 {
        [1.0, 0.0, 0.0, 0.0]
    } else {
        [q[0], q[1], q[2], q[3]]
    }
}

/// The activation `GaussianScene.opacities` uses.
#[inline]
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// One float step toward zero (for nonzero finite `v`).
#[inline]
fn toward_zero(v: f32) -> f32 {
    f32::from_bits(v.to_bits() - 1)
}

/// sh0 for a colour in [0, 1], nudged by an ulp where needed so that 0.5 + C0 * sh0 (float32,
/// as `GaussianScene.colors` computes it) stays inside [0, 1].
#[inline]
fn sh0_from_color(c: f32) -> f32 {
    let mut v = (c - 0.5) / SH_C0;
    if c <= 0.0 || c >= 1.0 {
        for _ in 0..4 {
            let back = 0.5 + SH_C0 * v;
            if (0.0..=1.0).contains(&back) || v == 0.0 {
                break;
            }
            v = toward_zero(v);
        }
    }
    v
}

/// logit(a) for a in [OPACITY_MIN, OPACITY_MAX], nudged so that sigmoid of it stays in range.
#[inline]
fn logit_in_range(a: f32) -> f32 {
    let mut x = (a / (1.0 - a)).ln();
    if !(1.01 * OPACITY_MIN..=1.0 - 1.01 * (1.0 - OPACITY_MAX)).contains(&a) {
        for _ in 0..8 {
            let s = sigmoid(x);
            if (OPACITY_MIN..=OPACITY_MAX).contains(&s) || x == 0.0 || !x.is_finite() {
                break;
            }
            x = toward_zero(x);
        }
    }
    x
}

/// ln(max(s, SCALE_MIN)), nudged so that exp of it is >= SCALE_MIN. NaN stays NaN.
#[inline]
fn log_scale_floored(s: f32) -> f32 {
    if s >= 1.01 * SCALE_MIN || s.is_nan() {
        return s.ln();
    }
    let mut x = SCALE_MIN.max(s).ln();
    for _ in 0..8 {
        if x.exp() >= SCALE_MIN {
            break;
        }
        x = toward_zero(x);
    }
    x
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(n: usize, degree: u8) -> Scene {
        let k3 = crate::scene::sh_rest_count(degree) * 3;
        let f = |i: usize, j: usize| ((i * 7 + j * 13) % 97) as f32 / 97.0;
        Scene {
            means: (0..n * 3).map(|t| f(t / 3, t % 3) * 10.0).collect(),
            quats: (0..n * 4).map(|t| f(t / 4, t % 4 + 1) - 0.5).collect(),
            log_scales: (0..n * 3)
                .map(|t| f(t / 3, t % 3 + 5) * 2.0 - 5.0)
                .collect(),
            opacity_logits: (0..n).map(|i| f(i, 9) * 4.0 - 2.0).collect(),
            sh0: (0..n * 3).map(|t| f(t / 3, t % 3 + 11) - 0.5).collect(),
            sh_rest: (0..n * k3).map(|t| t as f32).collect(),
            sh_degree: degree,
            extras: vec![("filter_3D".into(), (0..n).map(|i| i as f32).collect())],
        }
    }

    fn run(s: &Scene, p: &PerturbParams, seed: u64) -> (Scene, Vec<bool>) {
        let extras: Vec<(&str, &[f32])> = s
            .extras
            .iter()
            .map(|(n, v)| (n.as_str(), v.as_slice()))
            .collect();
        perturb(&s.view(), &extras, p, seed).expect("valid input")
    }

    #[test]
    fn presets_enable_their_category_at_paper_defaults() {
        let m = PerturbParams::preset("morphological").expect("known");
        assert_eq!(m.prune, Some(0.5));
        assert_eq!(m.scale_noise, Some(0.01));
        assert_eq!(m.position_jitter, None);
        assert_eq!(
            PerturbParams::preset("naive").expect("known"),
            PerturbParams::PAPER
        );
        let e = PerturbParams::preset("blur")
            .expect_err("unknown")
            .to_string();
        assert!(e.contains("naive") && e.contains("blur"), "{e}");
    }

    #[test]
    fn validation_names_the_field() {
        let bad = [
            (
                PerturbParams {
                    scale_noise: Some(-0.1),
                    ..Default::default()
                },
                "scale_noise",
            ),
            (
                PerturbParams {
                    color_noise: Some(f32::NAN),
                    ..Default::default()
                },
                "color_noise",
            ),
            (
                PerturbParams {
                    prune: Some(1.5),
                    ..Default::default()
                },
                "prune",
            ),
            (
                PerturbParams {
                    prune: Some(f32::NAN),
                    ..Default::default()
                },
                "prune",
            ),
        ];
        for (p, field) in bad {
            let e = p.validate().expect_err("invalid").to_string();
            assert!(e.starts_with(field), "{e}");
        }
    }

    #[test]
    fn output_matches_thread_count_one_bit_for_bit() {
        let s = scene(3 * CHUNK + 17, 3);
        let (a, ka) = run(&s, &PerturbParams::PAPER, 11);
        let single = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .expect("pool");
        let (b, kb) = single.install(|| run(&s, &PerturbParams::PAPER, 11));
        assert_eq!(ka, kb);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for (x, y) in [(&a.means, &b.means), (&a.quats, &b.quats), (&a.sh0, &b.sh0)] {
            assert_eq!(bits(x), bits(y));
        }
        assert_eq!(bits(&a.log_scales), bits(&b.log_scales));
        assert_eq!(bits(&a.opacity_logits), bits(&b.opacity_logits));
    }

    #[test]
    fn pruned_rows_follow_the_mask_with_extras_and_sh_rest_unchanged() {
        let s = scene(2 * CHUNK + 5, 2);
        let p = PerturbParams {
            prune: Some(0.3),
            ..Default::default()
        };
        let (out, keep) = run(&s, &p, 5);
        let kept = s.filter(&keep);
        assert!(out.len() < s.len() && out.len() > s.len() / 2);
        assert_eq!(out, kept);
    }

    #[test]
    fn zero_noise_and_disabled_ops_are_the_identity() {
        let s = scene(1000, 1);
        let zero = PerturbParams {
            position_jitter: Some(0.0),
            color_noise: Some(0.0),
            opacity_noise: Some(0.0),
            prune: Some(0.0),
            scale_noise: Some(0.0),
            rotation_noise: Some(0.0),
        };
        for p in [zero, PerturbParams::default()] {
            let (out, keep) = run(&s, &p, 1);
            assert!(keep.iter().all(|&k| k));
            assert_eq!(out, s);
        }
        let (all_gone, _) = run(
            &s,
            &PerturbParams {
                prune: Some(1.0),
                ..zero
            },
            1,
        );
        assert!(all_gone.is_empty() && all_gone.extras[0].1.is_empty());
    }

    #[test]
    fn clamps_hold_at_extreme_inputs() {
        let mut s = scene(20_000, 0);
        for (i, v) in s.opacity_logits.iter_mut().enumerate() {
            *v = if i % 2 == 0 { 30.0 } else { -30.0 };
        }
        for (i, v) in s.sh0.iter_mut().enumerate() {
            *v = if i % 2 == 0 { 10.0 } else { -10.0 };
        }
        s.log_scales.iter_mut().for_each(|v| *v = -18.0);
        let p = PerturbParams {
            color_noise: Some(0.3),
            opacity_noise: Some(0.3),
            scale_noise: Some(0.5),
            rotation_noise: Some(5.0),
            ..Default::default()
        };
        let (out, _) = run(&s, &p, 9);
        for &x in &out.opacity_logits {
            assert!((OPACITY_MIN..=OPACITY_MAX).contains(&sigmoid(x)), "{x}");
        }
        for &v in &out.sh0 {
            assert!((0.0..=1.0).contains(&(0.5 + SH_C0 * v)), "{v}");
        }
        assert!(out.log_scales.iter().all(|v| v.exp() >= SCALE_MIN));
        for q in out.quats.chunks_exact(4) {
            let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            assert!((n - 1.0).abs() < 1e-6);
        }
    }

    #[test]
    fn mean_extent_ignores_non_finite_centres() {
        let mut s = scene(10, 0);
        s.means = vec![0.0, 0.0, 0.0, 3.0, 6.0, 9.0, f32::NAN, 100.0, 0.0];
        s.means.extend(std::iter::repeat_n(1.0, 21));
        assert_eq!(mean_extent(&s.view()), 6.0);
        assert_eq!(mean_extent(&Scene::empty(0).view()), 0.0);
    }
}
