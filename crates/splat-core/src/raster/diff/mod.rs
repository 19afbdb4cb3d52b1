//! The differentiable rasterizer: a forward pass that keeps what the backward needs, and the
//! backward pass (gradients of the stored parameters from gradients of the images), both
//! multithreaded and bit-identical for any thread count.
//!
//! ```text
//! let mut ws = Workspace::default();            // reuse across steps: no per-step allocation
//! let mut grads = Gradients::default();
//! loop {
//!     ws.forward(&scene.view(), &cam, &opts, None, &mut rgb, &mut depth, &mut alpha)?;
//!     // ... loss and its image gradients v_rgb, v_depth, v_alpha ...
//!     grads.reset(scene.len(), scene.sh_rest_k(), false);
//!     ws.backward(&scene.view(), None, &ImageGrads { rgb: Some(&v_rgb), .. }, &mut grads,
//!                 None, Some(&mut densify))?;
//! }
//! ```
//!
//! Determinism: each (tile, Gaussian) intersection writes its gradient sums into a slot of its
//! own; each Gaussian then adds its slots in a fixed order (its tiles in row-major order). No
//! float is reduced across threads, so gradients are the same bits for 1 or N threads.
//! The slots lie in tile-list order; the sums stream through them once per binning chunk (whose
//! Gaussians' sums that chunk's task owns), so each Gaussian meets its tiles in row-major order.
//! Memory: 48 bytes per slot and a byte for its written flag; the image is processed in bands of tile rows whose slots fit
//! [`DiffOptions::slot_budget`] (the sums do not depend on the banding), plus 48 bytes per
//! visible Gaussian for the running sums.
use std::time::Instant;

use rayon::prelude::*;

use super::blend::{self, BlendParams, DepthOut, TileOut, LANES};
use super::project::{self, Projection, Projector, Splat};
use super::share::FrameColours;
use super::sort::{self, TileBins};
use super::{RenderOptions, RenderStats};
use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::scene::SceneView;

mod blend_bwd;
#[cfg(target_arch = "x86_64")]
mod blend_bwd_avx2;
#[cfg(target_arch = "x86_64")]
mod blend_bwd_avx512;
mod densify;
mod gauss_block;
#[cfg(target_arch = "x86_64")]
mod gauss_block_avx512;
mod gauss_bwd;
mod sh_bwd;
#[cfg(test)]
mod tests;

pub use densify::DensifyStats;

/// The per-intersection gradient sums ("slots"): layout of one slot's floats.
pub(crate) mod slot {
    /// dL/d(colour) of the r, g, b and depth channels: sum of w g_k (C0 + k).
    pub const C0: usize = 0;
    /// With u = e dL/dalpha per pixel (e = opacity exp(-sigma), so dL/dsigma = -u):
    /// sum u, u dx, u dy, u dx^2, u dx dy, u dy^2 (dx, dy: mean minus pixel centre).
    pub const V0: usize = 4;
    pub const VDX: usize = 5;
    pub const VDY: usize = 6;
    pub const VDX2: usize = 7;
    pub const VDXDY: usize = 8;
    pub const VDY2: usize = 9;
    /// sum |dL/dmean2d| per pixel, per axis (gsplat's absgrad; zero unless asked for).
    pub const ABSX: usize = 10;
    pub const ABSY: usize = 11;
    pub const LEN: usize = 12;
}

/// A slot's bytes.
pub const SLOT_BYTES: usize = slot::LEN * 4;

/// One splat's running sums of its slots: the `slot::LEN` values padded to 16 floats and
/// aligned to 64 bytes, so that each random access of the slot sums (`reduce_band`) and of the
/// per-Gaussian pass touches one cache line (a 48-byte row straddles two lines half the time).
/// The padding stays +0.0.
#[derive(Debug, Clone, Copy, Default)]
#[repr(C, align(64))]
pub(crate) struct AccRow(pub(crate) [f32; 16]);

impl AccRow {
    /// The summed slot values.
    #[inline(always)]
    pub(crate) fn sums(&self) -> &[f32; slot::LEN] {
        self.0[..slot::LEN].try_into().expect("16 >= slot::LEN")
    }

    /// Add one slot's values, element by element, to the sums (`keep`) or to +0.0 (the
    /// splat's first slot: its sums' memory is stale). The plain float additions, 4 lanes at
    /// a time where the target has SSE, so the bits are those of sums that start at +0.0.
    #[inline(always)]
    fn add(&mut self, s: &[f32; slot::LEN], keep: bool) {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: SSE is part of x86_64; every access lies inside `self.0` (64-byte aligned,
        // so the aligned loads hold) or `s`.
        unsafe {
            use std::arch::x86_64::*;
            // all ones (keep the sums) or +0.0
            let m = _mm_castsi128_ps(_mm_set1_epi32(-(keep as i32)));
            let a = self.0.as_mut_ptr();
            for q in 0..slot::LEN / 4 {
                let old = _mm_and_ps(_mm_load_ps(a.add(4 * q)), m);
                let v = _mm_add_ps(old, _mm_loadu_ps(s.as_ptr().add(4 * q)));
                _mm_store_ps(a.add(4 * q), v);
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        for (a, v) in self.0.iter_mut().zip(s) {
            *a = if keep { *a } else { 0.0 } + v;
        }
    }
}

/// The summed slots by sorted position as the per-Gaussian pass reads them: the rows, and
/// which of them hold sums (1 once `reduce_band` added a slot; the others read as zeros).
#[derive(Clone, Copy)]
pub(crate) struct Sums<'a> {
    pub(crate) acc: &'a [AccRow],
    pub(crate) touched: &'a [u8],
}

impl Sums<'_> {
    /// Sorted splat p's sums (zeros where no slot was added).
    #[inline(always)]
    pub(crate) fn get(&self, p: usize) -> &[f32; slot::LEN] {
        const ZERO: [f32; slot::LEN] = [0.0; slot::LEN];
        if self.touched[p] != 0 {
            self.acc[p].sums()
        } else {
            &ZERO
        }
    }
}

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
    fn reset(&mut self, n: usize) {
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

/// What the forward saved for the backward.
#[derive(Debug, Clone, Copy)]
struct Saved {
    cam: Camera,
    opts: DiffOptions,
    blend: BlendParams,
    degree: u8,
    n: usize,
    given_colors: bool,
}

/// Buffers of the differentiable rasterizer, reused across calls, and the state one forward
/// leaves for its backward. About 64 + 4 + 4 bytes per visible Gaussian and 4 bytes per
/// intersection (depth-sorted splats, their ids and sorted positions, the tile lists), 20 bytes per
/// pixel (final transmittance, colour and depth sums), and during the backward 49 bytes per
/// intersection of a band (slot and written flag) plus 65 bytes per visible Gaussian (its
/// 64-byte row of sums and a flag).
#[derive(Default)]
pub struct Workspace {
    saved: Option<Saved>,
    parts: Vec<Vec<Splat>>,
    part_ids: Vec<Vec<u32>>,
    keys: Vec<(u32, u32)>,
    tmp: Vec<(u32, u32)>,
    sorted: Vec<Splat>,
    ids: Vec<u32>,
    bins: TileBins,
    tiles: Vec<TileOut>,
    /// First visible rank of each projection chunk: visible Gaussians in index order are
    /// `parts` concatenated, rank = part_off[c] + j.
    part_off: Vec<usize>,
    /// Sorted position of each visible rank (the inverse of the depth order).
    pos: Vec<u32>,
    /// Per binning chunk, for the current band: its first slot and its first entry.
    band_base: Vec<usize>,
    band_lo: Vec<u32>,
    /// The band's slots, in tile-list order (chunk by chunk, tile by tile).
    slots: Vec<[f32; slot::LEN]>,
    /// Per slot of the band: 1 when the tile pass wrote it, 0 when its entry has no sums
    /// (`SlotSink::zero`: the slot is neither written nor read).
    written: Vec<u8>,
    /// Summed slots per sorted splat, valid where `touched` is 1 (never zeroed: a splat's
    /// first slot is added to +0.0 instead, see `AccRow::add`).
    acc: Vec<AccRow>,
    /// Per sorted splat: 1 once `reduce_band` added a slot to its sums (zeroed per chunk by
    /// the first band's reduction).
    touched: Vec<u8>,
    /// exp(log_scales) for the per-Gaussian pass.
    scales: Vec<f32>,
}

impl Workspace {
    /// Render `scene` from `cam` into `rgb` (H*W*3), `depth` and `alpha` (H*W) exactly as
    /// [`super::render_into`] does (same bits; `opts.depth` picks the depth written; with
    /// [`DepthKind::None`] `depth` is not written and may be empty), keeping
    /// the state the next [`Workspace::backward`] needs. `colors` (N*3), when given, replace
    /// the SH colours (gsplat's `sh_degree=None` with post-activation colours).
    pub fn forward(
        &mut self,
        scene: &SceneView<'_>,
        cam: &Camera,
        opts: &DiffOptions,
        colors: Option<&[f32]>,
        rgb: &mut [f32],
        depth: &mut [f32],
        alpha: &mut [f32],
    ) -> Result<RenderStats> {
        self.saved = None;
        cam.validate()?;
        opts.render.validate()?;
        scene.validate()?;
        let npix = cam.width as usize * cam.height as usize;
        let depth_ok = depth.len() == npix || (opts.depth == DepthKind::None && depth.is_empty());
        if rgb.len() != npix * 3 || !depth_ok || alpha.len() != npix {
            return Err(Error::InvalidArgument(format!(
                "output buffers hold {}, {} and {} values, expected {} for a {}x{} image",
                rgb.len(),
                depth.len(),
                alpha.len(),
                npix * 3,
                cam.width,
                cam.height
            )));
        }
        if let Some(c) = colors {
            check_colors(c, scene.len())?;
        }
        let degree = opts.render.effective_sh_degree(scene.sh_degree)?;
        if scene.len() > u32::MAX as usize {
            return Err(Error::InvalidArgument(format!(
                "a scene of {} Gaussians exceeds the rasterizer's limit of 2^32",
                scene.len()
            )));
        }
        let mut stats = RenderStats {
            frames: 1,
            gaussians: scene.len() as u64,
            ..Default::default()
        };
        let t0 = Instant::now();
        let proj = Projector::new(cam, &opts.render, degree);
        let chunks = project::project_visible_into(
            scene,
            &proj,
            FrameColours::Off,
            &mut self.parts,
            Some(&mut self.part_ids),
        );
        // (the backward walks every part: none left from a larger scene)
        self.parts.truncate(chunks);
        self.part_ids.truncate(chunks);
        let t1 = Instant::now();
        sort::sort_by_depth_with_ids(
            &self.parts,
            &self.part_ids,
            &mut self.keys,
            &mut self.tmp,
            &mut self.sorted,
            &mut self.ids,
        );
        stats.visible = self.sorted.len() as u64;
        self.part_off.clear();
        let mut off = 0;
        for part in &self.parts {
            self.part_off.push(off);
            off += part.len();
        }
        self.pos.clear();
        self.pos.resize(self.sorted.len(), 0);
        for (p, &(_, payload)) in self.keys.iter().enumerate() {
            let c = (payload >> project::PROJECT_CHUNK_BITS) as usize;
            let j = (payload & ((1 << project::PROJECT_CHUNK_BITS) - 1)) as usize;
            self.pos[self.part_off[c] + j] = p as u32;
        }
        if let Some(c) = colors {
            self.sorted
                .par_iter_mut()
                .zip(self.ids.par_iter())
                .with_min_len(4096)
                .for_each(|(s, &i)| {
                    let i = i as usize;
                    s.rgb = [c[i * 3], c[i * 3 + 1], c[i * 3 + 2]];
                });
        }
        let t2 = Instant::now();
        let (tiles_x, tiles_y) = cam.tiles();
        self.bins.rebuild(&self.sorted, tiles_x, tiles_y)?;
        stats.intersections = self.bins.intersections();
        let t3 = Instant::now();
        let blend = BlendParams::of(cam, &opts.render);
        self.tiles
            .resize_with((tiles_x * tiles_y) as usize, TileOut::default);
        let counts = blend::blend_frame_saving(
            &self.sorted,
            &self.bins,
            &blend,
            rgb,
            depth,
            alpha,
            &mut self.tiles,
            match opts.depth {
                DepthKind::Expected => DepthOut::Expected,
                DepthKind::Accumulated => DepthOut::Accumulated,
                DepthKind::None => DepthOut::Skip,
            },
        );
        stats.evaluations = counts.evals;
        stats.useful = counts.useful;
        let t4 = Instant::now();
        stats.project_s = (t1 - t0).as_secs_f64();
        stats.sort_s = (t2 - t1).as_secs_f64();
        stats.bin_s = (t3 - t2).as_secs_f64();
        stats.blend_s = (t4 - t3).as_secs_f64();
        self.saved = Some(Saved {
            cam: *cam,
            opts: *opts,
            blend,
            degree,
            n: scene.len(),
            given_colors: colors.is_some(),
        });
        Ok(stats)
    }

    /// Backward of the last [`Workspace::forward`]: add dL/d(parameters) to `out` (sized by
    /// [`Gradients::reset`] for this scene), write this view's intermediate gradients to `view`
    /// and add the densification statistics to `densify`. `scene` and `colors` must be the
    /// forward's.
    pub fn backward(
        &mut self,
        scene: &SceneView<'_>,
        colors: Option<&[f32]>,
        grads: &ImageGrads<'_>,
        out: &mut Gradients,
        view: Option<&mut ViewGrads>,
        densify: Option<&mut DensifyStats>,
    ) -> Result<BackwardStats> {
        let sv = self.saved.ok_or_else(|| {
            Error::InvalidArgument("backward needs a forward on this workspace first".into())
        })?;
        scene.validate()?;
        let n = scene.len();
        if n != sv.n || colors.is_some() != sv.given_colors {
            return Err(Error::InvalidArgument(format!(
                "backward got {n} Gaussians{}, the forward {}{}",
                if colors.is_some() {
                    " with colours"
                } else {
                    ""
                },
                sv.n,
                if sv.given_colors { " with colours" } else { "" },
            )));
        }
        if let Some(c) = colors {
            check_colors(c, n)?;
        }
        if grads.depth.is_some() && sv.opts.depth == DepthKind::None {
            return Err(Error::InvalidArgument(
                "a depth gradient was given, but the forward wrote no depth (DepthKind::None)"
                    .into(),
            ));
        }
        let npix = sv.cam.width as usize * sv.cam.height as usize;
        for (name, g, per) in [
            ("rgb", grads.rgb, 3),
            ("depth", grads.depth, 1),
            ("alpha", grads.alpha, 1),
        ] {
            if let Some(g) = g {
                if g.len() != npix * per {
                    return Err(Error::InvalidArgument(format!(
                        "the {name} gradient holds {} values, expected {} for a {}x{} image",
                        g.len(),
                        npix * per,
                        sv.cam.width,
                        sv.cam.height
                    )));
                }
            }
        }
        let k = scene.sh_rest_k();
        let want = [
            (out.means.len(), n * 3),
            (out.quats.len(), n * 4),
            (out.log_scales.len(), n * 3),
            (out.opacity_logits.len(), n),
            (out.sh0.len(), n * 3),
            (out.sh_rest.len(), n * k * 3),
            (out.scales.len(), n * 3),
            (out.opacities.len(), n),
            (out.colors.len(), if sv.given_colors { n * 3 } else { 0 }),
        ];
        if want.iter().any(|(a, b)| a != b) {
            return Err(Error::InvalidArgument(
                "the gradient buffers do not match the scene: call Gradients::reset first".into(),
            ));
        }
        if let Some(d) = &densify {
            d.check(n)?;
        }
        let mut stats = BackwardStats {
            intersections: self.bins.intersections(),
            ..Default::default()
        };

        // ---- blend backward, band by band, and the fixed-order per-Gaussian sums
        let visible = self.sorted.len();
        // the sums are not zeroed: the first band's reduction clears each chunk's touched
        // flags in its task, and a splat's first slot is added to +0.0
        self.acc.resize(visible, AccRow::default());
        self.touched.resize(visible, 0);
        let bands = self.bands(sv.opts.slot_budget);
        stats.bands = bands.len() as u32;
        if bands.is_empty() {
            self.touched.fill(0);
        }
        let mut v_bg = [0.0f64; 3];
        for (b, &(r0, r1)) in bands.iter().enumerate() {
            let t0 = Instant::now();
            let total = self.band_layout(r0, r1);
            stats.slot_bytes = stats.slot_bytes.max(total as u64 * SLOT_BYTES as u64);
            // no zeroing: the tile pass writes every slot of the band (TileSink::finish)
            if self.slots.len() < total {
                self.slots.resize(total, [0.0; slot::LEN]);
            }
            if self.written.len() < total {
                self.written.resize(total, 0);
            }
            let (evals, bg) = self.blend_band(&sv, grads, r0, r1);
            stats.evaluations += evals;
            for c in 0..3 {
                v_bg[c] += bg[c];
            }
            let t1 = Instant::now();
            self.reduce_band(r0, r1, b == 0);
            stats.blend_s += (t1 - t0).as_secs_f64();
            stats.reduce_s += t1.elapsed().as_secs_f64();
        }
        for c in 0..3 {
            out.background[c] += v_bg[c] as f32;
        }

        // ---- per Gaussian: projection, SH and activations
        let t0 = Instant::now();
        let proj = Projector::new(&sv.cam, &sv.opts.render, sv.degree);
        gauss_bwd::scales_into(scene.log_scales, &mut self.scales);
        let ctx = gauss_bwd::GaussCtx {
            scales: &self.scales,
            proj: &proj,
            scene,
            degree: sv.degree,
            colors,
            pose: view.as_ref().is_some_and(|v| v.viewmat.is_some()),
        };
        let mut view = view;
        if let Some(v) = view.as_deref_mut() {
            v.reset(n);
        }
        let scatter = Scatter::new(
            out,
            view.as_deref_mut(),
            densify,
            k,
            (sv.cam.width, sv.cam.height),
        );
        let acc = self.sums();
        let (part_off, pos) = (&self.part_off, &self.pos);
        let simd = sv.blend.simd;
        // per projection chunk (a fixed partition of the Gaussians) the camera-gradient sum of
        // its Gaussians in index order; the chunks are then added in order
        let pose_parts: Vec<[f64; gauss_bwd::POSE_LEN]> = self
            .parts
            .par_iter()
            .zip(self.part_ids.par_iter())
            .enumerate()
            .map(|(c, (ss, ids))| {
                let pos = &pos[part_off[c]..part_off[c] + ss.len()];
                // SAFETY: every Gaussian index occurs once among the visible splats, so in
                // one part only.
                unsafe { gauss_block::part_backward(simd, &ctx, ss, ids, pos, acc, &scatter) }
            })
            .collect();
        if let Some(m) = view.and_then(|v| v.viewmat.as_mut()) {
            let mut sum = [0.0f64; gauss_bwd::POSE_LEN];
            for part in &pose_parts {
                for (a, v) in sum.iter_mut().zip(part) {
                    *a += v;
                }
            }
            *m = viewmat_grad(&sum, &proj.rot, &proj.center);
        }
        stats.project_s = t0.elapsed().as_secs_f64();
        Ok(stats)
    }

    /// Every Gaussian's projection in the last forward (gsplat's `fully_fused_projection`
    /// outputs with opacities after compensation and colours; radius 0 and zeros where culled).
    pub fn projection(&self) -> Option<Projection> {
        let sv = self.saved?;
        let n = sv.n;
        let mut p = Projection {
            radii: vec![0; n * 2],
            means2d: vec![0.0; n * 2],
            depths: vec![0.0; n],
            conics: vec![0.0; n * 3],
            opacities: vec![0.0; n],
            colors: vec![0.0; n * 3],
        };
        for (&i, s) in self.ids.iter().zip(&self.sorted) {
            let i = i as usize;
            p.radii[i * 2..i * 2 + 2].copy_from_slice(&[s.radius[0] as i32, s.radius[1] as i32]);
            p.means2d[i * 2..i * 2 + 2].copy_from_slice(&s.xy);
            p.depths[i] = s.depth;
            p.conics[i * 3..i * 3 + 3].copy_from_slice(&s.conic);
            p.opacities[i] = crate::fastmath::exp(s.ln_opacity);
            p.colors[i * 3..i * 3 + 3].copy_from_slice(&s.rgb);
        }
        Some(p)
    }

    /// The visible Gaussians of the last forward and their radii: (Gaussian index, [rx, ry]).
    pub fn radii(&self) -> impl Iterator<Item = (usize, [i32; 2])> + '_ {
        self.ids
            .iter()
            .zip(&self.sorted)
            .map(|(&i, s)| (i as usize, [s.radius[0] as i32, s.radius[1] as i32]))
    }

    /// Bytes the workspace holds (buffer capacities): what the forward's saved state and the
    /// backward's slots and sums cost.
    pub fn bytes(&self) -> usize {
        use std::mem::size_of;
        let v = |cap: usize, size: usize| cap * size;
        v(self.sorted.capacity(), size_of::<Splat>())
            + self
                .parts
                .iter()
                .map(|p| v(p.capacity(), size_of::<Splat>()))
                .sum::<usize>()
            + self
                .part_ids
                .iter()
                .map(|p| v(p.capacity(), 4))
                .sum::<usize>()
            + v(self.keys.capacity() + self.tmp.capacity(), 8)
            + v(
                self.ids.capacity() + self.pos.capacity() + self.band_lo.capacity(),
                4,
            )
            + self.bins.bytes()
            + v(self.tiles.capacity(), size_of::<TileOut>())
            + v(self.slots.capacity(), SLOT_BYTES)
            + v(self.acc.capacity(), size_of::<AccRow>())
            + self.touched.capacity()
            + self.written.capacity()
            + v(self.scales.capacity(), 4)
    }

    /// Every contributing (pixel, Gaussian) pair of the last forward, in blend order per pixel:
    /// (pixel index y * W + x, Gaussian index, whether alpha was clamped at max_alpha). For tests
    /// and reference checks (it replays the whole frame on one thread).
    pub fn contributions(&self) -> Result<Vec<(u32, u32, bool)>> {
        let sv = self.saved.ok_or_else(|| {
            Error::InvalidArgument("contributions need a forward on this workspace first".into())
        })?;
        struct Rec<'a> {
            out: Vec<(u32, u32, bool)>,
            ids: &'a [u32],
            x0: u32,
            y0: u32,
            width: u32,
        }
        impl blend_bwd::SlotSink for Rec<'_> {
            fn put(&mut self, _pos: u32, _vals: &[f32; slot::LEN]) {}
            const RECORD: bool = true;
            fn contrib(&mut self, r: usize, l: usize, pos: u32, clamped: bool) {
                let pix = (self.y0 + r as u32) * self.width + self.x0 + l as u32;
                self.out.push((pix, self.ids[pos as usize], clamped));
            }
        }
        let tiles_x = self.bins.tiles_x as usize;
        let mut rec = Rec {
            out: Vec::new(),
            ids: &self.ids,
            x0: 0,
            y0: 0,
            width: sv.cam.width,
        };
        let pix = blend_bwd::PixIn::default();
        for t in 0..self.tiles.len() {
            let (x0, y0) = ((t % tiles_x) * LANES, (t / tiles_x) * LANES);
            rec.x0 = x0 as u32;
            rec.y0 = y0 as u32;
            blend_bwd::bwd_tile_generic(
                x0 as u32,
                y0 as u32,
                &sv.blend,
                &self.sorted,
                self.bins.lists(t),
                &pix,
                &mut rec,
            );
        }
        Ok(rec.out)
    }

    /// The summed slots of the last backward, by sorted position.
    fn sums(&self) -> Sums<'_> {
        Sums {
            acc: &self.acc,
            touched: &self.touched,
        }
    }

    /// Bands of tile rows [r0, r1) whose slots fit the budget (at least one row each).
    fn bands(&self, budget: usize) -> Vec<(u32, u32)> {
        let (tx, ty) = (self.bins.tiles_x as usize, self.bins.tiles_y as usize);
        let cap = (budget / SLOT_BYTES).max(1);
        let mut bands = Vec::new();
        let (mut r0, mut sum) = (0usize, 0usize);
        for r in 0..ty {
            let row: usize = (r * tx..(r + 1) * tx).map(|t| self.bins.tile_len(t)).sum();
            if r > r0 && sum + row > cap {
                bands.push((r0 as u32, r as u32));
                r0 = r;
                sum = 0;
            }
            sum += row;
        }
        if ty > r0 {
            bands.push((r0 as u32, ty as u32));
        }
        bands
    }

    /// The band of tile rows [r0, r1)'s slot layout: chunk c's entries of those rows are one
    /// contiguous run of its list entries, put at `band_base[c]`. Returns the band's slots.
    fn band_layout(&mut self, r0: u32, r1: u32) -> usize {
        let tx = self.bins.tiles_x as usize;
        self.band_base.clear();
        self.band_lo.clear();
        let mut sum = 0usize;
        for c in 0..self.bins.n_chunks() {
            let lo = self.bins.start(c, r0 as usize * tx);
            let hi = self.bins.start(c, r1 as usize * tx);
            self.band_base.push(sum);
            self.band_lo.push(lo);
            sum += (hi - lo) as usize;
        }
        sum
    }

    /// Run the tile backward over the tiles of rows [r0, r1); returns the evaluations and the
    /// band's share of dL/d(background).
    fn blend_band(
        &mut self,
        sv: &Saved,
        grads: &ImageGrads<'_>,
        r0: u32,
        r1: u32,
    ) -> (u64, [f64; 3]) {
        let tiles_x = self.bins.tiles_x as usize;
        let sink = SlotWriter {
            base: self.slots.as_mut_ptr(),
            written: self.written.as_mut_ptr(),
            len: self.slots.len().min(self.written.len()),
        };
        let (sorted, bins, tiles) = (&self.sorted, &self.bins, &self.tiles);
        let (band_base, band_lo) = (&self.band_base, &self.band_lo);
        let (width, height) = (sv.cam.width as usize, sv.cam.height as usize);
        let expected = sv.opts.depth == DepthKind::Expected;
        let per_tile: Vec<(u64, [f64; 3])> = (r0 as usize * tiles_x..r1 as usize * tiles_x)
            .into_par_iter()
            .map(|t| {
                let (x0, y0) = ((t % tiles_x) * LANES, (t / tiles_x) * LANES);
                let empty = bins.lists(t).all(|l| l.is_empty());
                if empty && grads.skip_background {
                    return (0, [0.0; 3]);
                }
                let mut pix = blend_bwd::PixIn::default();
                let bg = blend_bwd::tile_inputs(
                    x0,
                    y0,
                    width,
                    height,
                    &tiles[t],
                    grads,
                    sv.blend.background,
                    expected,
                    !grads.skip_background,
                    sv.blend.simd,
                    &mut pix,
                );
                if empty {
                    return (0, bg);
                }
                let mut out = TileSink {
                    w: &sink,
                    bins,
                    band_base,
                    band_lo,
                    t,
                    chunk: 0,
                    next: 0,
                    end: 0,
                };
                let evals = blend_bwd::bwd_tile(
                    x0 as u32,
                    y0 as u32,
                    &sv.blend,
                    sorted,
                    bins.lists(t),
                    &pix,
                    &mut out,
                    sv.opts.absgrad,
                    grads.depth.is_some(),
                );
                out.finish();
                (evals, bg)
            })
            .collect();
        let mut bg = [0.0f64; 3];
        let mut evals = 0;
        for (e, b) in per_tile {
            evals += e;
            for c in 0..3 {
                bg[c] += b[c];
            }
        }
        (evals, bg)
    }

    /// Add each visible splat's slots of rows [r0, r1) to its running sums, in row-major
    /// tile order: one task per binning chunk walks the chunk's slots of the band in storage
    /// order (tile by tile), adding each to its splat's sums, which only that task touches.
    /// Slots the tile pass did not write (`written` 0: zero sums, which would leave the
    /// running sums' bits unchanged, see `SlotSink::zero`) are skipped. With `first` (the
    /// frame's first band) each task clears its chunk's touched flags first; a splat's first
    /// slot is then added to +0.0 rather than to its stale sums (no zeroing pass over the
    /// sums, 64 bytes per visible splat, which costs about a millisecond per frame).
    fn reduce_band(&mut self, r0: u32, r1: u32, first: bool) {
        let tx = self.bins.tiles_x as usize;
        let (t0, t1) = (r0 as usize * tx, r1 as usize * tx);
        let (slots, written) = (&self.slots, &self.written);
        let (bins, band_base) = (&self.bins, &self.band_base);
        self.acc
            .par_chunks_mut(TileBins::CHUNK)
            .zip(self.touched.par_chunks_mut(TileBins::CHUNK))
            .enumerate()
            .for_each(|(c, (accs, touched))| {
                if first {
                    touched.fill(0);
                }
                let base = c * TileBins::CHUNK;
                let items = bins.chunk_items(c, t0, t1);
                let run = &slots[band_base[c]..band_base[c] + items.len()];
                let wr = &written[band_base[c]..band_base[c] + items.len()];
                for (k, ((&p, s), &w)) in items.iter().zip(run).zip(wr).enumerate() {
                    // the sums are a random access (L2 at best): fetch them ahead
                    if let (Some(&ahead), Some(&1)) =
                        (items.get(k + REDUCE_PREFETCH), wr.get(k + REDUCE_PREFETCH))
                    {
                        crate::mem::prefetch_at(accs, ahead as usize - base);
                    }
                    if w == 0 {
                        continue;
                    }
                    let q = p as usize - base;
                    accs[q].add(s, touched[q] != 0);
                    touched[q] = 1;
                }
            });
    }
}

/// How many slots ahead the slot sums prefetch the running sums they add to.
const REDUCE_PREFETCH: usize = 16;

fn check_colors(c: &[f32], n: usize) -> Result<()> {
    if c.len() != n * 3 {
        return Err(Error::InvalidArgument(format!(
            "colors hold {} values, expected {} for {n} Gaussians",
            c.len(),
            n * 3
        )));
    }
    Ok(())
}

/// The band's slot buffer and its written flags, written from the tile tasks.
struct SlotWriter {
    base: *mut [f32; slot::LEN],
    written: *mut u8,
    len: usize,
}

// SAFETY: each slot index (slot and flag) is written by exactly one (tile, splat) pair, hence
// one task (see `TileSink::put`), and nothing reads the buffers during the tile pass.
unsafe impl Sync for SlotWriter {}

/// Puts one tile's slots in list order: chunk c's entries of tile t go to consecutive slots
/// from band_base[c] + start(c, t) - band_lo[c].
struct TileSink<'a> {
    w: &'a SlotWriter,
    bins: &'a TileBins,
    band_base: &'a [usize],
    band_lo: &'a [u32],
    t: usize,
    /// The next chunk to start, and the current chunk's next and end slots.
    chunk: usize,
    next: usize,
    end: usize,
}

impl TileSink<'_> {
    /// Every entry was put (the kernels' contract).
    fn finish(&mut self) {
        while self.next == self.end && self.chunk < self.bins.n_chunks() {
            self.advance();
        }
        assert!(
            self.next == self.end,
            "a kernel left entries of tile {} without a slot",
            self.t
        );
    }

    fn advance(&mut self) {
        let c = self.chunk;
        let (s0, s1) = (self.bins.start(c, self.t), self.bins.start(c, self.t + 1));
        self.next = self.band_base[c] + (s0 - self.band_lo[c]) as usize;
        self.end = self.next + (s1 - s0) as usize;
        self.chunk += 1;
    }
}

impl TileSink<'_> {
    /// The next entry's slot index.
    #[inline(always)]
    fn next_slot(&mut self) -> usize {
        while self.next == self.end {
            assert!(
                self.chunk < self.bins.n_chunks(),
                "more slots than list entries"
            );
            self.advance();
        }
        let i = self.next;
        assert!(i < self.w.len, "slot index out of range");
        self.next += 1;
        i
    }
}

impl blend_bwd::SlotSink for TileSink<'_> {
    #[inline]
    fn put(&mut self, _pos: u32, vals: &[f32; slot::LEN]) {
        let i = self.next_slot();
        // SAFETY: i is in bounds (checked) and belongs to this tile's entries only: chunk c's
        // entries of tile t are [start(c, t), start(c, t + 1)), a run no other tile shares.
        unsafe {
            *self.w.base.add(i) = *vals;
            *self.w.written.add(i) = 1;
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[inline]
    unsafe fn put_m512(&mut self, _pos: u32, v: std::arch::x86_64::__m512) {
        let i = self.next_slot();
        // SAFETY: as in `put`; lanes 0..12 are stored, the slot's 12 floats; AVX-512F is
        // present (the caller's contract).
        unsafe {
            std::arch::x86_64::_mm512_mask_storeu_ps(
                self.w.base.add(i) as *mut f32,
                (1 << slot::LEN) - 1,
                v,
            );
            *self.w.written.add(i) = 1;
        }
    }

    #[inline]
    fn zero(&mut self, _pos: u32) {
        let i = self.next_slot();
        // SAFETY: as in `put`
        unsafe { *self.w.written.add(i) = 0 };
    }
}

/// Raw base pointers of the output buffers, taken once before the parallel per-Gaussian pass.
/// The 4x4 dL/d(world-to-camera) from the summed per-Gaussian terms (dL/dW, dL/dt through the
/// camera-space means and covariances; dL/dc = -sum of the SH directions' dL/d(mean), c the
/// camera centre). c is the translation column of the matrix inverse (as gsplat and torch take
/// it): with V = [[W, t], [0, 1]], dc = -W^-1 (dW c + dt) - c (dV[3, :3] c + dV[3, 3]).
fn viewmat_grad(sum: &[f64; gauss_bwd::POSE_LEN], w: &[[f64; 3]; 3], c: &[f64; 3]) -> [f64; 16] {
    let v_c = [-sum[12], -sum[13], -sum[14]];
    // u = W^-T v_c (the cofactor form of the inverse; W is a rotation for rigid cameras)
    let cof = |r: usize, k: usize| {
        let (r1, r2, k1, k2) = ((r + 1) % 3, (r + 2) % 3, (k + 1) % 3, (k + 2) % 3);
        w[r1][k1] * w[r2][k2] - w[r1][k2] * w[r2][k1]
    };
    let det = w[0][0] * cof(0, 0) + w[0][1] * cof(0, 1) + w[0][2] * cof(0, 2);
    // (W^-1)[k][r] = cof(r, k) / det, so (W^-T v_c)[r] = sum_k cof(r, k) v_c[k] / det
    let u: [f64; 3] =
        std::array::from_fn(|r| (0..3).map(|k| cof(r, k) * v_c[k]).sum::<f64>() / det);
    let vc_dot_c = v_c[0] * c[0] + v_c[1] * c[1] + v_c[2] * c[2];
    let mut m = [0.0f64; 16];
    for r in 0..3 {
        for k in 0..3 {
            m[r * 4 + k] = sum[r * 3 + k] - u[r] * c[k];
        }
        m[r * 4 + 3] = sum[9 + r] - u[r];
        m[12 + r] = -vc_dot_c * c[r];
    }
    m[15] = -vc_dot_c;
    m
}

struct Scatter<'a> {
    means: *mut f32,
    quats: *mut f32,
    log_scales: *mut f32,
    logits: *mut f32,
    scales: *mut f32,
    opacities: *mut f32,
    sh0: *mut f32,
    sh_rest: *mut f32,
    colors: *mut f32,
    given_colors: bool,
    sh_rest_k: usize,
    view: Option<[*mut f32; 6]>,
    densify: Option<densify::Raw>,
    _life: std::marker::PhantomData<&'a mut Gradients>,
}

// SAFETY: `put` writes only the entries of Gaussian i, and each i is put by one task.
unsafe impl Sync for Scatter<'_> {}

impl<'a> Scatter<'a> {
    fn new(
        out: &'a mut Gradients,
        view: Option<&'a mut ViewGrads>,
        densify: Option<&'a mut DensifyStats>,
        sh_rest_k: usize,
        size: (u32, u32),
    ) -> Self {
        Scatter {
            means: out.means.as_mut_ptr(),
            quats: out.quats.as_mut_ptr(),
            log_scales: out.log_scales.as_mut_ptr(),
            logits: out.opacity_logits.as_mut_ptr(),
            scales: out.scales.as_mut_ptr(),
            opacities: out.opacities.as_mut_ptr(),
            sh0: out.sh0.as_mut_ptr(),
            sh_rest: out.sh_rest.as_mut_ptr(),
            colors: out.colors.as_mut_ptr(),
            given_colors: !out.colors.is_empty(),
            sh_rest_k,
            view: view.map(|v| {
                [
                    v.means2d.as_mut_ptr(),
                    v.means2d_abs.as_mut_ptr(),
                    v.conics.as_mut_ptr(),
                    v.colors.as_mut_ptr(),
                    v.opacities.as_mut_ptr(),
                    v.depths.as_mut_ptr(),
                ]
            }),
            densify: densify.map(|d| d.raw(size)),
            _life: std::marker::PhantomData,
        }
    }

    /// Ask for the lines [`Scatter::put_lane`] will update for Gaussian i (a read-modify-write
    /// of a dozen arrays at random-ish rows: cache misses otherwise).
    #[inline(always)]
    fn prefetch(&self, i: usize, degree: u8) {
        for (b, k) in [
            (self.means, 3),
            (self.quats, 4),
            (self.log_scales, 3),
            (self.logits, 1),
            (self.scales, 3),
            (self.opacities, 1),
        ] {
            crate::mem::prefetch_ptr(b, i * k);
        }
        if self.given_colors {
            crate::mem::prefetch_ptr(self.colors, i * 3);
        } else {
            crate::mem::prefetch_ptr(self.sh0, i * 3);
            let used = ((degree as usize + 1) * (degree as usize + 1) - 1) * 3;
            let at = i * self.sh_rest_k * 3;
            for o in (0..used).step_by(16).chain((used > 0).then_some(used - 1)) {
                crate::mem::prefetch_ptr(self.sh_rest, at + o);
            }
        }
        if let Some(v) = self.view {
            for (b, k) in v.iter().zip([2, 2, 3, 3, 1, 1]) {
                crate::mem::prefetch_ptr(*b, i * k);
            }
        }
        if let Some(d) = &self.densify {
            d.prefetch(i);
        }
    }

    /// Add the gradients of Gaussian i, lane `l` of a block (set its view gradients, add its
    /// statistics).
    ///
    /// # Safety
    /// No other call may use the same `i` concurrently; `i` is below the buffers' Gaussian
    /// count (checked against the scene before the pass).
    #[inline(always)]
    unsafe fn put_lane(
        &self,
        i: usize,
        s: &Splat,
        g: &gauss_block::GradLanes,
        l: usize,
        degree: u8,
    ) {
        #[inline(always)]
        unsafe fn add<const K: usize>(
            base: *mut f32,
            at: usize,
            vals: &[gauss_block::Lane; K],
            l: usize,
        ) {
            for (k, x) in vals.iter().enumerate() {
                // SAFETY: the caller keeps at + k inside the buffer.
                unsafe { *base.add(at + k) += x[l] };
            }
        }
        #[inline(always)]
        unsafe fn set<const K: usize>(
            base: *mut f32,
            at: usize,
            vals: &[gauss_block::Lane; K],
            l: usize,
        ) {
            for (k, x) in vals.iter().enumerate() {
                // SAFETY: as above
                unsafe { *base.add(at + k) = x[l] };
            }
        }
        // SAFETY: every offset below is Gaussian i's entry of a buffer sized for the scene.
        unsafe {
            add(self.means, i * 3, &g.means, l);
            add(self.quats, i * 4, &g.quats, l);
            add(self.log_scales, i * 3, &g.log_scales, l);
            add(self.logits, i, &[g.opacity_logit], l);
            add(self.scales, i * 3, &g.scales, l);
            add(self.opacities, i, &[g.opacity], l);
            if self.given_colors {
                add(self.colors, i * 3, &g.rgb, l);
            } else {
                add(self.sh0, i * 3, &g.sh[0], l);
                let nb = (degree as usize + 1) * (degree as usize + 1);
                for b in 1..nb {
                    add(self.sh_rest, (i * self.sh_rest_k + b - 1) * 3, &g.sh[b], l);
                }
            }
            if let Some(v) = self.view {
                set(v[0], i * 2, &g.means2d, l);
                set(v[1], i * 2, &g.means2d_abs, l);
                set(v[2], i * 3, &g.conic, l);
                set(v[3], i * 3, &g.rgb, l);
                set(v[4], i, &[g.opacity_eff], l);
                set(v[5], i, &[g.depth], l);
            }
            if let Some(d) = &self.densify {
                let m2 = [g.means2d[0][l], g.means2d[1][l]];
                let ma = [g.means2d_abs[0][l], g.means2d_abs[1][l]];
                d.add(i, m2, ma, s.radius);
            }
        }
    }
}
