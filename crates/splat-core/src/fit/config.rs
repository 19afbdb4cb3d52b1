//! The optimiser's settings. Defaults are gsplat 1.5.3's `simple_trainer.py default` (which is
//! the INRIA 3DGS recipe), with the opacity reset ON as INRIA and gsplat after 1.5.3 do; see
//! docs/fit.md for the table with sources.
use crate::error::{Error, Result};
use crate::raster::RenderOptions;

use super::params::{AdamParams, GROUPS};

/// Learning rates per parameter array (means: times the scene scale, decayed exponentially to
/// `means_final` times its start over `steps`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LearningRates {
    pub means: f32,
    pub means_final: f32,
    pub quats: f32,
    pub scales: f32,
    pub opacities: f32,
    pub sh0: f32,
    pub sh_rest: f32,
}

impl Default for LearningRates {
    fn default() -> Self {
        LearningRates {
            means: 1.6e-4,
            means_final: 0.01,
            quats: 1e-3,
            scales: 5e-3,
            opacities: 5e-2,
            sh0: 2.5e-3,
            sh_rest: 2.5e-3 / 20.0,
        }
    }
}

/// gsplat's `DefaultStrategy` (clone / split / prune, opacity reset).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DefaultStrategy {
    pub grow_grad2d: f32,
    pub grow_scale3d: f32,
    pub prune_opa: f32,
    pub prune_scale3d: f32,
    pub refine_start: u32,
    pub refine_stop: u32,
    pub refine_every: u32,
    pub reset_every: u32,
    /// Reset opacities to 2 * prune_opa every `reset_every` steps (INRIA, gsplat > 1.5.3).
    /// `false` reproduces gsplat 1.5.3, whose reset never runs (`step % n == 0 & step > 0`).
    pub opacity_reset: bool,
    /// Use the per-pixel absolute 2D gradients (AbsGS) for growth.
    pub absgrad: bool,
    /// Split opacity 1 - sqrt(1 - o) (arXiv 2404.06109) instead of a copy.
    pub revised_opacity: bool,
}

impl Default for DefaultStrategy {
    fn default() -> Self {
        DefaultStrategy {
            grow_grad2d: 2e-4,
            grow_scale3d: 0.01,
            prune_opa: 0.005,
            prune_scale3d: 0.1,
            refine_start: 500,
            refine_stop: 15_000,
            refine_every: 100,
            reset_every: 3000,
            opacity_reset: true,
            absgrad: false,
            revised_opacity: false,
        }
    }
}

/// gsplat's `MCMCStrategy` (relocation of dead Gaussians, growth to a cap, position noise) and
/// the regularisers its trainer adds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct McmcStrategy {
    pub cap_max: u32,
    pub noise_lr: f32,
    pub refine_start: u32,
    pub refine_stop: u32,
    pub refine_every: u32,
    pub min_opacity: f32,
    /// Loss weight of mean(sigmoid(opacity logits)).
    pub opacity_reg: f32,
    /// Loss weight of mean(exp(log scales)).
    pub scale_reg: f32,
}

impl Default for McmcStrategy {
    fn default() -> Self {
        McmcStrategy {
            cap_max: 1_000_000,
            noise_lr: 5e5,
            refine_start: 500,
            refine_stop: 25_000,
            refine_every: 100,
            min_opacity: 0.005,
            opacity_reg: 0.01,
            scale_reg: 0.01,
        }
    }
}

/// How the Gaussian set changes during training.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Strategy {
    Default(DefaultStrategy),
    Mcmc(McmcStrategy),
}

/// Everything the optimiser loop needs besides the data and the initial scene.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitConfig {
    /// Total steps (the position lr decays over these).
    pub steps: u32,
    pub seed: u64,
    /// Scene scale (gsplat `scene_scale`, INRIA `cameras_extent`): scales the means lr and the
    /// strategies' 3D size thresholds.
    pub scene_scale: f32,
    /// Highest SH degree trained; the degree in use is min(step / interval, sh_degree).
    pub sh_degree: u8,
    pub sh_degree_interval: u32,
    pub ssim_lambda: f32,
    pub lr: LearningRates,
    pub adam: AdamParams,
    pub strategy: Strategy,
    /// Background, alpha cap and antialiasing of the training renders.
    pub render: RenderOptions,
}

impl Default for FitConfig {
    fn default() -> Self {
        FitConfig {
            steps: 30_000,
            seed: 0,
            scene_scale: 1.0,
            sh_degree: 3,
            sh_degree_interval: 1000,
            ssim_lambda: 0.2,
            lr: LearningRates::default(),
            adam: AdamParams::default(),
            strategy: Strategy::Default(DefaultStrategy::default()),
            render: RenderOptions::default(),
        }
    }
}

fn positive(name: &str, v: f32) -> Result<()> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(Error::InvalidArgument(format!(
            "{name} must be a positive number, got {v}"
        )))
    }
}

fn non_negative(name: &str, v: f32) -> Result<()> {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(Error::InvalidArgument(format!(
            "{name} must be a number >= 0, got {v}"
        )))
    }
}

impl FitConfig {
    /// Check every value; the error names the field.
    pub fn validate(&self) -> Result<()> {
        if self.steps == 0 {
            return Err(Error::InvalidArgument("steps must be >= 1".into()));
        }
        positive("scene_scale", self.scene_scale)?;
        if self.sh_degree > 3 {
            return Err(Error::InvalidArgument(format!(
                "sh_degree must be 0..=3, got {}",
                self.sh_degree
            )));
        }
        if self.sh_degree_interval == 0 {
            return Err(Error::InvalidArgument(
                "sh_degree_interval must be >= 1".into(),
            ));
        }
        if !(0.0..=1.0).contains(&self.ssim_lambda) {
            return Err(Error::InvalidArgument(format!(
                "ssim_lambda must be in [0, 1], got {}",
                self.ssim_lambda
            )));
        }
        let lr = &self.lr;
        for (name, v) in [
            ("lr.means", lr.means),
            ("lr.means_final", lr.means_final),
            ("lr.quats", lr.quats),
            ("lr.scales", lr.scales),
            ("lr.opacities", lr.opacities),
            ("lr.sh0", lr.sh0),
            ("lr.sh_rest", lr.sh_rest),
        ] {
            non_negative(name, v)?;
        }
        let a = &self.adam;
        if !(0.0..1.0).contains(&a.beta1) || !(0.0..1.0).contains(&a.beta2) {
            return Err(Error::InvalidArgument(
                "adam betas must be in [0, 1)".into(),
            ));
        }
        positive("adam.eps", a.eps)?;
        match &self.strategy {
            Strategy::Default(d) => {
                non_negative("default.grow_grad2d", d.grow_grad2d)?;
                non_negative("default.grow_scale3d", d.grow_scale3d)?;
                non_negative("default.prune_opa", d.prune_opa)?;
                non_negative("default.prune_scale3d", d.prune_scale3d)?;
                if d.refine_every == 0 || d.reset_every == 0 {
                    return Err(Error::InvalidArgument(
                        "default.refine_every and default.reset_every must be >= 1".into(),
                    ));
                }
                if d.prune_opa >= 0.5 {
                    return Err(Error::InvalidArgument(format!(
                        "default.prune_opa must be below 0.5, got {}",
                        d.prune_opa
                    )));
                }
            }
            Strategy::Mcmc(m) => {
                if m.cap_max == 0 {
                    return Err(Error::InvalidArgument("mcmc.cap_max must be >= 1".into()));
                }
                if m.refine_every == 0 {
                    return Err(Error::InvalidArgument(
                        "mcmc.refine_every must be >= 1".into(),
                    ));
                }
                non_negative("mcmc.noise_lr", m.noise_lr)?;
                non_negative("mcmc.opacity_reg", m.opacity_reg)?;
                non_negative("mcmc.scale_reg", m.scale_reg)?;
                if !(0.0..0.5).contains(&m.min_opacity) {
                    return Err(Error::InvalidArgument(format!(
                        "mcmc.min_opacity must be in [0, 0.5), got {}",
                        m.min_opacity
                    )));
                }
            }
        }
        self.render.validate()
    }

    /// The means learning rate at (0-based) step `step`: lr * scene_scale * final^(step/steps).
    pub fn lr_means(&self, step: u32) -> f32 {
        let frac = step.min(self.steps) as f64 / self.steps as f64;
        (self.lr.means as f64 * self.scene_scale as f64 * (self.lr.means_final as f64).powf(frac))
            as f32
    }

    /// Learning rates of the six arrays at `step` (order of [`super::params::NAMES`]).
    pub fn lrs(&self, step: u32) -> [f32; GROUPS] {
        let l = &self.lr;
        [
            self.lr_means(step),
            l.quats,
            l.scales,
            l.opacities,
            l.sh0,
            l.sh_rest,
        ]
    }

    /// The SH degree rendered and trained at `step`.
    pub fn sh_degree_at(&self, step: u32) -> u8 {
        ((step / self.sh_degree_interval).min(self.sh_degree as u32)) as u8
    }
}
