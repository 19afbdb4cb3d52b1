//! Per-Gaussian backward: from one Gaussian's summed blend gradients (a [`Slot`]) through the
//! projection (conic inverse, antialiasing compensation, EWA Jacobian with the frustum clamp,
//! world to camera, covariance from quaternion and scale), the SH colour and the activations
//! (exp of the log-scales, sigmoid of the opacity logit, quaternion normalisation) to the
//! stored parameters. gsplat's `projection_ewa_3dgs_fused_bwd` and
//! `sh_coeffs_to_color_fast_vjp`, plus the activation VJPs torch autograd does for it.
//!
//! Forward quantities are recomputed from the stored parameters as the forward computes them
//! (float32, camera-space mean in float64), as gsplat's kernel does.
//!
//! The camera (pose) gradient: each Gaussian's pose terms ([`POSE_LEN`] values), summed over
//! the Gaussians by the caller, become dL/d(world-to-camera matrix) in [`viewmat_grad`].
#[cfg(test)]
use super::sh_bwd::sh_vjp;
#[cfg(test)]
use super::slots::slot;
use crate::fastmath;
use crate::raster::project::Projector;
#[cfg(test)]
use crate::raster::project::{Splat, EPS2D};
use crate::scene::SceneView;

/// Everything one Gaussian's backward produces (of the scalar reference [`gauss_backward`]).
#[cfg(test)]
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct GaussGrad {
    pub means: [f32; 3],
    pub quats: [f32; 4],
    pub log_scales: [f32; 3],
    pub opacity_logit: f32,
    /// dL/d(exp(log_scales)) and dL/d(sigmoid(logit)): gsplat's activated parameters.
    pub scales: [f32; 3],
    pub opacity: f32,
    /// Coefficient gradients, basis-major (k = 0 is sh0); only the active bands are set.
    pub sh: [[f32; 3]; 16],
    /// dL/d(colour) for given (not SH) colours, ungated.
    pub color: [f32; 3],
    // the view's intermediate gradients (gsplat's rasterize_to_pixels VJP outputs)
    pub means2d: [f32; 2],
    pub means2d_abs: [f32; 2],
    pub conic: [f32; 3],
    pub rgb: [f32; 3],
    pub opacity_eff: f32,
    pub depth: f32,
    /// With [`GaussCtx::pose`]: this Gaussian's share of the camera gradient, summed over the
    /// Gaussians by the caller: dL/dW (3x3 row-major, W the world-to-camera rotation) through
    /// the camera-space mean and covariance, dL/dt (the translation), and dL/d(mean) through the
    /// SH view direction (which depends on the camera centre).
    pub pose: [f32; POSE_LEN],
}

/// Length of [`GaussGrad::pose`]: dL/dW (9), dL/dt (3), the SH direction's dL/d(mean) (3).
pub(crate) const POSE_LEN: usize = 15;

/// The 4x4 dL/d(world-to-camera) from the summed per-Gaussian terms (dL/dW, dL/dt through the
/// camera-space means and covariances; dL/dc = -sum of the SH directions' dL/d(mean), c the
/// camera centre). c is the translation column of the matrix inverse (as gsplat and torch take
/// it): with V = [[W, t], [0, 1]], dc = -W^-1 (dW c + dt) - c (dV[3, :3] c + dV[3, 3]).
pub(super) fn viewmat_grad(sum: &[f64; POSE_LEN], w: &[[f64; 3]; 3], c: &[f64; 3]) -> [f64; 16] {
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

/// The per-camera constants the per-Gaussian backward needs.
pub(crate) struct GaussCtx<'a> {
    pub proj: &'a Projector,
    pub scene: &'a SceneView<'a>,
    /// SH degree evaluated (colours from SH), ignored when `colors` is set.
    pub degree: u8,
    /// Given per-Gaussian colours (N,3) instead of SH.
    pub colors: Option<&'a [f32]>,
    /// Also compute [`GaussGrad::pose`].
    pub pose: bool,
    /// exp(log_scales) of every Gaussian (N,3), from [`scales_into`].
    pub scales: &'a [f32],
}

/// exp of every log-scale into `out`, in one pass the compiler vectorises (the same
/// `fastmath::exp` per value, so the same bits as computing each in the per-Gaussian pass,
/// where the exp's latency chains of one Gaussian did not overlap).
pub(crate) fn scales_into(log_scales: &[f32], out: &mut Vec<f32>) {
    use rayon::prelude::*;
    out.resize(log_scales.len(), 0.0);
    out.par_chunks_mut(SCALE_CHUNK)
        .zip(log_scales.par_chunks(SCALE_CHUNK))
        .for_each(|(o, l)| {
            for (o, &l) in o.iter_mut().zip(l) {
                *o = fastmath::exp(l);
            }
        });
}

/// Values per task of [`scales_into`].
const SCALE_CHUNK: usize = 3 << 12;

/// Backward of Gaussian `i`, whose depth-sorted splat is `s`, from its summed blend slot: the
/// one-Gaussian reference of the block version the backward runs
/// ([`super::gauss_block::block_backward`], which a test holds to it bit for bit).
#[cfg(test)]
pub(crate) fn gauss_backward(
    ctx: &GaussCtx<'_>,
    i: usize,
    s: &Splat,
    acc: &[f32; slot::LEN],
) -> GaussGrad {
    let p = ctx.proj;
    let sc = ctx.scene;
    let mut out = GaussGrad::default();
    let [ca, cb, cc] = s.conic;

    // ---- blend slot -> gradients of the splat's values
    let v_conic = [
        -0.5 * acc[slot::VDX2],
        -acc[slot::VDXDY],
        -0.5 * acc[slot::VDY2],
    ];
    let v_xy = [
        -(ca * acc[slot::VDX] + cb * acc[slot::VDY]),
        -(cb * acc[slot::VDX] + cc * acc[slot::VDY]),
    ];
    let v_rgb = [acc[slot::C0], acc[slot::C0 + 1], acc[slot::C0 + 2]];
    let v_z_blend = acc[slot::C0 + 3];
    out.means2d = v_xy;
    out.means2d_abs = [acc[slot::ABSX], acc[slot::ABSY]];
    out.conic = v_conic;
    out.rgb = v_rgb;
    out.depth = v_z_blend;

    // ---- recompute the forward (as `Projector::screen` / `footprint`)
    let mean = [sc.means[i * 3], sc.means[i * 3 + 1], sc.means[i * 3 + 2]];
    let mut pc = [0.0f32; 3];
    for (r, v) in pc.iter_mut().enumerate() {
        *v = (p.rot[r][0] * mean[0] as f64
            + p.rot[r][1] * mean[1] as f64
            + p.rot[r][2] * mean[2] as f64
            + p.trans[r]) as f32;
    }
    let [x, y, z] = pc;
    let (fx, fy) = (p.fx, p.fy);
    let (ux, uy) = (x / z, y / z);
    let in_x = ux >= -p.lim_x_neg && ux <= p.lim_x_pos;
    let in_y = uy >= -p.lim_y_neg && uy <= p.lim_y_pos;
    let tx = z * ux.max(-p.lim_x_neg).min(p.lim_x_pos);
    let ty = z * uy.max(-p.lim_y_neg).min(p.lim_y_pos);
    let j00 = fx / z;
    let j02 = -fx * tx / (z * z);
    let j11 = fy / z;
    let j12 = -fy * ty / (z * z);

    let qv = [
        sc.quats[i * 4],
        sc.quats[i * 4 + 1],
        sc.quats[i * 4 + 2],
        sc.quats[i * 4 + 3],
    ];
    let qn = (qv[0] * qv[0] + qv[1] * qv[1] + qv[2] * qv[2] + qv[3] * qv[3]).sqrt();
    let [qw, qx, qy, qz] = qv.map(|v| v / qn);
    let rq = crate::raster::project::quat_rotation(qw, qx, qy, qz);
    let scale = [
        ctx.scales[i * 3],
        ctx.scales[i * 3 + 1],
        ctx.scales[i * 3 + 2],
    ];
    let w = &p.rot32;
    // Mq = W Rq; T = Mq diag(s)
    let mut mq = [[0.0f32; 3]; 3];
    let mut t = [[0.0f32; 3]; 3];
    for r in 0..3 {
        for c in 0..3 {
            mq[r][c] = w[r][0] * rq[0][c] + w[r][1] * rq[1][c] + w[r][2] * rq[2][c];
            t[r][c] = mq[r][c] * scale[c];
        }
    }
    let mut a0 = [0.0f32; 3];
    let mut a1 = [0.0f32; 3];
    for c in 0..3 {
        a0[c] = j00 * t[0][c] + j02 * t[2][c];
        a1[c] = j11 * t[1][c] + j12 * t[2][c];
    }
    let c00 = a0[0] * a0[0] + a0[1] * a0[1] + a0[2] * a0[2];
    let c01 = a0[0] * a1[0] + a0[1] * a1[1] + a0[2] * a1[2];
    let c11 = a1[0] * a1[0] + a1[1] * a1[1] + a1[2] * a1[2];
    let (bx, by) = (c00 + EPS2D, c11 + EPS2D);
    let det = bx * by - c01 * c01;

    let logit = sc.opacity_logits[i];
    let opacity = 1.0 / (1.0 + fastmath::exp(-logit));
    let ratio = (c00 * c11 - c01 * c01) / det;
    let comp = if p.antialiased {
        ratio.max(0.005 * 0.005).sqrt()
    } else {
        1.0
    };
    let o_eff = opacity * comp;

    // ---- opacity: alpha = o_eff e^-sigma, so dL/do_eff = sum(e v_alpha) / o_eff
    let v_o_eff = acc[slot::V0] / o_eff;
    out.opacity_eff = v_o_eff;
    let v_opacity = v_o_eff * comp;
    let v_comp = v_o_eff * opacity;

    // ---- conic = inverse(Sigma2d + eps I): v_Sigma = -P V P with V = [[va, vb/2], [vb/2, vc]]
    let (pa, pb, pc_) = (s.conic[0], s.conic[1], s.conic[2]);
    let (va, vb, vc) = (v_conic[0], 0.5 * v_conic[1], v_conic[2]);
    // PV = [[pa va + pb vb, pa vb + pb vc], [pb va + pc vb, pb vb + pc vc]]
    let pv00 = pa * va + pb * vb;
    let pv01 = pa * vb + pb * vc;
    let pv10 = pb * va + pc_ * vb;
    let pv11 = pb * vb + pc_ * vc;
    let mut v_c00 = -(pv00 * pa + pv01 * pb);
    let mut v_c01 = -2.0 * (pv00 * pb + pv01 * pc_); // c01 appears twice in the matrix
    let mut v_c11 = -(pv10 * pb + pv11 * pc_);
    // antialiasing: comp = sqrt(max(0.005^2, det(Sigma) / det(Sigma + eps I)))
    if p.antialiased && ratio > 0.005 * 0.005 {
        let v_ratio = v_comp * 0.5 / comp;
        v_c00 += v_ratio * (c11 - ratio * by) / det;
        v_c11 += v_ratio * (c00 - ratio * bx) / det;
        v_c01 += v_ratio * (2.0 * c01 * (ratio - 1.0)) / det;
    }

    // ---- Sigma2d = A A^T with A = J T (2x3): v_A = 2 Vs A, Vs = [[v00, v01/2], [v01/2, v11]]
    let mut v_a0 = [0.0f32; 3];
    let mut v_a1 = [0.0f32; 3];
    for c in 0..3 {
        v_a0[c] = 2.0 * v_c00 * a0[c] + v_c01 * a1[c];
        v_a1[c] = v_c01 * a0[c] + 2.0 * v_c11 * a1[c];
    }
    // A0 = j00 T0 + j02 T2, A1 = j11 T1 + j12 T2 (T rows)
    let mut v_t = [[0.0f32; 3]; 3];
    for c in 0..3 {
        v_t[0][c] = j00 * v_a0[c];
        v_t[1][c] = j11 * v_a1[c];
        v_t[2][c] = j02 * v_a0[c] + j12 * v_a1[c];
    }
    let dot3 = |u: &[f32; 3], v: &[f32; 3]| u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
    let v_j00 = dot3(&v_a0, &t[0]);
    let v_j02 = dot3(&v_a0, &t[2]);
    let v_j11 = dot3(&v_a1, &t[1]);
    let v_j12 = dot3(&v_a1, &t[2]);

    // ---- camera-space mean: the projected mean, the Jacobian entries, the depth colour
    let rz = 1.0 / z;
    let rz2 = rz * rz;
    let mut v_pc = [fx * rz * v_xy[0], fy * rz * v_xy[1], 0.0];
    v_pc[2] -= (fx * x * v_xy[0] + fy * y * v_xy[1]) * rz2;
    v_pc[2] -= fx * rz2 * v_j00 + fy * rz2 * v_j11;
    if in_x {
        // j02 = -fx x / z^2
        v_pc[0] -= fx * rz2 * v_j02;
        v_pc[2] += 2.0 * fx * x * rz2 * rz * v_j02;
    } else {
        // j02 = -fx lim / z (tx = z lim)
        v_pc[2] += fx * tx * rz2 * rz * v_j02;
    }
    if in_y {
        v_pc[1] -= fy * rz2 * v_j12;
        v_pc[2] += 2.0 * fy * y * rz2 * rz * v_j12;
    } else {
        v_pc[2] += fy * ty * rz2 * rz * v_j12;
    }
    v_pc[2] += v_z_blend;
    // mean: pc = W mean + t
    let mut v_mean = [0.0f32; 3];
    for c in 0..3 {
        v_mean[c] = w[0][c] * v_pc[0] + w[1][c] * v_pc[1] + w[2][c] * v_pc[2];
    }

    // ---- covariance factor: T = Mq diag(s), Mq = W Rq
    let mut v_scale = [0.0f32; 3];
    let mut v_mq = [[0.0f32; 3]; 3];
    for c in 0..3 {
        for r in 0..3 {
            v_mq[r][c] = v_t[r][c] * scale[c];
            v_scale[c] += v_t[r][c] * mq[r][c];
        }
    }
    // v_Rq = W^T v_Mq
    let mut g = [[0.0f32; 3]; 3];
    for r in 0..3 {
        for c in 0..3 {
            g[r][c] = w[0][r] * v_mq[0][c] + w[1][r] * v_mq[1][c] + w[2][r] * v_mq[2][c];
        }
    }
    // rotation matrix of the unit quaternion -> its components
    let vq_hat = [
        2.0 * (qx * (g[2][1] - g[1][2]) + qy * (g[0][2] - g[2][0]) + qz * (g[1][0] - g[0][1])),
        2.0 * (-2.0 * qx * (g[1][1] + g[2][2])
            + qy * (g[1][0] + g[0][1])
            + qz * (g[2][0] + g[0][2])
            + qw * (g[2][1] - g[1][2])),
        2.0 * (qx * (g[1][0] + g[0][1]) - 2.0 * qy * (g[0][0] + g[2][2])
            + qz * (g[2][1] + g[1][2])
            + qw * (g[0][2] - g[2][0])),
        2.0 * (qx * (g[2][0] + g[0][2]) + qy * (g[2][1] + g[1][2])
            - 2.0 * qz * (g[0][0] + g[1][1])
            + qw * (g[1][0] - g[0][1])),
    ];
    // normalisation q / |q|
    let qh = [qw, qx, qy, qz];
    let d = vq_hat[0] * qh[0] + vq_hat[1] * qh[1] + vq_hat[2] * qh[2] + vq_hat[3] * qh[3];
    for c in 0..4 {
        out.quats[c] = (vq_hat[c] - d * qh[c]) / qn;
    }

    // ---- colour
    let mut v_dir_mean = [0.0f32; 3];
    match ctx.colors {
        Some(_) => out.color = v_rgb,
        None => {
            let (dir, dn) = p.view_dir(mean);
            let k = sc.sh_rest_k() * 3;
            let sh0 = &sc.sh0[i * 3..i * 3 + 3];
            let rest = &sc.sh_rest[i * k..i * k + k];
            let coef = |b: usize| -> [f32; 3] {
                if b == 0 {
                    [sh0[0], sh0[1], sh0[2]]
                } else {
                    [
                        rest[(b - 1) * 3],
                        rest[(b - 1) * 3 + 1],
                        rest[(b - 1) * 3 + 2],
                    ]
                }
            };
            // the clamp max(v + 0.5, 0) passes the gradient where v + 0.5 >= 0
            let mut basis = [0.0f32; 16];
            crate::raster::sh::basis(ctx.degree, dir, &mut basis);
            let nb = (ctx.degree as usize + 1) * (ctx.degree as usize + 1);
            let mut gate = [0.0f32; 3];
            for ch in 0..3 {
                let mut v = 0.0f32;
                for (b, yb) in basis.iter().enumerate().take(nb) {
                    v += yb * coef(b)[ch];
                }
                gate[ch] = if v + 0.5 >= 0.0 { v_rgb[ch] } else { 0.0 };
            }
            let v_d = sh_vjp(ctx.degree, dir, dn, coef, gate, &mut out.sh);
            for c in 0..3 {
                v_mean[c] += v_d[c];
            }
            v_dir_mean = v_d;
        }
    }

    if ctx.pose {
        // pc = W mean + t and Mq = W Rq: dL/dW = v_pc mean^T + v_Mq Rq^T, dL/dt = v_pc
        for r in 0..3 {
            for k in 0..3 {
                out.pose[r * 3 + k] = v_pc[r] * mean[k]
                    + v_mq[r][0] * rq[k][0]
                    + v_mq[r][1] * rq[k][1]
                    + v_mq[r][2] * rq[k][2];
            }
            out.pose[9 + r] = v_pc[r];
            out.pose[12 + r] = v_dir_mean[r];
        }
    }

    out.means = v_mean;
    out.scales = v_scale;
    out.log_scales = [
        v_scale[0] * scale[0],
        v_scale[1] * scale[1],
        v_scale[2] * scale[2],
    ];
    out.opacity = v_opacity;
    out.opacity_logit = v_opacity * opacity * (1.0 - opacity);
    out
}
