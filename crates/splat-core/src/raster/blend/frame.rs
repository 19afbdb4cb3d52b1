//! A frame's blend: every tile through the chosen kernel in parallel (one task per tile), each
//! tile's pixels written to the images, and the frozen frame the benchmarks blend alone.
use rayon::prelude::*;

use super::{blend_tile, BlendParams, Counts, DepthOut, TileOut, LANES};
use crate::raster::project::Splat;
use crate::raster::sort::TileBins;

/// The frame's output buffers, written tile by tile from parallel tasks.
struct FrameOut {
    rgb: *mut f32,
    depth: *mut f32,
    alpha: *mut f32,
    width: usize,
    height: usize,
    /// Which depth to write (none: `depth` is not touched and may be empty).
    depth_out: DepthOut,
}

// SAFETY: the pointers come from three `&mut [f32]` borrowed for the whole parallel pass, and
// `FrameOut::tile` only writes the pixels of one tile, each tile from exactly one task.
unsafe impl Sync for FrameOut {}

impl FrameOut {
    /// Ask for the cache lines of the tile at (x0, y0) in the output images, for writing, before
    /// its blend: [`FrameOut::tile`] then writes lines already in cache instead of stalling on
    /// each one (a 1080p frame's images, 41 MB, are not in cache when a frame starts; the stores'
    /// misses were about a seventh of the blend stage on grid-5).
    fn prefetch(&self, x0: usize, y0: usize) {
        use crate::mem::prefetch_for_write;
        let cols = LANES.min(self.width - x0);
        for r in 0..LANES.min(self.height - y0) {
            let i = (y0 + r) * self.width + x0;
            prefetch_for_write(self.rgb.wrapping_add(i * 3), cols * 3);
            prefetch_for_write(self.alpha.wrapping_add(i), cols);
            if self.depth_out != DepthOut::Skip {
                prefetch_for_write(self.depth.wrapping_add(i), cols);
            }
        }
    }

    /// Write the final colour, depth and alpha of the tile at (x0, y0): colour plus the
    /// background seen through the remaining transmittance, alpha = 1 - T, expected depth.
    /// `tile` None means no Gaussian touches it (background, zero alpha and depth). Without
    /// depth ([`DepthOut::Skip`]) the depth image is left as it is.
    ///
    /// # Safety
    /// Each tile must be written by one call only, while no other access to the buffers runs.
    unsafe fn tile(&self, x0: usize, y0: usize, tile: Option<&TileOut>, bg: [f32; 3]) {
        let cols = LANES.min(self.width - x0);
        for r in 0..LANES.min(self.height - y0) {
            let i = (y0 + r) * self.width + x0;
            // SAFETY: pixels i..i + cols lie in row y0 + r of the image, inside this tile.
            let (rgb, alpha) = unsafe {
                (
                    std::slice::from_raw_parts_mut(self.rgb.add(i * 3), cols * 3),
                    std::slice::from_raw_parts_mut(self.alpha.add(i), cols),
                )
            };
            // SAFETY: as above; the depth image is only there when it is written.
            let depth = (self.depth_out != DepthOut::Skip)
                .then(|| unsafe { std::slice::from_raw_parts_mut(self.depth.add(i), cols) });
            let Some(tile) = tile else {
                for px in rgb.chunks_exact_mut(3) {
                    px.copy_from_slice(&bg);
                }
                if let Some(depth) = depth {
                    depth.fill(0.0);
                }
                alpha.fill(0.0);
                continue;
            };
            for l in 0..cols {
                let t = tile.t[r][l].abs();
                for ch in 0..3 {
                    rgb[l * 3 + ch] = tile.c[ch][r][l] + t * bg[ch];
                }
                alpha[l] = 1.0 - t;
            }
            match depth {
                Some(depth) if self.depth_out == DepthOut::Expected => {
                    for l in 0..cols {
                        depth[l] = tile.d[r][l] / alpha[l].max(1e-10);
                    }
                }
                Some(depth) => depth.copy_from_slice(&tile.d[r][..cols]),
                None => {}
            }
        }
    }
}

/// Blend every tile of a frame and write rgb (H,W,3), depth (H,W) and alpha (H,W).
/// Returns the Gaussian-pixel evaluations and the useful ones.
pub(crate) fn blend_frame(
    sorted: &[Splat],
    bins: &TileBins,
    p: &BlendParams,
    rgb: &mut [f32],
    depth: &mut [f32],
    alpha: &mut [f32],
) -> Counts {
    blend_frame_impl(sorted, bins, p, rgb, depth, alpha, None, DepthOut::Expected)
}

/// [`blend_frame`] keeping every tile's final state (transmittance and colour and depth sums
/// per pixel, `saved[t]` for tile t) for the backward pass; `depth_out` picks the depth
/// written (with [`DepthOut::Skip`] `depth` may be empty and the saved depth sums are stale).
pub(crate) fn blend_frame_saving(
    sorted: &[Splat],
    bins: &TileBins,
    p: &BlendParams,
    rgb: &mut [f32],
    depth: &mut [f32],
    alpha: &mut [f32],
    saved: &mut [TileOut],
    depth_out: DepthOut,
) -> Counts {
    blend_frame_impl(sorted, bins, p, rgb, depth, alpha, Some(saved), depth_out)
}

fn blend_frame_impl(
    sorted: &[Splat],
    bins: &TileBins,
    p: &BlendParams,
    rgb: &mut [f32],
    depth: &mut [f32],
    alpha: &mut [f32],
    saved: Option<&mut [TileOut]>,
    depth_out: DepthOut,
) -> Counts {
    let (tiles_x, tiles_y) = (bins.tiles_x as usize, bins.tiles_y as usize);
    let (width, height) = (p.width as usize, p.height as usize);
    let with_depth = depth_out != DepthOut::Skip;
    assert!(rgb.len() == width * height * 3);
    assert!(depth.len() == width * height || (!with_depth && depth.is_empty()));
    assert!(alpha.len() == width * height && tiles_x * LANES >= width);
    assert!(tiles_y * LANES >= height);
    let out = FrameOut {
        rgb: rgb.as_mut_ptr(),
        depth: depth.as_mut_ptr(),
        alpha: alpha.as_mut_ptr(),
        width,
        height,
        depth_out,
    };
    // each tile blends into its own buffer and writes its pixels of the image; a tile no
    // Gaussian touches gets the background (and its saved state the default: T = 1, no colour)
    // (the kernels set the tile's starting state themselves: no clearing of `buf` first)
    let tile = |t: usize, buf: &mut TileOut, saving: bool| {
        let (x0, y0) = ((t % tiles_x) * LANES, (t / tiles_x) * LANES);
        if bins.lists(t).all(|l| l.is_empty()) {
            if saving {
                *buf = TileOut::default();
            }
            // SAFETY: tile t is written by this task only (see `FrameOut`).
            unsafe { out.tile(x0, y0, None, p.background) };
            return Counts::default();
        }
        out.prefetch(x0, y0);
        let evals = blend_tile(
            x0 as u32,
            y0 as u32,
            p,
            sorted,
            bins.lists(t),
            buf,
            with_depth,
        );
        // SAFETY: as above
        unsafe { out.tile(x0, y0, Some(buf), p.background) };
        evals
    };
    match saved {
        Some(saved) => {
            assert_eq!(saved.len(), tiles_x * tiles_y);
            saved
                .par_iter_mut()
                .enumerate()
                .map(|(t, buf)| tile(t, buf, true))
                .sum()
        }
        // one scratch tile per rayon task, not one per tile
        None => (0..tiles_x * tiles_y)
            .into_par_iter()
            .map_init(TileOut::default, |buf, t| tile(t, buf, false))
            .sum(),
    }
}

/// One frame projected, depth-sorted and binned once (as [`crate::raster::render_into`] does), so that a
/// benchmark can time the blend stage alone on a fixed workload (`benches/raster.rs`, group
/// `blend_1thread`): the kernels' own cost without the projection, sort and binning around
/// them, and without their run-to-run variation.
pub struct FrozenFrame {
    sorted: Vec<Splat>,
    bins: TileBins,
    params: BlendParams,
}

impl FrozenFrame {
    /// Project, sort and bin `scene` seen by `cam` with `opts` (their `simd` picks the kernel,
    /// `count_useful` whether it counts).
    pub fn new(
        scene: &crate::scene::SceneView<'_>,
        cam: &crate::camera::Camera,
        opts: &crate::raster::RenderOptions,
    ) -> crate::error::Result<Self> {
        cam.validate()?;
        opts.validate()?;
        scene.validate()?;
        let degree = opts.effective_sh_degree(scene.sh_degree)?;
        let proj = crate::raster::project::Projector::new(cam, opts, degree);
        let mut parts = Vec::new();
        let n = crate::raster::project::project_visible_into(
            scene,
            &proj,
            crate::raster::share::FrameColours::Off,
            &mut parts,
            None,
        );
        let (mut keys, mut tmp, mut sorted) = (Vec::new(), Vec::new(), Vec::new());
        let mut fp = crate::raster::sort::Footprints::default();
        crate::raster::sort::sort_by_depth_into(
            &parts[..n],
            &mut keys,
            &mut tmp,
            &mut sorted,
            &mut fp,
            cam.tiles(),
            crate::raster::footprint::Mode::current(),
        );
        let mut bins = TileBins::default();
        let (tx, ty) = cam.tiles();
        bins.rebuild_from_footprints(&fp, tx, ty)?;
        let params = BlendParams::of(cam, opts);
        Ok(FrozenFrame {
            sorted,
            bins,
            params,
        })
    }

    /// Blend the frame into `rgb` (H*W*3), `depth` and `alpha` (H*W), with the expected depth
    /// (`depth` true, as a render) or none (the fit's forward); returns the evaluations and the
    /// useful ones (0 unless counted).
    pub fn blend(
        &self,
        rgb: &mut [f32],
        depth: &mut [f32],
        alpha: &mut [f32],
        with_depth: bool,
    ) -> (u64, u64) {
        let mode = if with_depth {
            DepthOut::Expected
        } else {
            DepthOut::Skip
        };
        let d: &mut [f32] = if with_depth { depth } else { &mut [] };
        let c = blend_frame_impl(
            &self.sorted,
            &self.bins,
            &self.params,
            rgb,
            d,
            alpha,
            None,
            mode,
        );
        (c.evals, c.useful)
    }
}
