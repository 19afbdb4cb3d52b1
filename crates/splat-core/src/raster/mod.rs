//! The CPU tile rasterizer ("classic" 3DGS forward pass, SPEC §4).
//!
//! Stages, each parallel over fixed-size work units (so the output is bit-identical for any
//! thread count):
//! 1. [`project`]: Gaussians to screen-space splats (chunks of 8192 Gaussians);
//! 2. [`sort`]: one stable radix sort by depth, then per-chunk tile buckets;
//! 3. [`blend`]: per-pixel blending, one 16x16 tile per unit, SIMD chosen at run time.
//!
//! [`render_batch`] renders S scenes x F cameras in one parallel pass; [`diff`] is the
//! differentiable variant (a forward that keeps its state and the backward pass).
use std::time::Instant;

use rayon::prelude::*;

use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::scene::SceneView;

pub mod blend;
#[cfg(target_arch = "x86_64")]
mod blend_avx2;
#[cfg(target_arch = "x86_64")]
mod blend_avx512;
pub mod caps;
pub mod diff;
mod footprint;
pub mod project;
mod scratch;
pub mod sh;
mod share;
pub mod sort;

pub use project::{project_all, Projection, Splat};

/// Which blend kernel to run. `Auto` picks the best the CPU supports; an explicit level falls
/// back to the best available one below it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Simd {
    #[default]
    Auto,
    Avx512,
    Avx2,
    Scalar,
}

impl Simd {
    /// The level actually used on this CPU.
    pub fn resolve(self) -> Simd {
        #[cfg(target_arch = "x86_64")]
        {
            let avx512 = std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("avx512vl")
                && std::arch::is_x86_feature_detected!("avx512dq")
                && std::arch::is_x86_feature_detected!("avx512bw");
            let avx2 = std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma");
            match self {
                Simd::Auto | Simd::Avx512 if avx512 => Simd::Avx512,
                Simd::Auto | Simd::Avx512 | Simd::Avx2 if avx2 => Simd::Avx2,
                _ => Simd::Scalar,
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            Simd::Scalar
        }
    }

    /// Parse a level name as `name` prints it (`avx2` also accepted), case-insensitively.
    pub fn parse(s: &str) -> Option<Simd> {
        match s.trim().to_ascii_lowercase().as_str() {
            "auto" | "" => Some(Simd::Auto),
            "avx512" => Some(Simd::Avx512),
            "avx2" | "avx2+fma" => Some(Simd::Avx2),
            "scalar" => Some(Simd::Scalar),
            _ => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Simd::Auto => "auto",
            Simd::Avx512 => "avx512",
            Simd::Avx2 => "avx2+fma",
            Simd::Scalar => "scalar",
        }
    }
}

/// Rendering options (SPEC §4).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderOptions {
    /// Colour composited behind the Gaussians (depth uses a zero background).
    pub background: [f32; 3],
    /// Per-Gaussian alpha cap: 0.99 (INRIA, gsplat >= 1.6) or 0.999 (gsplat 1.5.3).
    pub max_alpha: f32,
    /// SH degree to evaluate; `None` uses the scene's degree (at most 3).
    pub sh_degree: Option<u8>,
    /// Multiply opacities by the antialiasing compensation sqrt(det_before / det_after).
    pub antialiased: bool,
    /// Blend kernel selection.
    pub simd: Simd,
    /// Count the useful evaluations in [`RenderStats::useful`] (costs the blend about 15%;
    /// for benchmarks). The images are the same bytes either way.
    pub count_useful: bool,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            background: [0.0; 3],
            max_alpha: 0.99,
            sh_degree: None,
            antialiased: false,
            simd: Simd::Auto,
            count_useful: false,
        }
    }
}

impl RenderOptions {
    pub fn validate(&self) -> Result<()> {
        if !(self.max_alpha > 0.0 && self.max_alpha <= 1.0) {
            return Err(Error::InvalidArgument(format!(
                "max_alpha must be in (0, 1], got {}",
                self.max_alpha
            )));
        }
        if !self.background.iter().all(|v| v.is_finite()) {
            return Err(Error::InvalidArgument(format!(
                "background must be finite, got {:?}",
                self.background
            )));
        }
        Ok(())
    }

    /// The SH degree to render a scene of degree `scene_degree` with.
    pub fn effective_sh_degree(&self, scene_degree: u8) -> Result<u8> {
        match self.sh_degree {
            None => Ok(scene_degree.min(3)),
            Some(d) if d > 3 => Err(Error::InvalidArgument(format!(
                "sh_degree {d} is not supported: the rasterizer evaluates SH degrees 0-3"
            ))),
            Some(d) if d > scene_degree => Err(Error::InvalidArgument(format!(
                "sh_degree {d} exceeds the scene's SH degree {scene_degree}"
            ))),
            Some(d) => Ok(d),
        }
    }
}

/// What a render did: counts and stage wall times (seconds, summed over frames).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct RenderStats {
    pub frames: u64,
    /// Gaussians given, summed over frames.
    pub gaussians: u64,
    /// Gaussians that survived projection and culling, summed over frames.
    pub visible: u64,
    /// Gaussian-tile pairs.
    pub intersections: u64,
    /// Gaussian-pixel evaluations in the blend (16 per tile row whose pixels the Gaussian's
    /// 1/255 contour may reach).
    pub evaluations: u64,
    /// The evaluations that can change a pixel: alpha >= 1/255 before the pixel stopped.
    /// `useful / evaluations` is the blend's efficiency. Counted only with
    /// [`RenderOptions::count_useful`] (else 0).
    pub useful: u64,
    pub project_s: f64,
    pub sort_s: f64,
    pub bin_s: f64,
    pub blend_s: f64,
}

impl RenderStats {
    pub fn add(&mut self, o: &RenderStats) {
        self.frames += o.frames;
        self.gaussians += o.gaussians;
        self.visible += o.visible;
        self.intersections += o.intersections;
        self.evaluations += o.evaluations;
        self.useful += o.useful;
        self.project_s += o.project_s;
        self.sort_s += o.sort_s;
        self.bin_s += o.bin_s;
        self.blend_s += o.blend_s;
    }
}

/// Render one scene from one camera into caller-provided buffers: `rgb` (H*W*3), `depth` and
/// `alpha` (H*W), row-major.
pub fn render_into(
    scene: &SceneView<'_>,
    cam: &Camera,
    opts: &RenderOptions,
    rgb: &mut [f32],
    depth: &mut [f32],
    alpha: &mut [f32],
) -> Result<RenderStats> {
    render_into_sharing(
        scene,
        cam,
        opts,
        rgb,
        depth,
        alpha,
        share::FrameColours::Off,
        &scratch::GLOBAL,
    )
}

/// [`render_into`] recording or reusing the frame's shared colours ([`share`]), with working
/// buffers from `pool`.
fn render_into_sharing(
    scene: &SceneView<'_>,
    cam: &Camera,
    opts: &RenderOptions,
    rgb: &mut [f32],
    depth: &mut [f32],
    alpha: &mut [f32],
    colours: share::FrameColours<'_>,
    pool: &scratch::Pool,
) -> Result<RenderStats> {
    cam.validate()?;
    opts.validate()?;
    scene.validate()?;
    let npix = cam.width as usize * cam.height as usize;
    if rgb.len() != npix * 3 || depth.len() != npix || alpha.len() != npix {
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
    let degree = opts.effective_sh_degree(scene.sh_degree)?;
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

    let mut scratch = pool.take();
    let s = &mut scratch;
    let t0 = Instant::now();
    let proj = project::Projector::new(cam, opts, degree);
    let chunks = project::project_visible_into(scene, &proj, colours, &mut s.parts, None);
    let visible = &s.parts[..chunks];
    stats.visible = visible.iter().map(|p| p.len() as u64).sum();
    let t1 = Instant::now();
    let (tiles_x, tiles_y) = cam.tiles();
    let (keys, tmp) = (&mut s.keys, &mut s.tmp);
    sort::sort_by_depth_into(
        visible,
        keys,
        tmp,
        &mut s.sorted,
        &mut s.footprints,
        cam.tiles(),
        footprint::Mode::current(),
    );
    let t2 = Instant::now();
    s.bins
        .rebuild_from_footprints(&s.footprints, tiles_x, tiles_y)?;
    stats.intersections = s.bins.intersections();
    let t3 = Instant::now();
    let params = blend::BlendParams::of(cam, opts);
    let counts = blend::blend_frame(&s.sorted, &s.bins, &params, rgb, depth, alpha);
    stats.evaluations = counts.evals;
    stats.useful = counts.useful;
    pool.give(scratch);
    let t4 = Instant::now();
    stats.project_s = (t1 - t0).as_secs_f64();
    stats.sort_s = (t2 - t1).as_secs_f64();
    stats.bin_s = (t3 - t2).as_secs_f64();
    stats.blend_s = (t4 - t3).as_secs_f64();
    Ok(stats)
}

/// Images of a batch render, frame-major: `rgb` is (S,F,H,W,3), `depth` and `alpha` (S,F,H,W).
#[derive(Debug, Clone, Default)]
pub struct BatchImages {
    pub scenes: usize,
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<f32>,
    pub depth: Vec<f32>,
    pub alpha: Vec<f32>,
    pub stats: RenderStats,
}

/// Render every scene from every camera (S x F images) in one parallel pass. All cameras must
/// share one image size. Stage times in the stats are summed over frames (frames overlap in
/// time when several run at once).
pub fn render_batch(
    scenes: &[SceneView<'_>],
    cams: &[Camera],
    opts: &RenderOptions,
) -> Result<BatchImages> {
    let Some((width, height, total)) = batch_size(scenes, cams, opts)? else {
        return Ok(BatchImages {
            scenes: scenes.len(),
            ..Default::default()
        });
    };
    // huge pages: the blend writes every pixel, so a 4 KiB page fault per 1024 values would
    // cost more than the writes (the 49-frame 832x480 pair's images are 780 MB)
    let mut rgb = crate::mem::zeroed_f32(total * 3);
    let mut depth = crate::mem::zeroed_f32(total);
    let mut alpha = crate::mem::zeroed_f32(total);
    let stats = render_batch_into(scenes, cams, opts, &mut rgb, &mut depth, &mut alpha)?;
    Ok(BatchImages {
        scenes: scenes.len(),
        frames: cams.len(),
        width,
        height,
        rgb,
        depth,
        alpha,
        stats,
    })
}

/// [`render_batch`] into images the caller owns, laid out as [`BatchImages`]'s: `rgb` holds
/// S x F x H x W x 3 values, `depth` and `alpha` S x F x H x W. Every value is written, so
/// buffers recycled from an earlier call need no clearing (fresh pages cost the kernel a clear
/// each on first write). Returns the stats summed over the images.
pub fn render_batch_into(
    scenes: &[SceneView<'_>],
    cams: &[Camera],
    opts: &RenderOptions,
    rgb: &mut [f32],
    depth: &mut [f32],
    alpha: &mut [f32],
) -> Result<RenderStats> {
    render_batch_into_caps(scenes, &[], cams, opts, rgb, depth, alpha)
}

/// [`render_batch_into`] with view-dependent visibility: `caps` is empty (no scene has caps) or
/// holds one entry per scene, and scene `s`'s Gaussians that `caps[s]` hides from a camera are
/// left out of that camera's frame ([`caps`]). A scene without caps renders as
/// [`render_batch_into`] renders it.
pub fn render_batch_into_caps(
    scenes: &[SceneView<'_>],
    caps: &[Option<caps::Caps<'_>>],
    cams: &[Camera],
    opts: &RenderOptions,
    rgb: &mut [f32],
    depth: &mut [f32],
    alpha: &mut [f32],
) -> Result<RenderStats> {
    if !caps.is_empty() && caps.len() != scenes.len() {
        return Err(Error::InvalidArgument(format!(
            "caps: expected one entry per scene ({}), got {}",
            scenes.len(),
            caps.len()
        )));
    }
    for (s, c) in scenes.iter().zip(caps) {
        if let Some(c) = c {
            c.validate(s.len())?;
        }
    }
    let total = batch_size(scenes, cams, opts)?.map_or(0, |(_, _, t)| t);
    if rgb.len() != total * 3 || depth.len() != total || alpha.len() != total {
        return Err(Error::InvalidArgument(format!(
            "output buffers hold {}, {} and {} values, expected {}, {total} and {total} for {} \
             scenes x {} cameras",
            rgb.len(),
            depth.len(),
            alpha.len(),
            total * 3,
            scenes.len(),
            cams.len()
        )));
    }
    let mut stats = RenderStats::default();
    if total == 0 {
        return Ok(stats);
    }
    let npix = cams[0].width as usize * cams[0].height as usize;
    let maps = colour_maps(scenes, cams.len(), opts)?;
    let pool = scratch::Pool::for_batch();
    let per_unit: Vec<RenderStats> = if let Some(maps) = maps {
        render_frames_sharing(scenes, caps, cams, opts, &maps, &pool, rgb, depth, alpha)?
    } else {
        rgb.par_chunks_mut(npix * 3)
            .zip(depth.par_chunks_mut(npix))
            .zip(alpha.par_chunks_mut(npix))
            .enumerate()
            .map(|(u, ((rgb, depth), alpha))| {
                let (s, cam) = (u / cams.len(), &cams[u % cams.len()]);
                let mut logits = Vec::new();
                let scene = &with_caps(&scenes[s], caps.get(s), cam, &mut logits);
                let colours = share::FrameColours::Off;
                render_into_sharing(scene, cam, opts, rgb, depth, alpha, colours, &pool)
            })
            .collect::<Result<_>>()?
    };
    pool.retire();
    for s in &per_unit {
        stats.add(s);
    }
    Ok(stats)
}

/// `scene` as `cam` sees it under its caps (its hidden Gaussians' logits -inf, held in
/// `logits`), or `scene` itself without caps. Colours stay shareable: caps change opacity only.
fn with_caps<'s>(
    scene: &SceneView<'s>,
    caps: Option<&Option<caps::Caps<'_>>>,
    cam: &Camera,
    logits: &'s mut Vec<f32>,
) -> SceneView<'s> {
    match caps {
        Some(Some(c)) => {
            c.logits(scene, caps::centre(cam), logits);
            SceneView {
                opacity_logits: logits,
                ..*scene
            }
        }
        _ => *scene,
    }
}

/// Checks a batch (options, cameras of one size, scenes and their SH degrees) and gives its
/// image size and its pixel count over all images (`None` without cameras).
fn batch_size(
    scenes: &[SceneView<'_>],
    cams: &[Camera],
    opts: &RenderOptions,
) -> Result<Option<(u32, u32, usize)>> {
    opts.validate()?;
    let Some(first) = cams.first() else {
        return Ok(None);
    };
    for c in cams {
        c.validate()?;
        if (c.width, c.height) != (first.width, first.height) {
            return Err(Error::InvalidArgument(format!(
                "all cameras must share one image size, got {}x{} and {}x{}",
                first.width, first.height, c.width, c.height
            )));
        }
    }
    for s in scenes {
        s.validate()?;
        opts.effective_sh_degree(s.sh_degree)?;
    }
    let npix = first.width as usize * first.height as usize;
    let units = scenes.len() * cams.len();
    npix.checked_mul(units)
        .filter(|&v| {
            v.checked_mul(3)
                .is_some_and(|v| v <= isize::MAX as usize / 4)
        })
        .map(|total| Some((first.width, first.height, total)))
        .ok_or_else(|| {
            Error::InvalidArgument(format!(
                "{units} images of {}x{} are too large to hold in memory",
                first.width, first.height
            ))
        })
}

/// For each scene after the first, its [`share::colour_map`] against the first (`None` for a
/// scene that shares nothing), when sharing colours can pay: two or more scenes, the same SH
/// degree, and two or more frames (the maps cost about one projection of the scenes).
#[allow(clippy::type_complexity)]
fn colour_maps(
    scenes: &[SceneView<'_>],
    frames: usize,
    opts: &RenderOptions,
) -> Result<Option<Vec<Option<Vec<u32>>>>> {
    let Some(first) = scenes.first() else {
        return Ok(None);
    };
    if scenes.len() < 2 || frames < 2 {
        return Ok(None);
    }
    let degree = opts.effective_sh_degree(first.sh_degree)?;
    let mut maps = Vec::with_capacity(scenes.len() - 1);
    for s in &scenes[1..] {
        let same = opts.effective_sh_degree(s.sh_degree)? == degree;
        maps.push(if same {
            share::colour_map(first, s)
        } else {
            None
        });
    }
    Ok(maps.iter().any(Option::is_some).then_some(maps))
}

/// The units of [`render_batch`] frame by frame: each frame renders the first scene, recording
/// its colours, then the others, reusing them where `maps` says a Gaussian's mean and SH equal
/// one of the first scene's. Returns the per-unit stats in unit order (scene-major).
#[allow(clippy::too_many_arguments)]
fn render_frames_sharing(
    scenes: &[SceneView<'_>],
    caps: &[Option<caps::Caps<'_>>],
    cams: &[Camera],
    opts: &RenderOptions,
    maps: &[Option<Vec<u32>>],
    pool: &scratch::Pool,
    rgb: &mut [f32],
    depth: &mut [f32],
    alpha: &mut [f32],
) -> Result<Vec<RenderStats>> {
    type Unit<'b> = (&'b mut [f32], &'b mut [f32], &'b mut [f32]);
    let f = cams.len();
    let npix = cams[0].width as usize * cams[0].height as usize;
    // group the units' outputs by frame: frames[k][s] is scene s's images of frame k
    let mut frames: Vec<Vec<Unit<'_>>> = (0..f).map(|_| Vec::new()).collect();
    for (u, ((rgb, depth), alpha)) in rgb
        .chunks_mut(npix * 3)
        .zip(depth.chunks_mut(npix))
        .zip(alpha.chunks_mut(npix))
        .enumerate()
    {
        frames[u % f].push((rgb, depth, alpha));
    }
    let n0 = scenes[0].len();
    // slot buffers of finished frames, reused by the next ones (one per frame in flight, so
    // each buffer's pages are faulted in once)
    let slot_pool = std::sync::Mutex::new(Vec::new());
    let per_frame: Vec<Vec<RenderStats>> = frames
        .into_par_iter()
        .enumerate()
        .map(|(k, units)| {
            let popped = slot_pool.lock().ok().and_then(|mut p| p.pop());
            let mut slots = popped.unwrap_or_else(|| share::slots(n0));
            // frame k's stamp: slots left by an earlier frame of this buffer never match
            let stamp = k as u32 + 1;
            let mut stats = Vec::with_capacity(units.len());
            for (s, (rgb, depth, alpha)) in units.into_iter().enumerate() {
                let colours = match s {
                    0 => share::FrameColours::Record(&mut slots, stamp),
                    _ => match &maps[s - 1] {
                        Some(map) => share::FrameColours::Reuse(map, &slots, stamp),
                        None => share::FrameColours::Off,
                    },
                };
                let cam = &cams[k];
                let mut logits = Vec::new();
                let scene = &with_caps(&scenes[s], caps.get(s), cam, &mut logits);
                let st = render_into_sharing(scene, cam, opts, rgb, depth, alpha, colours, pool)?;
                stats.push(st);
            }
            if let Ok(mut p) = slot_pool.lock() {
                p.push(slots);
            }
            Ok(stats)
        })
        .collect::<Result<_>>()?;
    // back to unit order (u = s * F + k)
    Ok((0..scenes.len())
        .flat_map(|s| per_frame.iter().map(move |fr| fr[s]))
        .collect())
}

#[cfg(test)]
mod tests;
