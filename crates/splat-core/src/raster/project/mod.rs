//! Projection of 3D Gaussians to screen-space splats (SPEC §4 steps 1-5), as gsplat's
//! `fully_fused_projection` with opacities: EWA Jacobian with the frustum clamp, eps2d low-pass,
//! optional antialiasing compensation, the 1/255 opacity cull and the opacity-aware extent.
//!
//! - this module: the [`Splat`] the blend reads and the per-camera [`Projector`];
//! - `math`: the formulas the projection, the backward and densification share;
//! - `block`: a range of Gaussians 16 lanes at a time (the three stages, the splats' writes),
//!   with `block_avx512`'s shuffles in the AVX-512 build;
//! - `frame`: the drivers over a whole scene, one task per projection chunk.
use super::{RenderOptions, Simd};
use crate::camera::Camera;

mod block;
#[cfg(target_arch = "x86_64")]
mod block_avx512;
mod frame;
pub(crate) mod math;
#[cfg(test)]
mod tests;

#[cfg(test)]
pub(crate) use frame::project_visible;
pub(crate) use frame::project_visible_into;
pub use frame::{project_all, project_frame, Projection};
pub(crate) use math::{cov2d, quat_rotation};

/// Low-pass filter added to both diagonal entries of the 2D covariance.
pub const EPS2D: f32 = 0.3;
/// Smallest alpha that contributes (and smallest opacity kept).
pub const ALPHA_THRESHOLD: f32 = 1.0 / 255.0;
/// Gaussians per projection work unit (fixed, independent of the thread count).
const PROJECT_CHUNK: usize = 1 << PROJECT_CHUNK_BITS;

/// Gaussians per projection work unit, as a shift: chunk c holds Gaussians
/// [c << PROJECT_CHUNK_BITS, (c + 1) << PROJECT_CHUNK_BITS).
pub(crate) const PROJECT_CHUNK_BITS: u32 = 13;

/// One Gaussian as the blend sees it.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[repr(C, align(64))]
pub struct Splat {
    /// Projected mean in pixels (x right, y down).
    pub xy: [f32; 2],
    /// Inverse 2D covariance (a, b, c): sigma = 0.5 (a dx^2 + c dy^2) + b dx dy.
    pub conic: [f32; 3],
    /// Natural log of the opacity (after the antialiasing compensation when enabled): the
    /// blend computes alpha = exp(ln_opacity - sigma) in one exponential.
    pub ln_opacity: f32,
    pub rgb: [f32; 3],
    /// Camera-space z.
    pub depth: f32,
    /// Integer-valued box half-sizes in pixels (x, y).
    pub radius: [f32; 2],
    /// Blend-side constants of the 1/255 contour 0.5 (a dx^2 + 2 b dx dy + c dy^2) = level,
    /// level = ln(255 opacity) enlarged by a relative 1e-4 (so rounding never drops a pixel
    /// the exact per-pixel test keeps): 2 a level, the conic's determinant a c - b^2, 1 / a and
    /// the contour's half-height sqrt(2 level a / det) in pixels.
    pub two_a_level: f32,
    pub conic_det: f32,
    pub inv_a: f32,
    pub half_height: f32,
}

/// Per-camera constants, in float32 as the reference kernels use them.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Projector {
    pub(crate) rot: [[f64; 3]; 3],
    pub(crate) trans: [f64; 3],
    pub(crate) rot32: [[f32; 3]; 3],
    pub(crate) fx: f32,
    pub(crate) fy: f32,
    pub(crate) cx: f32,
    pub(crate) cy: f32,
    pub(crate) lim_x_pos: f32,
    pub(crate) lim_x_neg: f32,
    pub(crate) lim_y_pos: f32,
    pub(crate) lim_y_neg: f32,
    pub(crate) width: f32,
    pub(crate) height: f32,
    pub(crate) near: f64,
    pub(crate) far: f64,
    pub(crate) center: [f64; 3],
    /// Upper bound of the spectral norm of R (1 for a rigid camera).
    pub(crate) rot_gain: f32,
    pub(crate) antialiased: bool,
    pub(crate) sh_degree: u8,
    /// The build of the projection to run (the render options' kernel level, resolved for this
    /// CPU: every build gives the same bits, and `MORPHGS_SIMD` picks the plain one too).
    pub(crate) simd: Simd,
}

impl Projector {
    /// The unit view direction from the camera centre to `mean` (zero at the centre) and that
    /// distance: the SH evaluation direction of the forward, and of the backward, which needs
    /// the distance for its gradient.
    #[inline(always)]
    pub(crate) fn view_dir(&self, mean: [f32; 3]) -> ([f32; 3], f32) {
        let d = [
            (mean[0] as f64 - self.center[0]) as f32,
            (mean[1] as f64 - self.center[1]) as f32,
            (mean[2] as f64 - self.center[2]) as f32,
        ];
        let dn = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        let dir = if dn > 0.0 {
            [d[0] / dn, d[1] / dn, d[2] / dn]
        } else {
            [0.0; 3]
        };
        (dir, dn)
    }

    pub(crate) fn new(cam: &Camera, opts: &RenderOptions, sh_degree: u8) -> Self {
        let (w, h) = (cam.width as f32, cam.height as f32);
        let (fx, fy, cx, cy) = (cam.fx as f32, cam.fy as f32, cam.cx as f32, cam.cy as f32);
        let tan_fovx = 0.5 * w / fx;
        let tan_fovy = 0.5 * h / fy;
        let rot = cam.rotation();
        Projector {
            rot,
            trans: cam.translation(),
            rot32: rot.map(|r| r.map(|v| v as f32)),
            fx,
            fy,
            cx,
            cy,
            lim_x_pos: (w - cx) / fx + 0.3 * tan_fovx,
            lim_x_neg: cx / fx + 0.3 * tan_fovx,
            lim_y_pos: (h - cy) / fy + 0.3 * tan_fovy,
            lim_y_neg: cy / fy + 0.3 * tan_fovy,
            width: w,
            height: h,
            near: cam.near,
            far: cam.far,
            center: cam.center(),
            rot_gain: math::spectral_norm_bound(&rot),
            antialiased: opts.antialiased,
            sh_degree,
            simd: opts.simd.resolve(),
        }
    }
}
