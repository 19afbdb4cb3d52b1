//! The per-Gaussian backward of [`super::gauss_bwd::gauss_backward`], 16 Gaussians at a time:
//! the inputs gathered into lane arrays (one array per value), the arithmetic as short loops
//! over the lanes that the compiler vectorises, the results in lane arrays.
//!
//! Every lane computes exactly the scalar function's operations in the same order (Rust never
//! reassociates or contracts float operations; branches become selects between the values
//! both sides compute), so the block gives the scalar function's bits in every lane; the
//! callers compile it for AVX-512 and AVX2 too and pick one at run time (as
//! `Projector::project_range` does), which changes the speed only. A test holds every output
//! to the scalar function bit for bit.
use super::gauss_bwd::{GaussCtx, POSE_LEN};
use super::sh_bwd::basis_grad;
use super::slots::slot;
use crate::fastmath;
use crate::raster::project::{cov2d, quat_rotation, Splat, EPS2D};
use crate::raster::{sh, Simd};

/// Gaussians per block.
pub(crate) const BLOCK: usize = 16;

/// One value per lane.
pub(crate) type Lane = [f32; BLOCK];

/// A block's inputs. Unused lanes hold zeros (their results are ignored).
#[derive(Default)]
pub(crate) struct InLanes {
    pub(super) mean: [Lane; 3],
    pub(super) q: [Lane; 4],
    pub(super) scale: [Lane; 3],
    pub(super) logit: Lane,
    pub(super) conic: [Lane; 3],
    pub(super) acc: [Lane; slot::LEN],
    /// SH coefficients, basis-major (k = 0 is sh0), only the bands in use.
    pub(super) coef: [[Lane; 3]; 16],
}

impl InLanes {
    /// Load Gaussian `i` (depth-sorted splat `s`, summed slots `acc`) into lane `l`.
    #[inline(always)]
    pub(crate) fn set(
        &mut self,
        ctx: &GaussCtx<'_>,
        l: usize,
        i: usize,
        s: &Splat,
        acc: &[f32; slot::LEN],
    ) {
        let sc = ctx.scene;
        for c in 0..3 {
            self.mean[c][l] = sc.means[i * 3 + c];
            self.scale[c][l] = ctx.scales[i * 3 + c];
            self.conic[c][l] = s.conic[c];
        }
        for c in 0..4 {
            self.q[c][l] = sc.quats[i * 4 + c];
        }
        self.logit[l] = sc.opacity_logits[i];
        for (k, v) in acc.iter().enumerate() {
            self.acc[k][l] = *v;
        }
        if ctx.colors.is_none() {
            let nb = (ctx.degree as usize + 1) * (ctx.degree as usize + 1);
            for ch in 0..3 {
                self.coef[0][ch][l] = sc.sh0[i * 3 + ch];
            }
            let k3 = sc.sh_rest_k() * 3;
            let rest = &sc.sh_rest[i * k3..i * k3 + k3];
            for b in 1..nb {
                for ch in 0..3 {
                    self.coef[b][ch][l] = rest[(b - 1) * 3 + ch];
                }
            }
        }
    }
}

/// A block's gradients, the fields of [`super::gauss_bwd::GaussGrad`] as lane arrays (given
/// colours' gradient is `rgb`).
#[derive(Default)]
pub(crate) struct GradLanes {
    pub means: [Lane; 3],
    pub quats: [Lane; 4],
    pub log_scales: [Lane; 3],
    pub opacity_logit: Lane,
    pub scales: [Lane; 3],
    pub opacity: Lane,
    pub sh: [[Lane; 3]; 16],
    pub means2d: [Lane; 2],
    pub means2d_abs: [Lane; 2],
    pub conic: [Lane; 3],
    pub rgb: [Lane; 3],
    pub opacity_eff: Lane,
    pub depth: Lane,
    pub pose: [Lane; POSE_LEN],
}

/// The backward of a loaded block into `o` (every lane; the caller reads the lanes it set).
/// The pose terms are computed whether or not the caller uses them (a few operations per lane).
#[inline(always)]
pub(crate) fn block_backward(ctx: &GaussCtx<'_>, g: &InLanes, o: &mut GradLanes) {
    let p = ctx.proj;
    // camera-space mean in float64 (its own loop: the f32 loops below stay 16 wide)
    let mut pc = [[0.0f32; BLOCK]; 3];
    for (r, v) in pc.iter_mut().enumerate() {
        for l in 0..BLOCK {
            v[l] = (p.rot[r][0] * g.mean[0][l] as f64
                + p.rot[r][1] * g.mean[1][l] as f64
                + p.rot[r][2] * g.mean[2][l] as f64
                + p.trans[r]) as f32;
        }
    }
    for l in 0..BLOCK {
        geometry_lane(ctx, g, &pc, o, l);
    }
    if ctx.colors.is_some() {
        // dL/d(colour) is `rgb`; no view-direction term
        for r in 0..3 {
            o.pose[12 + r] = [0.0; BLOCK];
        }
        return;
    }
    match ctx.degree {
        0 => colour_lanes::<0>(ctx, g, o),
        1 => colour_lanes::<1>(ctx, g, o),
        2 => colour_lanes::<2>(ctx, g, o),
        _ => colour_lanes::<3>(ctx, g, o),
    }
}

/// Lane `l`'s projection backward: the scalar function's code up to the colour, with the
/// per-Gaussian branches as selects.
#[inline(always)]
fn geometry_lane(ctx: &GaussCtx<'_>, g: &InLanes, pc: &[Lane; 3], o: &mut GradLanes, l: usize) {
    let p = ctx.proj;
    let acc = |k: usize| g.acc[k][l];
    let [ca, cb, cc] = [g.conic[0][l], g.conic[1][l], g.conic[2][l]];

    // ---- blend slot -> gradients of the splat's values
    let v_conic = [
        -0.5 * acc(slot::VDX2),
        -acc(slot::VDXDY),
        -0.5 * acc(slot::VDY2),
    ];
    let v_xy = [
        -(ca * acc(slot::VDX) + cb * acc(slot::VDY)),
        -(cb * acc(slot::VDX) + cc * acc(slot::VDY)),
    ];
    let v_rgb = [acc(slot::C0), acc(slot::C0 + 1), acc(slot::C0 + 2)];
    let v_z_blend = acc(slot::C0 + 3);
    for c in 0..2 {
        o.means2d[c][l] = v_xy[c];
    }
    o.means2d_abs[0][l] = acc(slot::ABSX);
    o.means2d_abs[1][l] = acc(slot::ABSY);
    for c in 0..3 {
        o.conic[c][l] = v_conic[c];
        o.rgb[c][l] = v_rgb[c];
    }
    o.depth[l] = v_z_blend;

    // ---- recompute the forward
    let mean = [g.mean[0][l], g.mean[1][l], g.mean[2][l]];
    let [x, y, z] = [pc[0][l], pc[1][l], pc[2][l]];
    let (fx, fy) = (p.fx, p.fy);
    let (ux, uy) = (x / z, y / z);
    let in_x = (ux >= -p.lim_x_neg) & (ux <= p.lim_x_pos);
    let in_y = (uy >= -p.lim_y_neg) & (uy <= p.lim_y_pos);
    let tx = z * ux.max(-p.lim_x_neg).min(p.lim_x_pos);
    let ty = z * uy.max(-p.lim_y_neg).min(p.lim_y_pos);
    let j00 = fx / z;
    let j02 = -fx * tx / (z * z);
    let j11 = fy / z;
    let j12 = -fy * ty / (z * z);

    let qv = [g.q[0][l], g.q[1][l], g.q[2][l], g.q[3][l]];
    let qn = (qv[0] * qv[0] + qv[1] * qv[1] + qv[2] * qv[2] + qv[3] * qv[3]).sqrt();
    let [qw, qx, qy, qz] = qv.map(|v| v / qn);
    let rq = quat_rotation(qw, qx, qy, qz);
    let scale = [g.scale[0][l], g.scale[1][l], g.scale[2][l]];
    let w = &p.rot32;
    let mut mq = [[0.0f32; 3]; 3];
    let mut t = [[0.0f32; 3]; 3];
    for r in 0..3 {
        for c in 0..3 {
            mq[r][c] = w[r][0] * rq[0][c] + w[r][1] * rq[1][c] + w[r][2] * rq[2][c];
            t[r][c] = mq[r][c] * scale[c];
        }
    }
    let (a0, a1, [c00, c01, c11]) = cov2d([j00, j02, j11, j12], &t);
    let (bx, by) = (c00 + EPS2D, c11 + EPS2D);
    let det = bx * by - c01 * c01;

    let logit = g.logit[l];
    let opacity = 1.0 / (1.0 + fastmath::exp(-logit));
    let ratio = (c00 * c11 - c01 * c01) / det;
    let comp = if p.antialiased {
        ratio.max(0.005 * 0.005).sqrt()
    } else {
        1.0
    };
    let o_eff = opacity * comp;

    // ---- opacity
    let v_o_eff = acc(slot::V0) / o_eff;
    o.opacity_eff[l] = v_o_eff;
    let v_opacity = v_o_eff * comp;
    let v_comp = v_o_eff * opacity;

    // ---- conic = inverse(Sigma2d + eps I)
    let (pa, pb, pc_) = (ca, cb, cc);
    let (va, vb, vc) = (v_conic[0], 0.5 * v_conic[1], v_conic[2]);
    let pv00 = pa * va + pb * vb;
    let pv01 = pa * vb + pb * vc;
    let pv10 = pb * va + pc_ * vb;
    let pv11 = pb * vb + pc_ * vc;
    let mut v_c00 = -(pv00 * pa + pv01 * pb);
    let mut v_c01 = -2.0 * (pv00 * pb + pv01 * pc_);
    let mut v_c11 = -(pv10 * pb + pv11 * pc_);
    // antialiasing, where the clamp passes the gradient (a select: both values are computed)
    let pass = p.antialiased & (ratio > 0.005 * 0.005);
    let v_ratio = v_comp * 0.5 / comp;
    let d00 = v_c00 + v_ratio * (c11 - ratio * by) / det;
    let d11 = v_c11 + v_ratio * (c00 - ratio * bx) / det;
    let d01 = v_c01 + v_ratio * (2.0 * c01 * (ratio - 1.0)) / det;
    v_c00 = if pass { d00 } else { v_c00 };
    v_c11 = if pass { d11 } else { v_c11 };
    v_c01 = if pass { d01 } else { v_c01 };

    // ---- Sigma2d = A A^T with A = J T
    let mut v_a0 = [0.0f32; 3];
    let mut v_a1 = [0.0f32; 3];
    for c in 0..3 {
        v_a0[c] = 2.0 * v_c00 * a0[c] + v_c01 * a1[c];
        v_a1[c] = v_c01 * a0[c] + 2.0 * v_c11 * a1[c];
    }
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

    // ---- camera-space mean (the frustum clamp's two cases as selects)
    let rz = 1.0 / z;
    let rz2 = rz * rz;
    let mut v_pc = [fx * rz * v_xy[0], fy * rz * v_xy[1], 0.0];
    v_pc[2] -= (fx * x * v_xy[0] + fy * y * v_xy[1]) * rz2;
    v_pc[2] -= fx * rz2 * v_j00 + fy * rz2 * v_j11;
    let px_in = v_pc[0] - fx * rz2 * v_j02;
    v_pc[0] = if in_x { px_in } else { v_pc[0] };
    let zx = if in_x {
        2.0 * fx * x * rz2 * rz * v_j02
    } else {
        fx * tx * rz2 * rz * v_j02
    };
    v_pc[2] += zx;
    let py_in = v_pc[1] - fy * rz2 * v_j12;
    v_pc[1] = if in_y { py_in } else { v_pc[1] };
    let zy = if in_y {
        2.0 * fy * y * rz2 * rz * v_j12
    } else {
        fy * ty * rz2 * rz * v_j12
    };
    v_pc[2] += zy;
    v_pc[2] += v_z_blend;
    for c in 0..3 {
        o.means[c][l] = w[0][c] * v_pc[0] + w[1][c] * v_pc[1] + w[2][c] * v_pc[2];
    }

    // ---- covariance factor
    let mut v_scale = [0.0f32; 3];
    let mut v_mq = [[0.0f32; 3]; 3];
    for c in 0..3 {
        for r in 0..3 {
            v_mq[r][c] = v_t[r][c] * scale[c];
            v_scale[c] += v_t[r][c] * mq[r][c];
        }
    }
    let mut gm = [[0.0f32; 3]; 3];
    for r in 0..3 {
        for c in 0..3 {
            gm[r][c] = w[0][r] * v_mq[0][c] + w[1][r] * v_mq[1][c] + w[2][r] * v_mq[2][c];
        }
    }
    let g_ = &gm;
    let vq_hat = [
        2.0 * (qx * (g_[2][1] - g_[1][2])
            + qy * (g_[0][2] - g_[2][0])
            + qz * (g_[1][0] - g_[0][1])),
        2.0 * (-2.0 * qx * (g_[1][1] + g_[2][2])
            + qy * (g_[1][0] + g_[0][1])
            + qz * (g_[2][0] + g_[0][2])
            + qw * (g_[2][1] - g_[1][2])),
        2.0 * (qx * (g_[1][0] + g_[0][1]) - 2.0 * qy * (g_[0][0] + g_[2][2])
            + qz * (g_[2][1] + g_[1][2])
            + qw * (g_[0][2] - g_[2][0])),
        2.0 * (qx * (g_[2][0] + g_[0][2]) + qy * (g_[2][1] + g_[1][2])
            - 2.0 * qz * (g_[0][0] + g_[1][1])
            + qw * (g_[1][0] - g_[0][1])),
    ];
    let qh = [qw, qx, qy, qz];
    let d = vq_hat[0] * qh[0] + vq_hat[1] * qh[1] + vq_hat[2] * qh[2] + vq_hat[3] * qh[3];
    for c in 0..4 {
        o.quats[c][l] = (vq_hat[c] - d * qh[c]) / qn;
    }

    // ---- camera gradient terms: dL/dW = v_pc mean^T + v_Mq Rq^T, dL/dt = v_pc
    for r in 0..3 {
        for k in 0..3 {
            o.pose[r * 3 + k][l] = v_pc[r] * mean[k]
                + v_mq[r][0] * rq[k][0]
                + v_mq[r][1] * rq[k][1]
                + v_mq[r][2] * rq[k][2];
        }
        o.pose[9 + r][l] = v_pc[r];
    }

    for c in 0..3 {
        o.scales[c][l] = v_scale[c];
        o.log_scales[c][l] = v_scale[c] * scale[c];
    }
    o.opacity[l] = v_opacity;
    o.opacity_logit[l] = v_opacity * opacity * (1.0 - opacity);
}

/// The SH colour's backward at degree `D` for every lane: coefficient gradients into `o.sh`,
/// the view direction's dL/d(mean) added to `o.means` and kept in the pose terms 12..15.
#[inline(always)]
fn colour_lanes<const D: usize>(ctx: &GaussCtx<'_>, g: &InLanes, o: &mut GradLanes) {
    let p = ctx.proj;
    let nb = (D + 1) * (D + 1);
    for l in 0..BLOCK {
        let mean = [g.mean[0][l], g.mean[1][l], g.mean[2][l]];
        let (dir, dn) = p.view_dir(mean);
        let mut basis = [0.0f32; 16];
        sh::basis(D as u8, dir, &mut basis);
        // the clamp max(v + 0.5, 0) passes the gradient where v + 0.5 >= 0
        let mut gate = [0.0f32; 3];
        for (ch, gt) in gate.iter_mut().enumerate() {
            let mut v = 0.0f32;
            for (b, yb) in basis.iter().enumerate().take(nb) {
                v += yb * g.coef[b][ch][l];
            }
            let v_rgb = o.rgb[ch][l];
            *gt = if v + 0.5 >= 0.0 { v_rgb } else { 0.0 };
        }
        // `sh_vjp`
        for (k, yb) in basis.iter().enumerate().take(nb) {
            for ch in 0..3 {
                o.sh[k][ch][l] = yb * gate[ch];
            }
        }
        let mut v_d = [0.0f32; 3];
        if D > 0 {
            let mut db = [[0.0f32; 3]; 16];
            basis_grad(D as u8, dir, &mut db);
            let mut v_hat = [0.0f32; 3];
            for (k, dbk) in db.iter().enumerate().take(nb).skip(1) {
                let c = [g.coef[k][0][l], g.coef[k][1][l], g.coef[k][2][l]];
                let wk = c[0] * gate[0] + c[1] * gate[1] + c[2] * gate[2];
                for a in 0..3 {
                    v_hat[a] += wk * dbk[a];
                }
            }
            let dot = v_hat[0] * dir[0] + v_hat[1] * dir[1] + v_hat[2] * dir[2];
            let zero = dn <= 0.0;
            for a in 0..3 {
                let v = (v_hat[a] - dot * dir[a]) / dn;
                v_d[a] = if zero { 0.0 } else { v };
            }
        }
        for c in 0..3 {
            o.means[c][l] += v_d[c];
            o.pose[12 + c][l] = v_d[c];
        }
    }
}

/// The per-Gaussian backward of one projection part (its visible splats `ss` in index order,
/// their Gaussian indices `ids` and sorted positions `pos`, the summed slots `acc` by sorted
/// position), block by block, each Gaussian's gradients added through `scatter`. Returns the
/// part's camera-gradient sum, added in index order in float64 (zeros unless `ctx.pose`).
/// `simd` (the frame's resolved kernel level, `MORPHGS_SIMD`) picks the build of the same code:
/// AVX-512, AVX2 or the baseline target's; all give the same bits.
///
/// # Safety
/// No other call may put the same Gaussian indices concurrently (see [`super::scatter::Scatter::put_lane`]).
pub(super) unsafe fn part_backward(
    simd: Simd,
    ctx: &GaussCtx<'_>,
    ss: &[Splat],
    ids: &[u32],
    pos: &[u32],
    acc: super::slots::Sums<'_>,
    scatter: &super::scatter::Scatter<'_>,
) -> [f64; POSE_LEN] {
    #[cfg(target_arch = "x86_64")]
    {
        let avx2 = std::is_x86_feature_detected!("avx2");
        let avx512 = avx2
            && std::is_x86_feature_detected!("avx512f")
            && std::is_x86_feature_detected!("avx512dq")
            && std::is_x86_feature_detected!("avx512vl");
        match simd {
            Simd::Auto | Simd::Avx512 if avx512 => {
                // SAFETY: the CPU has these features (checked just above); the caller's
                // contract.
                return unsafe { part_avx512(ctx, ss, ids, pos, acc, scatter) };
            }
            Simd::Auto | Simd::Avx512 | Simd::Avx2 if avx2 => {
                // SAFETY: the CPU has AVX2 (checked just above); the caller's contract.
                return unsafe { part_avx2(ctx, ss, ids, pos, acc, scatter) };
            }
            _ => {}
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = simd;
    // SAFETY: the caller's contract.
    unsafe { part_impl::<false>(ctx, ss, ids, pos, acc, scatter) }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
unsafe fn part_avx512(
    ctx: &GaussCtx<'_>,
    ss: &[Splat],
    ids: &[u32],
    pos: &[u32],
    acc: super::slots::Sums<'_>,
    scatter: &super::scatter::Scatter<'_>,
) -> [f64; POSE_LEN] {
    // SAFETY: the caller's contract; the CPU has AVX-512F (this function's features).
    unsafe { part_impl::<true>(ctx, ss, ids, pos, acc, scatter) }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn part_avx2(
    ctx: &GaussCtx<'_>,
    ss: &[Splat],
    ids: &[u32],
    pos: &[u32],
    acc: super::slots::Sums<'_>,
    scatter: &super::scatter::Scatter<'_>,
) -> [f64; POSE_LEN] {
    // SAFETY: the caller's contract.
    unsafe { part_impl::<false>(ctx, ss, ids, pos, acc, scatter) }
}

/// Ask for the stored parameters of Gaussian `i` that [`InLanes::set`] reads.
#[inline(always)]
fn prefetch_inputs(ctx: &GaussCtx<'_>, i: usize) {
    let sc = ctx.scene;
    crate::mem::prefetch_ptr(sc.means.as_ptr(), i * 3);
    crate::mem::prefetch_ptr(sc.quats.as_ptr(), i * 4);
    crate::mem::prefetch_ptr(ctx.scales.as_ptr(), i * 3);
    crate::mem::prefetch_ptr(sc.opacity_logits.as_ptr(), i);
    if ctx.colors.is_none() {
        crate::mem::prefetch_ptr(sc.sh0.as_ptr(), i * 3);
        let k3 = sc.sh_rest_k() * 3;
        let used = ((ctx.degree as usize + 1) * (ctx.degree as usize + 1) - 1) * 3;
        for o in (0..used).step_by(16).chain((used > 0).then_some(used - 1)) {
            crate::mem::prefetch_ptr(sc.sh_rest.as_ptr(), i * k3 + o);
        }
    }
}

/// The block loop; with `V512` (the AVX-512 build only: the CPU has AVX-512F) the inputs are
/// loaded through `gauss_block_avx512`'s transposes.
#[inline(always)]
unsafe fn part_impl<const V512: bool>(
    ctx: &GaussCtx<'_>,
    ss: &[Splat],
    ids: &[u32],
    pos: &[u32],
    acc: super::slots::Sums<'_>,
    scatter: &super::scatter::Scatter<'_>,
) -> [f64; POSE_LEN] {
    let mut part = [0.0f64; POSE_LEN];
    let mut g = InLanes::default();
    let mut o = GradLanes::default();
    let n_all = ss.len().min(ids.len()).min(pos.len());
    let mut j0 = 0;
    while j0 < n_all {
        let n = BLOCK.min(n_all - j0);
        // the sums lie in depth order (a cache miss each otherwise): fetch the next block's
        for &ahead in pos.iter().skip(j0 + BLOCK).take(BLOCK) {
            crate::mem::prefetch_at(acc.acc, ahead as usize);
        }
        // and the next block's splats (a cache line each, cold since the projection), its
        // stored parameters and the gradient rows it will update
        for (sp, &i) in ss.iter().zip(ids).skip(j0 + BLOCK).take(BLOCK) {
            crate::mem::prefetch(sp);
            prefetch_inputs(ctx, i as usize);
            scatter.prefetch(i as usize, ctx.degree);
        }
        let blk = j0..j0 + n;
        #[cfg(target_arch = "x86_64")]
        if V512 {
            // SAFETY: V512 only in the AVX-512 build; ids and positions index the scene and
            // `acc` (the caller's contract).
            unsafe {
                super::gauss_block_avx512::load_block(
                    ctx,
                    &mut g,
                    &ss[blk.clone()],
                    &ids[blk.clone()],
                    &pos[blk.clone()],
                    acc,
                )
            };
        }
        if !V512 || cfg!(not(target_arch = "x86_64")) {
            for l in 0..n {
                let j = j0 + l;
                g.set(ctx, l, ids[j] as usize, &ss[j], acc.get(pos[j] as usize));
            }
        }
        // lanes n.. keep the previous block's values (zeros from the AVX-512 loads):
        // computed, never read
        block_backward(ctx, &g, &mut o);
        for l in 0..n {
            let j = j0 + l;
            if ctx.pose {
                for (a, v) in part.iter_mut().zip(&o.pose) {
                    *a += v[l] as f64;
                }
            }
            // SAFETY: the caller's contract.
            unsafe { scatter.put_lane(ids[j] as usize, &ss[j], &o, l, ctx.degree) };
        }
        j0 += n;
    }
    part
}
