//! Projection of 3D Gaussians to screen-space splats (SPEC §4 steps 1-5), as gsplat's
//! `fully_fused_projection` with opacities: EWA Jacobian with the frustum clamp, eps2d low-pass,
//! optional antialiasing compensation, the 1/255 opacity cull and the opacity-aware extent.
use rayon::prelude::*;

use super::{sh, RenderOptions};
use crate::camera::Camera;
use crate::scene::SceneView;

/// Low-pass filter added to both diagonal entries of the 2D covariance.
pub const EPS2D: f32 = 0.3;
/// Smallest alpha that contributes (and smallest opacity kept).
pub const ALPHA_THRESHOLD: f32 = 1.0 / 255.0;
/// Gaussians per projection work unit (fixed, independent of the thread count).
const PROJECT_CHUNK: usize = 1 << PROJECT_CHUNK_BITS;

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
    rot: [[f64; 3]; 3],
    trans: [f64; 3],
    rot32: [[f32; 3]; 3],
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    lim_x_pos: f32,
    lim_x_neg: f32,
    lim_y_pos: f32,
    lim_y_neg: f32,
    width: f32,
    height: f32,
    near: f64,
    far: f64,
    center: [f64; 3],
    /// Upper bound of the spectral norm of R (1 for a rigid camera).
    rot_gain: f32,
    antialiased: bool,
    sh_degree: u8,
}

impl Projector {
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
            rot_gain: spectral_norm_bound(&rot),
            antialiased: opts.antialiased,
            sh_degree,
        }
    }

    /// Project Gaussian `i`; `None` when it is culled or holds non-finite values.
    #[inline]
    pub(crate) fn project(&self, scene: &SceneView<'_>, i: usize) -> Option<Splat> {
        self.project_with_opacity(scene, i).map(|(s, _)| s)
    }

    /// [`Projector::project`], also returning the opacity itself.
    #[inline(always)]
    fn project_with_opacity(&self, scene: &SceneView<'_>, i: usize) -> Option<(Splat, f32)> {
        let mean = &scene.means[i * 3..i * 3 + 3];
        // camera-space centre in float64 (far-from-origin scenes keep their precision)
        let mut pc = [0.0f64; 3];
        for (r, p) in pc.iter_mut().enumerate() {
            *p = self.rot[r][0] * mean[0] as f64
                + self.rot[r][1] * mean[1] as f64
                + self.rot[r][2] * mean[2] as f64
                + self.trans[r];
        }
        // also rejects NaN depths
        let in_range = pc[2] > self.near && pc[2] < self.far;
        if !(in_range && pc[0].is_finite() && pc[1].is_finite()) {
            return None;
        }
        let (x, y, z) = (pc[0] as f32, pc[1] as f32, pc[2] as f32);
        let ls = &scene.log_scales[i * 3..i * 3 + 3];
        let sh0 = &scene.sh0[i * 3..i * 3 + 3];
        if !(all_finite(ls) && all_finite(sh0)) {
            return None;
        }

        // EWA Jacobian with the frustum clamp
        let tx = z * (x / z).clamp(-self.lim_x_neg, self.lim_x_pos);
        let ty = z * (y / z).clamp(-self.lim_y_neg, self.lim_y_pos);
        let j00 = self.fx / z;
        let j02 = -self.fx * tx / (z * z);
        let j11 = self.fy / z;
        let j12 = -self.fy * ty / (z * z);
        let xy = [self.fx * x / z + self.cx, self.fy * y / z + self.cy];

        // Early out for Gaussians far off-screen, before the covariance: the box half-size on
        // axis a is at most 3.33 sqrt(|J_a|^2 s_max^2 + eps2d) (|T^T v| <= s_max |v|), so a
        // mean farther out than that (plus a pixel for ceil and rounding) is culled anyway.
        let s_max = ls[0].max(ls[1]).max(ls[2]).exp() * self.rot_gain;
        let bx = 3.33 * ((j00 * j00 + j02 * j02) * s_max * s_max + EPS2D).sqrt() + 1.0;
        let by = 3.33 * ((j11 * j11 + j12 * j12) * s_max * s_max + EPS2D).sqrt() + 1.0;
        if xy[0] + bx <= 0.0
            || xy[0] - bx >= self.width
            || xy[1] + by <= 0.0
            || xy[1] - by >= self.height
        {
            return None;
        }

        // world covariance factor M = R(q) S, camera factor T = W M
        let q = &scene.quats[i * 4..i * 4 + 4];
        let qn = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
        if !(qn > 0.0 && qn.is_finite()) {
            return None;
        }
        let (qw, qx, qy, qz) = (q[0] / qn, q[1] / qn, q[2] / qn, q[3] / qn);
        let rq = [
            [
                1.0 - 2.0 * (qy * qy + qz * qz),
                2.0 * (qx * qy - qw * qz),
                2.0 * (qx * qz + qw * qy),
            ],
            [
                2.0 * (qx * qy + qw * qz),
                1.0 - 2.0 * (qx * qx + qz * qz),
                2.0 * (qy * qz - qw * qx),
            ],
            [
                2.0 * (qx * qz - qw * qy),
                2.0 * (qy * qz + qw * qx),
                1.0 - 2.0 * (qx * qx + qy * qy),
            ],
        ];
        let s = [ls[0].exp(), ls[1].exp(), ls[2].exp()];
        // T = W R S (3x3)
        let mut t = [[0.0f32; 3]; 3];
        for r in 0..3 {
            for c in 0..3 {
                let w = &self.rot32[r];
                t[r][c] = (w[0] * rq[0][c] + w[1] * rq[1][c] + w[2] * rq[2][c]) * s[c];
            }
        }

        // A = J T (2x3); Sigma_2d = A A^T
        let mut a0 = [0.0f32; 3];
        let mut a1 = [0.0f32; 3];
        for c in 0..3 {
            a0[c] = j00 * t[0][c] + j02 * t[2][c];
            a1[c] = j11 * t[1][c] + j12 * t[2][c];
        }
        let c00 = a0[0] * a0[0] + a0[1] * a0[1] + a0[2] * a0[2];
        let c01 = a0[0] * a1[0] + a0[1] * a1[1] + a0[2] * a1[2];
        let c11 = a1[0] * a1[0] + a1[1] * a1[1] + a1[2] * a1[2];

        let det_orig = c00 * c11 - c01 * c01;
        let (c00, c11) = (c00 + EPS2D, c11 + EPS2D);
        let det = c00 * c11 - c01 * c01;
        if !(det > 0.0 && det.is_finite()) {
            return None;
        }
        let inv = 1.0 / det;
        let conic = [c11 * inv, -c01 * inv, c00 * inv];

        let logit = scene.opacity_logits[i];
        if !logit.is_finite() {
            return None;
        }
        let mut opacity = 1.0 / (1.0 + (-logit).exp());
        if self.antialiased {
            opacity *= (det_orig / det).max(0.005 * 0.005).sqrt();
        }
        if opacity.is_nan() || opacity < ALPHA_THRESHOLD {
            return None;
        }
        let ln_over = (opacity / ALPHA_THRESHOLD).ln();
        let extent = (2.0 * ln_over).sqrt().min(3.33);
        let radius = [(extent * c00.sqrt()).ceil(), (extent * c11.sqrt()).ceil()];
        if !(radius[0] > 0.0 && radius[1] > 0.0) {
            return None;
        }
        let inside = xy[0] + radius[0] > 0.0
            && xy[0] - radius[0] < self.width
            && xy[1] + radius[1] > 0.0
            && xy[1] - radius[1] < self.height;
        if !inside {
            return None;
        }

        // colour along the view direction mean - camera centre
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
        let k = scene.sh_rest_k() * 3;
        let rest = &scene.sh_rest[i * k..i * k + k];
        // every stored value must be finite, including SH bands this render does not use
        if !all_finite(rest) || !q.iter().all(|v| v.is_finite()) {
            return None;
        }
        let rgb = sh::color(self.sh_degree, dir, sh0, rest);

        let splat = Splat {
            xy,
            conic,
            ln_opacity: opacity.ln(),
            rgb,
            depth: z,
            radius,
            ..Default::default()
        };
        let level = ln_over * 1.0001 + 1e-4;
        let two_a_level = 2.0 * conic[0] * level;
        let conic_det = conic[0] * conic[2] - conic[1] * conic[1];
        let splat = Splat {
            two_a_level,
            conic_det,
            inv_a: 1.0 / conic[0],
            // sqrt(2 level a / det) = sqrt(2 level Sigma_yy), the robust form
            half_height: (2.0 * level * c11).sqrt(),
            ..splat
        };
        splat_is_finite(&splat).then_some((splat, opacity))
    }
}

/// An upper bound of the largest singular value of `m`: 1 (plus rounding slack) for a rotation,
/// else the Frobenius norm, so the off-screen early out stays conservative for any matrix.
fn spectral_norm_bound(m: &[[f64; 3]; 3]) -> f32 {
    let mut frob2 = 0.0;
    let mut off = 0.0f64;
    for i in 0..3 {
        for j in 0..3 {
            let mtm: f64 = (0..3).map(|k| m[k][i] * m[k][j]).sum();
            off = off.max((mtm - if i == j { 1.0 } else { 0.0 }).abs());
            if i == j {
                frob2 += mtm;
            }
        }
    }
    if off < 1e-5 {
        1.0001
    } else {
        (frob2.sqrt() * 1.0001) as f32
    }
}

/// Whether every value is finite, without an early exit so it vectorises (the 45 SH values of a
/// degree-3 Gaussian were 15% of projection as a scalar loop): the largest magnitude bit
/// pattern must be below the infinity's.
#[inline]
fn all_finite(v: &[f32]) -> bool {
    v.iter().fold(0u32, |m, x| m.max(x.to_bits() & 0x7FFF_FFFF)) < 0x7F80_0000
}

fn splat_is_finite(s: &Splat) -> bool {
    all_finite(&[
        s.xy[0],
        s.xy[1],
        s.conic[0],
        s.conic[1],
        s.conic[2],
        s.rgb[0],
        s.rgb[1],
        s.rgb[2],
        s.radius[0],
        s.radius[1],
        s.ln_opacity,
        s.depth,
        s.two_a_level,
        s.inv_a,
        s.conic_det,
        s.half_height,
    ])
}

/// Gaussians per projection work unit, as a shift: chunk c holds Gaussians
/// [c << PROJECT_CHUNK_BITS, (c + 1) << PROJECT_CHUNK_BITS).
pub(crate) const PROJECT_CHUNK_BITS: u32 = 13;

/// The visible splats of one view, per projection chunk, each in Gaussian-index order.
pub(crate) fn project_visible(scene: &SceneView<'_>, proj: &Projector) -> Vec<Vec<Splat>> {
    let n = scene.len();
    (0..n.div_ceil(PROJECT_CHUNK))
        .into_par_iter()
        .map(|c| {
            let lo = c * PROJECT_CHUNK;
            let hi = (lo + PROJECT_CHUNK).min(n);
            (lo..hi).filter_map(|i| proj.project(scene, i)).collect()
        })
        .collect()
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
