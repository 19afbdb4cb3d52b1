//! The differentiable rasterizer's options, inputs and outputs: [`DiffOptions`] (with
//! [`DepthKind`]), the image gradients [`ImageGrads`] the backward takes, the parameter
//! [`Gradients`] it adds to, one view's intermediate [`ViewGrads`] and the [`BackwardStats`].
use rayon::prelude::*;

use crate::raster::RenderOptions;

/// Which depth the depth image holds (and its gradient refers to).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DepthKind {
    /// D / max(alpha, 1e-10): the expected camera z, as `render` writes it.
    #[default]
    Expected,
    /// D = sum of w_i z_i.
    Accumulated,
    /// No depth: the forward skips the depth sums and leaves the depth image as it is (it may
    /// be empty), and the backward takes no depth gradient. Rgb, alpha and the gradients have
    /// the bits of the other kinds (with no depth gradient). The fit's trainer uses it.
    None,
}

/// Options of the differentiable forward.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DiffOptions {
    pub render: RenderOptions,
    pub depth: DepthKind,
    /// Most bytes of per-intersection slots held at once (bands of tile rows are processed in
    /// turn when a frame needs more; a band holds at least one tile row).
    pub slot_budget: usize,
    /// Also sum |dL/dmean2d| per pixel (gsplat's absgrad, for AbsGS densification); about 15%
    /// of the blend backward.
    pub absgrad: bool,
}

impl Default for DiffOptions {
    fn default() -> Self {
        DiffOptions {
            render: RenderOptions::default(),
            depth: DepthKind::Expected,
            slot_budget: 256 << 20,
            absgrad: false,
        }
    }
}

/// Gradients of the images: `rgb` (H*W*3), `depth` and `alpha` (H*W), row-major; `None` is a
/// zero gradient.
#[derive(Debug, Clone, Copy, Default)]
pub struct ImageGrads<'a> {
    pub rgb: Option<&'a [f32]>,
    pub depth: Option<&'a [f32]>,
    pub alpha: Option<&'a [f32]>,
    /// Leave [`Gradients::background`] as it is: skips a serial float64 sum over the pixels,
    /// for callers with no background parameter (the fit's trainer).
    pub skip_background: bool,
}

/// Gradients of the stored parameters (SPEC §1 layout), accumulated (+=) by every backward
/// call, so several cameras add up in call order. Also dL/d(exp(log_scales)) and
/// dL/d(sigmoid(logit)) (gsplat's activated parameters), and dL/d(colours) for given colours.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Gradients {
    pub means: Vec<f32>,
    pub quats: Vec<f32>,
    pub log_scales: Vec<f32>,
    pub opacity_logits: Vec<f32>,
    pub sh0: Vec<f32>,
    pub sh_rest: Vec<f32>,
    pub scales: Vec<f32>,
    pub opacities: Vec<f32>,
    /// (N,3) when the forward took given colours, else empty.
    pub colors: Vec<f32>,
    pub background: [f32; 3],
}

impl Gradients {
    /// Zero-sized for `n` Gaussians with `sh_rest_k` higher SH bands (keeps the allocations).
    pub fn reset(&mut self, n: usize, sh_rest_k: usize, given_colors: bool) {
        let z = |v: &mut Vec<f32>, len: usize| {
            v.clear();
            v.resize(len, 0.0);
        };
        z(&mut self.means, n * 3);
        z(&mut self.quats, n * 4);
        z(&mut self.log_scales, n * 3);
        z(&mut self.opacity_logits, n);
        z(&mut self.sh0, n * 3);
        z(&mut self.sh_rest, n * sh_rest_k * 3);
        z(&mut self.scales, n * 3);
        z(&mut self.opacities, n);
        z(&mut self.colors, if given_colors { n * 3 } else { 0 });
        self.background = [0.0; 3];
    }

    /// [`Gradients::reset`] for buffers that were reset for the same sizes and since then
    /// received only backward passes at SH degree `degree` or lower (`None`: unknown): the
    /// higher SH bands are still zero and are left as they are, so an optimiser whose degree
    /// grows step by step does not clear all of `sh_rest` every step (45 of a Gaussian's 59
    /// floats with 3 bands stored and degree 0 in use). Other sizes get a full reset.
    pub fn reset_since(
        &mut self,
        n: usize,
        sh_rest_k: usize,
        given_colors: bool,
        degree: Option<u8>,
    ) {
        let same = self.means.len() == n * 3
            && self.sh_rest.len() == n * sh_rest_k * 3
            && self.colors.len() == if given_colors { n * 3 } else { 0 };
        let Some(d) = degree.filter(|_| same) else {
            return self.reset(n, sh_rest_k, given_colors);
        };
        for v in [
            &mut self.means,
            &mut self.quats,
            &mut self.log_scales,
            &mut self.opacity_logits,
            &mut self.sh0,
            &mut self.scales,
            &mut self.opacities,
            &mut self.colors,
        ] {
            par_zero(v);
        }
        self.background = [0.0; 3];
        let used = ((d as usize + 1) * (d as usize + 1) - 1).min(sh_rest_k) * 3;
        if used == sh_rest_k * 3 {
            par_zero(&mut self.sh_rest);
        } else if used > 0 {
            let per = sh_rest_k * 3;
            self.sh_rest
                .par_chunks_mut(per * ZERO_CHUNK.div_ceil(per))
                .for_each(|c| {
                    for g in c.chunks_exact_mut(per) {
                        g[..used].fill(0.0);
                    }
                });
        }
    }
}

/// Floats per task of the parallel clears (256 KiB).
const ZERO_CHUNK: usize = 1 << 16;

/// Zeroes `v` in parallel: a fit step clears tens of MB of gradients, which one thread's
/// memset makes a serial part of every step.
fn par_zero(v: &mut [f32]) {
    if v.len() <= ZERO_CHUNK {
        v.fill(0.0);
    } else {
        v.par_chunks_mut(ZERO_CHUNK).for_each(|c| c.fill(0.0));
    }
}

/// One view's intermediate gradients per Gaussian (gsplat's `rasterize_to_pixels` VJP outputs:
/// dL/d means2d, its absolute per-pixel sum, conics, colours, opacities after compensation,
/// camera depths through the depth channel). Overwritten by each backward; zero for Gaussians
/// the view culled.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ViewGrads {
    pub means2d: Vec<f32>,
    pub means2d_abs: Vec<f32>,
    pub conics: Vec<f32>,
    pub colors: Vec<f32>,
    pub opacities: Vec<f32>,
    pub depths: Vec<f32>,
    /// dL/d(world-to-camera matrix), 4x4 row-major, when set to `Some` before the backward
    /// (gsplat's `v_viewmats`, camera-centre path through the matrix inverse included); summed
    /// over Gaussians in index order in float64, so it has the same bits for any thread count.
    pub viewmat: Option<[f64; 16]>,
}

impl ViewGrads {
    pub(super) fn reset(&mut self, n: usize) {
        for (v, k) in [
            (&mut self.means2d, 2),
            (&mut self.means2d_abs, 2),
            (&mut self.conics, 3),
            (&mut self.colors, 3),
            (&mut self.opacities, 1),
            (&mut self.depths, 1),
        ] {
            v.clear();
            v.resize(n * k, 0.0);
        }
        if let Some(m) = self.viewmat.as_mut() {
            *m = [0.0; 16];
        }
    }
}

/// What a backward did: counts and stage wall times in seconds.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct BackwardStats {
    /// Gaussian-pixel evaluations of the blend backward.
    pub evaluations: u64,
    pub intersections: u64,
    /// Bands of tile rows the frame was processed in.
    pub bands: u32,
    /// Bytes of the largest band's slots.
    pub slot_bytes: u64,
    /// Blend backward (tile inputs, kernels, slot writes).
    pub blend_s: f64,
    /// Per-Gaussian sums of the slots.
    pub reduce_s: f64,
    /// Per-Gaussian projection, SH and activation backward.
    pub project_s: f64,
}
