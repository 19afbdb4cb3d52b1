//! The paper's six perturbation operations (SPEC §2), seeded and parallel, and the strength
//! parameterisation's relative scale noise and rotation by an angle (ops 7 and 8).
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

pub mod artifacts;
pub mod haze;
mod kernel;
pub mod popping;
pub mod shatter;
pub mod veil;

use crate::error::{Error, Result};
use crate::mem::zeroed_f32;
use crate::rng::{
    op_key, OP_COLOR, OP_LOG_SCALE, OP_OPACITY, OP_POSITION, OP_PRUNE, OP_ROTATION,
    OP_ROTATION_ANGLE, OP_SCALE,
};
use crate::scene::{Scene, SceneView};

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
    /// Strength parameterisation (op 7): sigma of the noise added to each log axis scale,
    /// `log s' = log s + sigma * z`, so relative to each Gaussian's own scale.
    pub log_scale_noise: Option<f32>,
    /// Strength parameterisation (op 8): RMS angle (radians) of an isotropic rotation,
    /// `q' = exp(omega) * q` with `omega = angle / sqrt(3) * z`, `z ~ N(0, I3)`.
    pub rotation_angle: Option<f32>,
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
        log_scale_noise: None,
        rotation_angle: None,
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
            ("log_scale_noise", self.log_scale_noise),
            ("rotation_angle", self.rotation_angle),
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
        .map(kernel::finite_bounds)
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
        keep.par_chunks_mut(CHUNK)
            .enumerate()
            .for_each(|(c, ks)| kernel::fill_keep(key, (c * CHUNK) as u64, p, ks));
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
    run(view, extras, params, seed, None, false)
}

/// [`perturb`] that also removes the rows where `keep` is false (the holes of
/// [`artifacts::apply`]), besides those pruning removes; every other row's noise is the same as
/// without the mask. Errors as [`perturb`], and for a mask of the wrong length.
pub fn perturb_masked(
    view: &SceneView<'_>,
    extras: &[(&str, &[f32])],
    params: &PerturbParams,
    seed: u64,
    keep: &[bool],
) -> Result<(Scene, Vec<bool>)> {
    run(view, extras, params, seed, Some(keep), false)
}

/// The arrays a perturbation without pruning writes; `None` means the op that writes it is
/// disabled, so the array equals the input's bit for bit (as do `sh_rest` and the extras).
#[derive(Debug, Clone, PartialEq)]
pub struct Changed {
    pub means: Option<Vec<f32>>,
    pub quats: Option<Vec<f32>>,
    pub log_scales: Option<Vec<f32>>,
    pub opacity_logits: Option<Vec<f32>>,
    pub sh0: Option<Vec<f32>>,
}

/// [`perturb`] for parameters that prune nothing, allocating only the arrays an enabled op
/// changes (callers share the others with the input). `Ok(None)` when `params` prune.
pub fn perturb_changed(
    view: &SceneView<'_>,
    params: &PerturbParams,
    seed: u64,
) -> Result<Option<Changed>> {
    if params.prune.is_some_and(|p| p > 0.0) {
        params.validate()?;
        return Ok(None);
    }
    let (s, _) = run(view, &[], params, seed, None, true)?;
    let some = |v: Vec<f32>, on: Option<f32>| on.filter(|&x| x > 0.0).map(|_| v);
    let either = |a: Option<f32>, b: Option<f32>| a.filter(|&x| x > 0.0).or(b);
    Ok(Some(Changed {
        means: some(s.means, params.position_jitter),
        quats: some(
            s.quats,
            either(params.rotation_noise, params.rotation_angle),
        ),
        log_scales: some(
            s.log_scales,
            either(params.scale_noise, params.log_scale_noise),
        ),
        opacity_logits: some(s.opacity_logits, params.opacity_noise),
        sh0: some(s.sh0, params.color_noise),
    }))
}

/// The engine behind both entry points. With `only_changed` (and no pruning), arrays no enabled
/// op writes are left empty instead of copied.
fn run(
    view: &SceneView<'_>,
    extras: &[(&str, &[f32])],
    params: &PerturbParams,
    seed: u64,
    mask: Option<&[bool]>,
    only_changed: bool,
) -> Result<(Scene, Vec<bool>)> {
    view.validate()?;
    params.validate()?;
    let n = view.len();
    if let Some(m) = mask {
        if m.len() != n {
            return Err(Error::InvalidArgument(format!(
                "keep mask holds {} values, expected {n}",
                m.len()
            )));
        }
    }
    check_extras(extras, n)?;
    let mut keep = prune_mask(n, params.prune, seed);
    if let Some(m) = mask {
        keep.iter_mut().zip(m).for_each(|(k, &m)| *k &= m);
    }
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
        log_scale: active(params.log_scale_noise).map(|s| (op_key(seed, OP_LOG_SCALE), s)),
        rotation_angle: active(params.rotation_angle)
            .map(|a| (op_key(seed, OP_ROTATION_ANGLE), a / 3f32.sqrt())),
    };
    let only_changed = only_changed && m == n;
    let buffer = |len: usize, written: bool| {
        if written || !only_changed {
            zeroed_f32(len)
        } else {
            Vec::new()
        }
    };
    let mut out = Scene {
        means: buffer(m * 3, ops.position.is_some()),
        quats: buffer(
            m * 4,
            ops.rotation.is_some() || ops.rotation_angle.is_some(),
        ),
        log_scales: buffer(m * 3, ops.scale.is_some() || ops.log_scale.is_some()),
        opacity_logits: buffer(m, ops.opacity.is_some()),
        sh0: buffer(m * 3, ops.color.is_some()),
        sh_rest: buffer(m * k3, false),
        sh_degree: view.sh_degree,
        extras: extras
            .iter()
            .map(|(name, _)| ((*name).to_owned(), buffer(m, false)))
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
    parts.into_par_iter().enumerate().for_each_init(
        kernel::Scratch::default,
        |scratch, (c, rows)| {
            let i0 = c * CHUNK;
            let i1 = (i0 + CHUNK).min(n);
            scratch.idx.clear();
            scratch
                .idx
                .extend((i0..i1).filter(|&i| keep[i]).map(|i| i as u64));
            kernel::run_chunk(view, extras, k3, &ops, rows, scratch);
        },
    );
    Ok((out, keep))
}

/// Every extra property must hold one value per Gaussian (`n`); names the one that does not.
pub(crate) fn check_extras(extras: &[(&str, &[f32])], n: usize) -> Result<()> {
    for (name, v) in extras {
        if v.len() != n {
            return Err(Error::InvalidArgument(format!(
                "extra property '{name}' holds {} values, expected {n}",
                v.len()
            )));
        }
    }
    Ok(())
}

/// Enabled ops with their stream key and sigma (position: sigma already times E_avg).
pub(crate) struct Ops {
    pub position: Option<(u64, f32)>,
    pub color: Option<(u64, f32)>,
    pub opacity: Option<(u64, f32)>,
    pub scale: Option<(u64, f32)>,
    pub rotation: Option<(u64, f32)>,
    /// Op 7: sigma in log space.
    pub log_scale: Option<(u64, f32)>,
    /// Op 8: sigma of each rotation-vector component (the RMS angle / sqrt 3).
    pub rotation_angle: Option<(u64, f32)>,
}

/// Mutable output rows of one chunk.
pub(crate) struct Rows<'a> {
    pub means: &'a mut [f32],
    pub quats: &'a mut [f32],
    pub log_scales: &'a mut [f32],
    pub opacity_logits: &'a mut [f32],
    pub sh0: &'a mut [f32],
    pub sh_rest: &'a mut [f32],
    pub extras: Vec<&'a mut [f32]>,
}

impl<'a> Rows<'a> {
    /// The first `rows` rows and the rest.
    /// An empty array (one not written) stays empty in both halves.
    fn split(self, rows: usize, k3: usize) -> (Rows<'a>, Rows<'a>) {
        fn cut(s: &mut [f32], len: usize) -> (&mut [f32], &mut [f32]) {
            let len = if s.is_empty() { 0 } else { len };
            s.split_at_mut(len)
        }
        let (means, means_t) = cut(self.means, rows * 3);
        let (quats, quats_t) = cut(self.quats, rows * 4);
        let (log_scales, log_scales_t) = cut(self.log_scales, rows * 3);
        let (opacity_logits, opacity_t) = cut(self.opacity_logits, rows);
        let (sh0, sh0_t) = cut(self.sh0, rows * 3);
        let (sh_rest, sh_rest_t) = cut(self.sh_rest, rows * k3);
        let (extras, extras_t) = self.extras.into_iter().map(|e| cut(e, rows)).unzip();
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::SH_C0;

    /// The activation `GaussianScene.opacities` uses.
    fn sigmoid(x: f32) -> f32 {
        1.0 / (1.0 + (-x).exp())
    }

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
            log_scale_noise: Some(0.0),
            rotation_angle: Some(0.0),
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
    fn batched_kernel_draws_the_documented_stream_values() {
        let s = scene(CHUNK + 300, 0);
        let p = PerturbParams {
            position_jitter: Some(0.01),
            prune: Some(0.5),
            ..Default::default()
        };
        let (out, keep) = run(&s, &p, 99);
        let sigma = (f64::from(0.01f32) * mean_extent(&s.view())) as f32;
        let kept: Vec<usize> = (0..s.len()).filter(|&i| keep[i]).collect();
        for (r, &i) in kept.iter().enumerate() {
            assert_eq!(keep[i], crate::rng::uniform(99, OP_PRUNE, i as u64) >= 0.5);
            for d in 0..3 {
                let z = crate::rng::normal(99, OP_POSITION, i as u64, d as u32);
                let want = s.means[i * 3 + d] + sigma * z;
                assert_eq!(
                    out.means[r * 3 + d].to_bits(),
                    want.to_bits(),
                    "row {i} axis {d}"
                );
            }
        }
    }

    #[test]
    fn changed_arrays_match_the_full_perturbation() {
        let s = scene(2 * CHUNK + 9, 3);
        for name in ["spatial", "radiometric"] {
            let p = PerturbParams::preset(name).expect("known");
            let (full, _) = run(&s, &p, 4);
            let c = perturb_changed(&s.view(), &p, 4)
                .expect("valid")
                .expect("no pruning");
            let pick = |v: Option<Vec<f32>>, orig: &Vec<f32>| v.unwrap_or_else(|| orig.clone());
            assert_eq!(pick(c.means, &s.means), full.means);
            assert_eq!(pick(c.quats, &s.quats), full.quats);
            assert_eq!(pick(c.log_scales, &s.log_scales), full.log_scales);
            assert_eq!(
                pick(c.opacity_logits, &s.opacity_logits),
                full.opacity_logits
            );
            assert_eq!(pick(c.sh0, &s.sh0), full.sh0);
        }
        let morph = PerturbParams::preset("morphological").expect("known");
        assert!(perturb_changed(&s.view(), &morph, 4)
            .expect("valid")
            .is_none());
        let bad = PerturbParams {
            prune: Some(2.0),
            ..Default::default()
        };
        assert!(perturb_changed(&s.view(), &bad, 4).is_err());
    }

    /// The strength ops (7, 8) at once with pruning, as `morphgs.Strength` runs them.
    const STRENGTH: PerturbParams = PerturbParams {
        position_jitter: None,
        color_noise: None,
        opacity_noise: None,
        prune: Some(0.4),
        scale_noise: None,
        rotation_noise: None,
        log_scale_noise: Some(0.7),
        rotation_angle: Some(1.3),
    };

    #[test]
    fn strength_ops_draw_ops_7_and_8_of_each_input_index() {
        let s = scene(CHUNK + 700, 1);
        let (out, keep) = run(&s, &STRENGTH, 21);
        let kept: Vec<usize> = (0..s.len()).filter(|&i| keep[i]).collect();
        assert_eq!(out.len(), kept.len());
        let sigma = 1.3f32 / 3f32.sqrt();
        for (r, &i) in kept.iter().enumerate() {
            for d in 0..3 {
                let z = crate::rng::normal(21, OP_LOG_SCALE, i as u64, d as u32);
                let want = s.log_scales[i * 3 + d] + 0.7 * z;
                assert_eq!(out.log_scales[r * 3 + d].to_bits(), want.to_bits());
            }
            // the rotation in float64 from the same draws
            let z: Vec<f64> = (0..3)
                .map(|d| f64::from(sigma * crate::rng::normal(21, OP_ROTATION_ANGLE, i as u64, d)))
                .collect();
            let theta = (z[0] * z[0] + z[1] * z[1] + z[2] * z[2]).sqrt();
            let k = if theta > 0.0 {
                (0.5 * theta).sin() / theta
            } else {
                0.5
            };
            let (dw, dv) = ((0.5 * theta).cos(), [z[0] * k, z[1] * k, z[2] * k]);
            let q: Vec<f64> = s.quats[i * 4..i * 4 + 4]
                .iter()
                .map(|&v| f64::from(v))
                .collect();
            let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            let (w, v) = (q[0] / n, [q[1] / n, q[2] / n, q[3] / n]);
            let want = [
                dw * w - (dv[0] * v[0] + dv[1] * v[1] + dv[2] * v[2]),
                dw * v[0] + w * dv[0] + dv[1] * v[2] - dv[2] * v[1],
                dw * v[1] + w * dv[1] + dv[2] * v[0] - dv[0] * v[2],
                dw * v[2] + w * dv[2] + dv[0] * v[1] - dv[1] * v[0],
            ];
            for k in 0..4 {
                let got = f64::from(out.quats[r * 4 + k]);
                assert!(
                    (got - want[k]).abs() < 2e-6,
                    "row {i}: {got} vs {}",
                    want[k]
                );
            }
        }
        // the rows the strength ops do not touch follow the mask unchanged
        let kept_scene = s.filter(&keep);
        assert_eq!(out.means, kept_scene.means);
        assert_eq!(out.sh0, kept_scene.sh0);
    }

    #[test]
    fn strength_ops_match_thread_count_one_bit_for_bit() {
        let s = scene(3 * CHUNK + 11, 2);
        let (a, ka) = run(&s, &STRENGTH, 8);
        let single = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .expect("pool");
        let (b, kb) = single.install(|| run(&s, &STRENGTH, 8));
        assert_eq!(ka, kb);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&a.quats), bits(&b.quats));
        assert_eq!(bits(&a.log_scales), bits(&b.log_scales));
        // and the same noise without pruning (perturb_changed) for the same input index
        let p = PerturbParams {
            prune: None,
            ..STRENGTH
        };
        let c = perturb_changed(&s.view(), &p, 8)
            .expect("valid")
            .expect("no pruning");
        let (full, _) = run(&s, &p, 8);
        assert_eq!(c.quats.expect("rotated"), full.quats);
        assert_eq!(c.log_scales.expect("scaled"), full.log_scales);
        assert!(c.means.is_none() && c.sh0.is_none());
    }

    #[test]
    fn rotation_by_an_angle_turns_by_that_angle() {
        for (x, want) in [(0.0f32, 0.0f64), (0.3, 0.3), (2.0, 2.0), (7.0, 7.0)] {
            let q = kernel::rotate([0.3, -0.5, 0.1, 0.8], [x * 0.6, 0.0, x * 0.8]);
            let u = {
                let n = (0.09f64 + 0.25 + 0.01 + 0.64).sqrt();
                [0.3 / n, -0.5 / n, 0.1 / n, 0.8 / n]
            };
            let dot: f64 = (0..4).map(|k| f64::from(q[k]) * u[k]).sum();
            // |<q', q>| = |cos(angle / 2)|
            assert!((dot - (want / 2.0).cos()).abs() < 1e-6, "{x}: {dot}");
            let n: f32 = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            assert!((n - 1.0).abs() < 1e-6);
        }
    }

    #[test]
    fn sin_cos_is_accurate_over_many_turns() {
        for t in 0..20_000 {
            let x = t as f32 * 0.01;
            let (s, c) = kernel::sin_cos(x);
            let xd = f64::from(x);
            assert!((f64::from(s) - xd.sin()).abs() < 1e-6, "sin {x}");
            assert!((f64::from(c) - xd.cos()).abs() < 1e-6, "cos {x}");
        }
        let (s, c) = kernel::sin_cos(f32::INFINITY);
        assert!(s.is_nan() && c.is_nan());
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
