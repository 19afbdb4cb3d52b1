//! One training step, and the state it advances.
//!
//! A step (0-based index s): pick view order(s / V)[s % V] (a fresh permutation of the V
//! training views per epoch); render it at SH degree min(s / interval, degree); loss and image
//! gradient; backward (densification statistics while the default strategy still refines); the
//! MCMC regularisers; Adam with the step's learning rates (t = s + 1); then the strategy. Every
//! stage is deterministic for any thread count, so a run is a pure function of its config,
//! data, initial scene and seed, and a run restored from a checkpoint continues bit for bit.
use std::time::Instant;

use rayon::prelude::*;

use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::raster::diff::{DensifyStats, DepthKind, DiffOptions, Gradients, ImageGrads, Workspace};
use crate::raster::{render_into, RenderOptions};
use crate::scene::{sh_rest_count, Scene, SceneView};

use super::checkpoint::Checkpoint;
use super::config::{FitConfig, Strategy};
use super::densify::{self, RefineReport};
use super::loss::{psnr, LossWorkspace};
use super::mcmc;
use super::params::{Params, GROUPS, OPACITY, SCALES};
use super::rand::epoch_order;

/// A posed image: the camera and its uint8 RGB pixels (H*W*3, row-major), with an optional
/// mask (H*W, row-major; 0: the pixel is left out of the loss and the held-out metrics).
#[derive(Debug, Clone)]
pub struct View {
    pub cam: Camera,
    pub image: Vec<u8>,
    pub mask: Option<Vec<u8>>,
}

impl View {
    /// Check the image holds exactly the camera's W*H*3 values.
    pub fn new(cam: Camera, image: Vec<u8>) -> Result<Self> {
        cam.validate()?;
        let want = cam.width as usize * cam.height as usize * 3;
        if image.len() != want {
            return Err(Error::InvalidArgument(format!(
                "image holds {} values, the camera's {}x{} needs {want}",
                image.len(),
                cam.width,
                cam.height
            )));
        }
        Ok(View {
            cam,
            image,
            mask: None,
        })
    }

    /// The view with a mask of W*H values (0: ignored pixel); at least one pixel must count.
    pub fn with_mask(mut self, mask: Vec<u8>) -> Result<Self> {
        let want = self.cam.width as usize * self.cam.height as usize;
        if mask.len() != want {
            return Err(Error::InvalidArgument(format!(
                "mask holds {} values, the camera's {}x{} needs {want}",
                mask.len(),
                self.cam.width,
                self.cam.height
            )));
        }
        if mask.iter().all(|&m| m == 0) {
            return Err(Error::InvalidArgument(
                "the mask leaves no pixel (0 means ignored)".into(),
            ));
        }
        self.mask = Some(mask);
        Ok(self)
    }
}

/// Zero the masked pixels (mask 0) of each RGB buffer: masked pixels then add nothing to L1
/// and give zero gradient (the loss sees render * mask against target * mask, nerfstudio's
/// splatfacto rule).
fn apply_mask(mask: &[u8], bufs: &mut [&mut [f32]]) {
    for (i, &m) in mask.iter().enumerate() {
        if m == 0 {
            for b in bufs.iter_mut() {
                b[i * 3..i * 3 + 3].fill(0.0);
            }
        }
    }
}

/// Metrics over the kept pixels from metrics over the whole masked image (masked pixels zero
/// in both): MSE scales by N / N_kept, so PSNR drops by 10 log10(N / N_kept); SSIM removes the
/// masked pixels' map values, taken as 1 (exact for windows wholly inside the mask).
fn masked_metrics(psnr_all: f64, ssim_all: f64, mask: &[u8]) -> (f64, f64) {
    let n = mask.len() as f64;
    let kept = mask.iter().filter(|&&m| m != 0).count() as f64;
    (
        psnr_all - 10.0 * (n / kept).log10(),
        (ssim_all * n - (n - kept)) / kept,
    )
}

/// What one step did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StepRecord {
    /// Steps completed, this one included.
    pub step: u32,
    /// Index of the training view used.
    pub view: u32,
    pub loss: f64,
    pub l1: f64,
    pub ssim: f64,
    /// PSNR of this step's (unclamped) render against its image.
    pub psnr: f64,
    /// Gaussians after the step.
    pub gaussians: u32,
    pub sh_degree: u8,
    pub lr_means: f32,
    pub refine: RefineReport,
    /// Wall seconds: whole step, forward, loss, backward, Adam, strategy.
    pub seconds: f64,
    pub forward_s: f64,
    pub loss_s: f64,
    pub backward_s: f64,
    pub adam_s: f64,
    pub strategy_s: f64,
}

/// One held-out view's metrics.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct EvalView {
    pub psnr: f64,
    pub ssim: f64,
}

/// The optimiser's state and buffers.
pub struct Trainer {
    cfg: FitConfig,
    train: Vec<View>,
    eval: Vec<View>,
    params: Params,
    stats: DensifyStats,
    step: u32,
    order: Option<(u64, Vec<u32>)>,
    ws: Workspace,
    loss: LossWorkspace,
    grads: Gradients,
    /// The SH degree of the last backward into `grads` (None before the first).
    grads_degree: Option<u8>,
    /// Adam zeroed the gradients it read after the last backward (every array but the
    /// activated `scales` and `opacities`, which only the backward writes).
    adam_cleared: bool,
    rgb: Vec<f32>,
    alpha: Vec<f32>,
    target: Vec<f32>,
    v_rgb: Vec<f32>,
}

/// `scene`'s arrays with its SH bands cut or zero-padded to `degree`.
fn with_degree(scene: &SceneView<'_>, degree: u8) -> Scene {
    let mut s = scene.to_owned_scene();
    let (k0, k1) = (scene.sh_rest_k(), sh_rest_count(degree));
    if k0 != k1 {
        let n = scene.len();
        let mut rest = vec![0.0f32; n * k1 * 3];
        let k = k0.min(k1) * 3;
        for i in 0..n {
            rest[i * k1 * 3..i * k1 * 3 + k]
                .copy_from_slice(&scene.sh_rest[i * k0 * 3..i * k0 * 3 + k]);
        }
        s.sh_rest = rest;
        s.sh_degree = degree;
    }
    s
}

impl Trainer {
    /// A trainer at step 0 from an initial scene (its SH bands cut or zero-padded to the
    /// config's degree).
    pub fn new(
        cfg: FitConfig,
        train: Vec<View>,
        eval: Vec<View>,
        init: &SceneView<'_>,
    ) -> Result<Self> {
        cfg.validate()?;
        init.validate()?;
        if init.is_empty() {
            return Err(Error::InvalidArgument(
                "the initial scene has no Gaussians".into(),
            ));
        }
        let s = with_degree(init, cfg.sh_degree);
        let params = Params::from_view(&s.view());
        Self::with_params(cfg, train, eval, params, None, 0)
    }

    /// A trainer restored from a checkpoint (taken with the same config and data).
    pub fn restore(
        cfg: FitConfig,
        train: Vec<View>,
        eval: Vec<View>,
        ck: Checkpoint,
    ) -> Result<Self> {
        cfg.validate()?;
        if ck.params.sh_degree != cfg.sh_degree {
            return Err(Error::InvalidArgument(format!(
                "the checkpoint holds SH degree {}, the config asks for {}",
                ck.params.sh_degree, cfg.sh_degree
            )));
        }
        Self::with_params(cfg, train, eval, ck.params, Some(ck.stats), ck.step)
    }

    fn with_params(
        cfg: FitConfig,
        train: Vec<View>,
        eval: Vec<View>,
        params: Params,
        stats: Option<DensifyStats>,
        step: u32,
    ) -> Result<Self> {
        if train.is_empty() {
            return Err(Error::InvalidArgument("no training view was given".into()));
        }
        if params.is_empty() {
            return Err(Error::InvalidArgument("the scene has no Gaussians".into()));
        }
        let n = params.len();
        let stats = match stats {
            Some(s) if s.count.len() == n => s,
            _ => {
                let mut s = DensifyStats::default();
                s.reset(n);
                s
            }
        };
        let mut loss = LossWorkspace::default();
        loss.ssim.simd = cfg.render.simd;
        Ok(Trainer {
            cfg,
            train,
            eval,
            params,
            stats,
            step,
            order: None,
            ws: Workspace::default(),
            loss,
            grads: Gradients::default(),
            grads_degree: None,
            adam_cleared: false,
            rgb: Vec::new(),
            alpha: Vec::new(),
            target: Vec::new(),
            v_rgb: Vec::new(),
        })
    }

    pub fn config(&self) -> &FitConfig {
        &self.cfg
    }

    /// Steps completed.
    pub fn step(&self) -> u32 {
        self.step
    }

    pub fn params(&self) -> &Params {
        &self.params
    }

    pub fn len(&self) -> usize {
        self.params.len()
    }

    pub fn is_empty(&self) -> bool {
        self.params.is_empty()
    }

    pub fn train_views(&self) -> &[View] {
        &self.train
    }

    pub fn eval_views(&self) -> &[View] {
        &self.eval
    }

    /// The current scene (stored parameters).
    pub fn scene(&self) -> Scene {
        self.params.view().to_owned_scene()
    }

    /// The state a checkpoint stores.
    pub fn checkpoint(&self, fingerprint: &[u8]) -> Checkpoint {
        Checkpoint {
            fingerprint: fingerprint.to_vec(),
            step: self.step,
            params: self.params.clone(),
            stats: self.stats.clone(),
        }
    }

    /// The training view of (0-based) step `s`.
    pub fn view_at(&mut self, s: u32) -> usize {
        let v = self.train.len();
        let epoch = s as u64 / v as u64;
        if self.order.as_ref().is_none_or(|(e, _)| *e != epoch) {
            self.order = Some((epoch, epoch_order(self.cfg.seed, epoch, v)));
        }
        match &self.order {
            Some((_, o)) => o[s as usize % v] as usize,
            None => 0,
        }
    }

    /// Render options of the current step (the SH degree in use).
    fn render_options(&self) -> RenderOptions {
        RenderOptions {
            sh_degree: Some(self.cfg.sh_degree_at(self.step)),
            ..self.cfg.render
        }
    }

    /// Run one step.
    pub fn step_once(&mut self) -> Result<StepRecord> {
        let t0 = Instant::now();
        let s = self.step;
        let vi = self.view_at(s);
        let ropts = self.render_options();
        let degree = ropts.sh_degree.unwrap_or(0);
        let absgrad =
            matches!(&self.cfg.strategy, Strategy::Default(d) if d.absgrad && s < d.refine_stop);
        let opts = DiffOptions {
            render: ropts,
            // the fit has no depth loss: its forward sums no depth
            depth: DepthKind::None,
            absgrad,
            ..DiffOptions::default()
        };
        let view = &self.train[vi];
        let (w, h) = (view.cam.width as usize, view.cam.height as usize);
        let npix = w * h;
        for (b, len) in [
            (&mut self.rgb, npix * 3),
            (&mut self.alpha, npix),
            (&mut self.target, npix * 3),
            (&mut self.v_rgb, npix * 3),
        ] {
            b.resize(len, 0.0);
        }
        self.ws.forward(
            &self.params.view(),
            &view.cam,
            &opts,
            None,
            &mut self.rgb,
            &mut [],
            &mut self.alpha,
        )?;
        let t1 = Instant::now();
        self.target
            .par_chunks_mut((w * 3).max(1))
            .zip(view.image.par_chunks((w * 3).max(1)))
            .for_each(|(t, p)| {
                for (t, &p) in t.iter_mut().zip(p) {
                    *t = p as f32 * (1.0 / 255.0);
                }
            });
        if let Some(m) = &view.mask {
            apply_mask(m, &mut [&mut self.rgb, &mut self.target]);
        }
        let mut terms = self.loss.loss_and_grad(
            &self.rgb,
            &self.target,
            w,
            h,
            self.cfg.ssim_lambda,
            &mut self.v_rgb,
        );
        if let Some(m) = &view.mask {
            apply_mask(m, &mut [&mut self.v_rgb]);
        }
        let t2 = Instant::now();
        let n = self.params.len();
        // the last step's backward wrote SH bands up to its degree only
        let written = self.grads_degree.replace(degree);
        let k = self.params.view().sh_rest_k();
        let g = &mut self.grads;
        let same = g.means.len() == n * 3 && g.sh_rest.len() == n * k * 3 && g.colors.is_empty();
        if std::mem::take(&mut self.adam_cleared) && same {
            // Adam zeroed what it read (in its pass: no separate clear of those arrays); the
            // activated gradients it does not read are cleared here
            for v in [&mut g.scales, &mut g.opacities] {
                v.par_chunks_mut(1 << 16).for_each(|c| c.fill(0.0));
            }
        } else {
            g.reset_since(n, k, false, written);
        }
        let densify = match &self.cfg.strategy {
            Strategy::Default(d) if s < d.refine_stop => Some(&mut self.stats),
            _ => None,
        };
        let grads = ImageGrads {
            rgb: Some(&self.v_rgb),
            // the fit has no background parameter
            skip_background: true,
            ..ImageGrads::default()
        };
        self.ws.backward(
            &self.params.view(),
            None,
            &grads,
            &mut self.grads,
            None,
            densify,
        )?;
        if let Strategy::Mcmc(m) = &self.cfg.strategy {
            let g = &mut self.grads;
            terms.loss +=
                mcmc::add_regularisers(m, &self.params, &mut g.opacity_logits, &mut g.log_scales);
        }
        let t3 = Instant::now();
        let g = &mut self.grads;
        let grads: [&mut [f32]; GROUPS] = [
            &mut g.means,
            &mut g.quats,
            &mut g.log_scales,
            &mut g.opacity_logits,
            &mut g.sh0,
            &mut g.sh_rest,
        ];
        self.params
            .adam_step(grads, self.cfg.lrs(s), s as u64 + 1, &self.cfg.adam, degree);
        self.adam_cleared = true;
        let t4 = Instant::now();
        let refine = match &self.cfg.strategy {
            Strategy::Default(d) => densify::post_step(
                d,
                &mut self.params,
                &mut self.stats,
                s,
                self.cfg.scene_scale,
                self.cfg.seed,
            ),
            Strategy::Mcmc(m) => {
                let r = mcmc::post_step(
                    m,
                    &mut self.params,
                    s,
                    self.cfg.lr_means(s + 1),
                    self.cfg.seed,
                );
                if self.stats.count.len() != self.params.len() {
                    self.stats.reset(self.params.len());
                }
                r
            }
        };
        let t5 = Instant::now();
        self.step += 1;
        Ok(StepRecord {
            step: self.step,
            view: vi as u32,
            loss: terms.loss,
            l1: terms.l1,
            ssim: terms.ssim,
            psnr: psnr(terms.mse),
            gaussians: self.params.len() as u32,
            sh_degree: degree,
            lr_means: self.cfg.lr_means(s),
            refine,
            seconds: (t5 - t0).as_secs_f64(),
            forward_s: (t1 - t0).as_secs_f64(),
            loss_s: (t2 - t1).as_secs_f64(),
            backward_s: (t3 - t2).as_secs_f64(),
            adam_s: (t4 - t3).as_secs_f64(),
            strategy_s: (t5 - t4).as_secs_f64(),
        })
    }

    /// Render `cam` with the current parameters (the SH degree in use).
    pub fn render(&self, cam: &Camera) -> Result<Vec<f32>> {
        let npix = cam.width as usize * cam.height as usize;
        let (mut rgb, mut depth, mut alpha) =
            (vec![0.0; npix * 3], vec![0.0; npix], vec![0.0; npix]);
        render_into(
            &self.params.view(),
            cam,
            &self.render_options(),
            &mut rgb,
            &mut depth,
            &mut alpha,
        )?;
        Ok(rgb)
    }

    /// Render every held-out view and score it (PSNR and SSIM of the render clamped to
    /// [0, 1]); `each` sees (view index, metrics, render).
    pub fn evaluate(
        &mut self,
        mut each: impl FnMut(usize, &EvalView, &[f32]),
    ) -> Result<Vec<EvalView>> {
        let mut out = Vec::with_capacity(self.eval.len());
        let mut target = Vec::new();
        for i in 0..self.eval.len() {
            let rgb = self.render(&self.eval[i].cam)?;
            let v = &self.eval[i];
            target.clear();
            target.extend(v.image.iter().map(|&p| p as f32 * (1.0 / 255.0)));
            let (w, h) = (v.cam.width as usize, v.cam.height as usize);
            let (p, s) = match &v.mask {
                None => self.loss.metrics(&rgb, &target, w, h),
                Some(m) => {
                    let mut masked = rgb.clone();
                    apply_mask(m, &mut [&mut masked, &mut target]);
                    let (p, s) = self.loss.metrics(&masked, &target, w, h);
                    masked_metrics(p, s, m)
                }
            };
            let e = EvalView { psnr: p, ssim: s };
            each(i, &e, &rgb);
            out.push(e);
        }
        Ok(out)
    }

    /// Mean opacity and mean largest scale (diagnostics).
    pub fn summary(&self) -> (f64, f64) {
        let n = self.params.len().max(1) as f64;
        let o: f64 = self.params.groups[OPACITY]
            .value
            .iter()
            .map(|&l| densify::sigmoid(l) as f64)
            .sum();
        let s: f64 = self.params.groups[SCALES]
            .value
            .chunks(3)
            .map(|c| c[0].max(c[1]).max(c[2]).exp() as f64)
            .sum();
        (o / n, s / n)
    }
}

#[cfg(test)]
mod mask_tests {
    use super::{apply_mask, masked_metrics};

    #[test]
    fn masked_pixels_are_zeroed_and_psnr_counts_only_kept_pixels() {
        let mask = [1u8, 0, 1, 0];
        let mut a = vec![0.5f32; 12];
        let mut b = vec![0.25f32; 12];
        apply_mask(&mask, &mut [&mut a, &mut b]);
        assert_eq!(&a[3..6], &[0.0, 0.0, 0.0]);
        assert_eq!(&b[9..12], &[0.0, 0.0, 0.0]);
        assert_eq!(&a[0..3], &[0.5, 0.5, 0.5]);
        // MSE over all 4 pixels is half the MSE over the 2 kept ones: 10 log10(2) dB less
        let (p, s) = masked_metrics(20.0, 0.9, &mask);
        assert!((p - (20.0 - 10.0 * 2f64.log10())).abs() < 1e-12);
        assert!((s - 0.8).abs() < 1e-12);
    }
}
