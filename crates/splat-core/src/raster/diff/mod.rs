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
//!
//! Here the [`Workspace`] with its forward and backward; `types`: the options, inputs and
//! outputs; `slots`: the slot bands; `blend_bwd`: the tile backward that writes them;
//! `gauss_bwd` and `gauss_block`: the per-Gaussian backward (and the camera gradient);
//! `scatter`: its writes to the outputs.
use std::time::Instant;

use rayon::prelude::*;

use super::blend::{self, BlendParams, DepthOut, TileOut, LANES};
use super::project::{self, Projection, Projector, Splat};
use super::share::FrameColours;
use super::sort::{self, TileBins};
use super::RenderStats;
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
mod scatter;
mod sh_bwd;
mod slots;
#[cfg(test)]
mod tests;
mod types;

pub use densify::DensifyStats;
pub use slots::SLOT_BYTES;
pub use types::{BackwardStats, DepthKind, DiffOptions, Gradients, ImageGrads, ViewGrads};

use scatter::Scatter;
use slots::{slot, AccRow};

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
        let sv = self.check_backward(scene, colors, grads, out, densify.as_deref())?;
        let (n, k) = (scene.len(), scene.sh_rest_k());
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
            *m = gauss_bwd::viewmat_grad(&sum, &proj.rot, &proj.center);
        }
        stats.project_s = t0.elapsed().as_secs_f64();
        Ok(stats)
    }

    /// The backward's argument checks: a forward ran on this workspace, and `scene`, `colors`,
    /// the image gradients, the gradient buffers and the densification statistics match it.
    /// Returns what the forward saved.
    fn check_backward(
        &self,
        scene: &SceneView<'_>,
        colors: Option<&[f32]>,
        grads: &ImageGrads<'_>,
        out: &Gradients,
        densify: Option<&DensifyStats>,
    ) -> Result<Saved> {
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
        if let Some(d) = densify {
            d.check(n)?;
        }
        Ok(sv)
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
}

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
