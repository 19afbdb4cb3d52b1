//! The projection drivers over a whole scene: one task per projection chunk (a fixed partition
//! of the Gaussians, so the output does not depend on the thread count), and the inspection
//! path that projects every Gaussian.
use rayon::iter::Either;
use rayon::prelude::*;

use super::{Projector, Splat, PROJECT_CHUNK};
use crate::camera::Camera;
use crate::raster::share::{ChunkColours, FrameColours};
use crate::raster::RenderOptions;
use crate::scene::SceneView;

/// The visible splats of one view, per projection chunk, each in Gaussian-index order.
#[cfg(test)]
pub(crate) fn project_visible(scene: &SceneView<'_>, proj: &Projector) -> Vec<Vec<Splat>> {
    let mut parts = Vec::new();
    let n = project_visible_into(scene, proj, FrameColours::Off, &mut parts, None);
    parts.truncate(n);
    parts
}

/// [`project_visible`] into reused buffers, recording or reusing the frame's shared colours
/// (see [`crate::raster::share`]; the splats are the same bits either way), and with `ids` the
/// Gaussian index of every splat: chunk c's visible splats go to `parts[c]` (their indices to
/// `ids[c]`), for the returned number of chunks (`parts` and `ids` may hold more, left from a
/// larger scene, so their capacity survives too). A recording buffer holds at least one slot
/// per Gaussian.
pub(crate) fn project_visible_into(
    scene: &SceneView<'_>,
    proj: &Projector,
    colours: FrameColours<'_>,
    parts: &mut Vec<Vec<Splat>>,
    ids: Option<&mut Vec<Vec<u32>>>,
) -> usize {
    let n = scene.len();
    let chunks = n.div_ceil(PROJECT_CHUNK);
    if parts.len() < chunks {
        parts.resize_with(chunks, Vec::new);
    }
    // each chunk's index buffer, or none: settled once per pass (`Either` drives one of its
    // two iterators), and per chunk in the range projection, never per Gaussian
    let ids = match ids {
        Some(ids) => {
            if ids.len() < chunks {
                ids.resize_with(chunks, Vec::new);
            }
            Either::Left(ids[..chunks].par_iter_mut().map(Some))
        }
        None => Either::Right((0..chunks).into_par_iter().map(|_| None)),
    };
    let run = |c: usize,
               out: &mut Vec<Splat>,
               mut id: Option<&mut Vec<u32>>,
               mut cc: ChunkColours<'_>| {
        let lo = c * PROJECT_CHUNK;
        let hi = (lo + PROJECT_CHUNK).min(n);
        out.clear();
        if let Some(id) = id.as_deref_mut() {
            id.clear();
        }
        proj.project_range(scene, lo, hi, out, id, &mut cc);
    };
    let parts = parts[..chunks].par_iter_mut().zip(ids).enumerate();
    match colours {
        FrameColours::Record(slots, stamp) => slots[..n]
            .par_chunks_mut(PROJECT_CHUNK)
            .zip(parts)
            .for_each(|(part, (c, (out, id)))| {
                run(
                    c,
                    out,
                    id,
                    ChunkColours::Record(part, c * PROJECT_CHUNK, stamp),
                )
            }),
        FrameColours::Reuse(map, slots, stamp) => {
            parts.for_each(|(c, (out, id))| run(c, out, id, ChunkColours::Reuse(map, slots, stamp)))
        }
        FrameColours::Off => parts.for_each(|(c, (out, id))| run(c, out, id, ChunkColours::Off)),
    }
    chunks
}

/// The renderer's projection stage alone, for benchmarks: the visible splats of one view
/// (no shared colours), chunk c's in Gaussian-index order in `parts[c]` (reused buffers, as the
/// renderer's); returns the number of visible splats.
pub fn project_frame(
    scene: &SceneView<'_>,
    cam: &Camera,
    opts: &RenderOptions,
    parts: &mut Vec<Vec<Splat>>,
) -> crate::Result<usize> {
    cam.validate()?;
    opts.validate()?;
    scene.validate()?;
    let degree = opts.effective_sh_degree(scene.sh_degree)?;
    let proj = Projector::new(cam, opts, degree);
    let chunks = project_visible_into(scene, &proj, FrameColours::Off, parts, None);
    Ok(parts[..chunks].iter().map(Vec::len).sum())
}

/// Every Gaussian's projection, for inspection and tests (gsplat's `fully_fused_projection`
/// outputs plus opacity and colour). Culled Gaussians have radius 0 and zeros elsewhere.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Projection {
    /// (N,2) integer box half-sizes.
    pub radii: Vec<i32>,
    /// (N,2) pixel means.
    pub means2d: Vec<f32>,
    /// (N,) camera z.
    pub depths: Vec<f32>,
    /// (N,3) conics (a, b, c).
    pub conics: Vec<f32>,
    /// (N,) opacities after compensation.
    pub opacities: Vec<f32>,
    /// (N,3) SH colours (+0.5, clamped at 0).
    pub colors: Vec<f32>,
}

/// Project all Gaussians of a scene for one camera (see [`Projection`]).
pub fn project_all(
    scene: &SceneView<'_>,
    cam: &Camera,
    opts: &RenderOptions,
) -> crate::Result<Projection> {
    cam.validate()?;
    opts.validate()?;
    scene.validate()?;
    let degree = opts.effective_sh_degree(scene.sh_degree)?;
    let proj = Projector::new(cam, opts, degree);
    let splats: Vec<Option<(Splat, f32)>> = (0..scene.len())
        .into_par_iter()
        .with_min_len(PROJECT_CHUNK)
        .map(|i| proj.project_with_opacity(scene, i))
        .collect();
    // (one lane per call: this inspection path favours simplicity over speed)
    let mut p = Projection::default();
    for s in splats {
        let (s, opacity) = s.unwrap_or_default();
        p.radii.extend([s.radius[0] as i32, s.radius[1] as i32]);
        p.means2d.extend(s.xy);
        p.depths.push(s.depth);
        p.conics.extend(s.conic);
        p.opacities.push(opacity);
        p.colors.extend(s.rgb);
    }
    Ok(p)
}
