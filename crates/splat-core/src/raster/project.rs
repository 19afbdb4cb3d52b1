//! Projection of 3D Gaussians to screen-space splats (SPEC §4 steps 1-5), as gsplat's
//! `fully_fused_projection` with opacities: EWA Jacobian with the frustum clamp, eps2d low-pass,
//! optional antialiasing compensation, the 1/255 opacity cull and the opacity-aware extent.
use rayon::prelude::*;

use super::share::{ChunkColours, FrameColours};
use super::{sh, RenderOptions, Simd};
use crate::camera::Camera;
use crate::fastmath;
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
            rot_gain: spectral_norm_bound(&rot),
            antialiased: opts.antialiased,
            sh_degree,
            simd: opts.simd.resolve(),
        }
    }

    /// Project Gaussian `i`: the splat and its opacity, `None` when it is culled or holds
    /// non-finite values. The one-Gaussian form of [`Projector::project_range`] (a block with
    /// one lane), so it gives the same bits.
    fn project_with_opacity(&self, scene: &SceneView<'_>, i: usize) -> Option<(Splat, f32)> {
        let mut g = Lanes::default();
        g.set(0, scene, i);
        let sc = self.screen(&g);
        if !sc.ok[0] {
            return None;
        }
        let fp = self.footprint(&g, &sc);
        if !fp.ok[0] {
            return None;
        }
        let mut out = Vec::with_capacity(1);
        let ok = self.finish_block::<false>(
            scene,
            &[i],
            &g,
            &sc,
            &fp,
            &mut ChunkColours::Off,
            &mut out,
            None,
        );
        ok[0].then(|| (out[0], fp.opacity[0]))
    }

    /// Project Gaussians `lo..hi` and append the visible splats to `out` in index order.
    /// Stage 1 (camera space, Jacobian, the off-screen early out) runs on every Gaussian and
    /// stage 2 (covariance, conic, opacity, box) on stage 1's survivors, both 16 lanes at a time
    /// as short loops over lane arrays that the compiler vectorises (this function is compiled
    /// for AVX-512 and AVX2 too and picked at run time; no FMA contraction and `fastmath`'s
    /// exp and ln, so every build gives the same bits). Stage 3 (SH colour, the splat) runs per
    /// visible Gaussian.
    pub(crate) fn project_range(
        &self,
        scene: &SceneView<'_>,
        lo: usize,
        hi: usize,
        out: &mut Vec<Splat>,
        ids: Option<&mut Vec<u32>>,
    ) {
        self.project_range_sharing(scene, lo, hi, out, ids, &mut ChunkColours::Off)
    }

    /// [`Projector::project_range`] recording or reusing shared colours (see [`super::share`]).
    pub(crate) fn project_range_sharing(
        &self,
        scene: &SceneView<'_>,
        lo: usize,
        hi: usize,
        out: &mut Vec<Splat>,
        ids: Option<&mut Vec<u32>>,
        colours: &mut ChunkColours<'_>,
    ) {
        #[cfg(target_arch = "x86_64")]
        match self.simd {
            // SAFETY: `Simd::resolve` gives Avx512 only on a CPU with AVX-512 F, VL, DQ and
            // BW, and AVX2 is checked here (the features this build enables).
            Simd::Avx512 if std::is_x86_feature_detected!("avx2") => unsafe {
                self.project_range_avx512(scene, lo, hi, out, ids, colours)
            },
            // SAFETY: `Simd::resolve` gives Avx2 only on a CPU with AVX2 and FMA.
            Simd::Avx2 => unsafe { self.project_range_avx2(scene, lo, hi, out, ids, colours) },
            _ => self.project_range_impl::<false>(scene, lo, hi, out, ids, colours),
        }
        #[cfg(not(target_arch = "x86_64"))]
        self.project_range_impl::<false>(scene, lo, hi, out, ids, colours)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx512bw,avx2")]
    fn project_range_avx512(
        &self,
        scene: &SceneView<'_>,
        lo: usize,
        hi: usize,
        out: &mut Vec<Splat>,
        ids: Option<&mut Vec<u32>>,
        colours: &mut ChunkColours<'_>,
    ) {
        self.project_range_impl::<true>(scene, lo, hi, out, ids, colours)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn project_range_avx2(
        &self,
        scene: &SceneView<'_>,
        lo: usize,
        hi: usize,
        out: &mut Vec<Splat>,
        ids: Option<&mut Vec<u32>>,
        colours: &mut ChunkColours<'_>,
    ) {
        self.project_range_impl::<false>(scene, lo, hi, out, ids, colours)
    }

    /// `ids`, when given, receives the Gaussian index of every splat pushed to `out`.
    #[inline(always)]
    fn project_range_impl<const X: bool>(
        &self,
        scene: &SceneView<'_>,
        lo: usize,
        hi: usize,
        out: &mut Vec<Splat>,
        mut ids: Option<&mut Vec<u32>>,
        colours: &mut ChunkColours<'_>,
    ) {
        // survivors of sparse blocks waiting for a block of their own, in index order
        let mut pending = [0usize; 2 * BLOCK];
        let mut np = 0;
        let mut i0 = lo;
        while i0 < hi {
            let n = BLOCK.min(hi - i0);
            // stage 1 reads only the means and scales (24 of a Gaussian's 56 bytes outside
            // the SH): most Gaussians of a large scene are culled here
            // the scales only for a block with a mean between the near and far planes
            let mut g = Lanes::default();
            deinterleave::<X, _>(scene.means, i0, n, &mut g.mean);
            if !self.any_in_depth::<X>(&g) {
                i0 += n;
                continue;
            }
            deinterleave::<X, _>(scene.log_scales, i0, n, &mut g.ls);
            let sc = self.screen(&g);
            // the survivors' indices, compacted without branches
            let mut idx = [0usize; BLOCK];
            let mut m = 0;
            for (l, &ok) in sc.ok.iter().enumerate().take(n) {
                idx[m] = i0 + l;
                m += ok as usize;
            }
            if m >= DENSE {
                // most of the block survives: stage 2 on it as it is (its stage 1 lanes and
                // contiguous loads) rather than gathering the survivors and redoing stage 1;
                // the pending survivors come first, to keep the index order
                if np > 0 {
                    self.project_survivors::<X>(
                        scene,
                        &pending[..np],
                        out,
                        ids.as_deref_mut(),
                        colours,
                    );
                    np = 0;
                }
                for &i in &idx[..m] {
                    colours.prefetch(i);
                }
                deinterleave::<X, _>(scene.quats, i0, n, &mut g.q);
                deinterleave::<X, _>(scene.sh0, i0, n, &mut g.sh0);
                deinterleave::<X, _>(
                    scene.opacity_logits,
                    i0,
                    n,
                    std::array::from_mut(&mut g.logit),
                );
                let fp = self.footprint(&g, &sc);
                let block: [usize; BLOCK] = std::array::from_fn(|l| i0 + l);
                self.finish_block::<X>(
                    scene,
                    &block[..n],
                    &g,
                    &sc,
                    &fp,
                    colours,
                    out,
                    ids.as_deref_mut(),
                );
            } else {
                pending[np..np + BLOCK].copy_from_slice(&idx);
                np += m;
                if np >= BLOCK {
                    self.project_survivors::<X>(
                        scene,
                        &pending[..BLOCK],
                        out,
                        ids.as_deref_mut(),
                        colours,
                    );
                    pending.copy_within(BLOCK..2 * BLOCK, 0);
                    np -= BLOCK;
                }
            }
            i0 += n;
        }
        if np > 0 {
            self.project_survivors::<X>(scene, &pending[..np], out, ids, colours);
        }
    }

    /// Stages 2 and 3 for up to 16 stage-1 survivors `block` gathered into one block (stage 1
    /// again for them: its lanes are not kept).
    #[inline(always)]
    fn project_survivors<const X: bool>(
        &self,
        scene: &SceneView<'_>,
        block: &[usize],
        out: &mut Vec<Splat>,
        ids: Option<&mut Vec<u32>>,
        colours: &mut ChunkColours<'_>,
    ) {
        let k = scene.sh_rest_k() * 3;
        // stage 3 reads each survivor's SH (180 bytes at degree 3, the first touch of
        // them) or its shared colour at random: ask for them before stage 2's arithmetic
        for &i in block {
            if !colours.prefetch(i) && k > 0 {
                let rest = &scene.sh_rest[i * k..i * k + k];
                for j in (0..k).step_by(16).chain([k - 1]) {
                    crate::mem::prefetch(&rest[j]);
                }
            }
        }
        let mut g = Lanes::default();
        for (l, &i) in block.iter().enumerate() {
            g.set(l, scene, i);
        }
        let sc = self.screen(&g);
        let fp = self.footprint(&g, &sc);
        self.finish_block::<X>(scene, block, &g, &sc, &fp, colours, out, ids);
    }

    /// Whether any lane's camera-space z lies between the near and far planes, computed as
    /// [`Projector::screen`] computes it (the same bits): a block of Gaussians all behind the
    /// camera or beyond the far plane needs nothing but its means read.
    #[inline(always)]
    fn any_in_depth<const X: bool>(&self, g: &Lanes) -> bool {
        #[cfg(target_arch = "x86_64")]
        if X {
            // SAFETY: `X` is true only in the build compiled for AVX-512 (on a CPU that has it)
            return unsafe {
                avx512::any_in_depth(&self.rot[2], self.trans[2], self.near, self.far, &g.mean)
            };
        }
        let (rot, tr) = (&self.rot[2], self.trans[2]);
        let mut any = false;
        for l in 0..BLOCK {
            let z = rot[0] * g.mean[0][l] as f64
                + rot[1] * g.mean[1][l] as f64
                + rot[2] * g.mean[2][l] as f64
                + tr;
            any |= (z > self.near) & (z < self.far);
        }
        any
    }

    /// Stage 1 for a block: camera space (float64, so far-from-origin scenes keep their
    /// precision), the projected mean, the EWA Jacobian with the frustum clamp, and the early
    /// out for Gaussians far off-screen: the box half-size on axis a is at most
    /// 3.33 sqrt(|J_a|^2 s_max^2 + eps2d) (|T^T v| <= s_max |v|), so a mean farther out than that
    /// (plus a pixel for ceil and rounding) is culled anyway.
    #[inline(always)]
    fn screen(&self, g: &Lanes) -> ScreenLanes {
        let mut o = ScreenLanes::default();
        let (rot, tr) = (&self.rot, &self.trans);
        let mut x = [0.0f32; BLOCK];
        let mut y = [0.0f32; BLOCK];
        // one loop per lane for the float64 part (LLVM scattered a row-by-row form into a
        // stack array and stalled reading it back)
        for l in 0..BLOCK {
            let m = [
                g.mean[0][l] as f64,
                g.mean[1][l] as f64,
                g.mean[2][l] as f64,
            ];
            let pc =
                [0, 1, 2].map(|r| rot[r][0] * m[0] + rot[r][1] * m[1] + rot[r][2] * m[2] + tr[r]);
            // also rejects NaN depths
            o.ok[l] =
                (pc[2] > self.near) & (pc[2] < self.far) & pc[0].is_finite() & pc[1].is_finite();
            x[l] = pc[0] as f32;
            y[l] = pc[1] as f32;
            o.z[l] = pc[2] as f32;
        }
        for l in 0..BLOCK {
            o.ok[l] &= fin(g.ls[0][l]) & fin(g.ls[1][l]) & fin(g.ls[2][l]);
        }
        let (fx, fy) = (self.fx, self.fy);
        for l in 0..BLOCK {
            // min/max rather than clamp: lanes of culled Gaussians may hold NaN
            let z = o.z[l];
            let tx = z * (x[l] / z).max(-self.lim_x_neg).min(self.lim_x_pos);
            let ty = z * (y[l] / z).max(-self.lim_y_neg).min(self.lim_y_pos);
            o.j[0][l] = fx / z;
            o.j[1][l] = -fx * tx / (z * z);
            o.j[2][l] = fy / z;
            o.j[3][l] = -fy * ty / (z * z);
            o.xy[0][l] = fx * x[l] / z + self.cx;
            o.xy[1][l] = fy * y[l] / z + self.cy;
        }
        let mut s_max = [0.0f32; BLOCK];
        for l in 0..BLOCK {
            s_max[l] = fastmath::exp(g.ls[0][l].max(g.ls[1][l]).max(g.ls[2][l])) * self.rot_gain;
        }
        for l in 0..BLOCK {
            let [j00, j02, j11, j12] = [o.j[0][l], o.j[1][l], o.j[2][l], o.j[3][l]];
            let s2 = s_max[l] * s_max[l];
            let bx = 3.33 * ((j00 * j00 + j02 * j02) * s2 + EPS2D).sqrt() + 1.0;
            let by = 3.33 * ((j11 * j11 + j12 * j12) * s2 + EPS2D).sqrt() + 1.0;
            let (px, py) = (o.xy[0][l], o.xy[1][l]);
            o.ok[l] &= (px + bx > 0.0)
                & (px - bx < self.width)
                & (py + by > 0.0)
                & (py - by < self.height);
        }
        o
    }

    /// Stage 2 for a block: covariance factor T = W R(q) S, the 2D covariance J T (J T)^T plus
    /// eps2d, conic, opacity (with the antialiasing compensation), the 1/255 cull and the box.
    #[inline(always)]
    fn footprint(&self, g: &Lanes, sc: &ScreenLanes) -> FootLanes {
        let mut o = FootLanes::default();
        let mut q = [[0.0f32; BLOCK]; 4];
        for l in 0..BLOCK {
            let v = [g.q[0][l], g.q[1][l], g.q[2][l], g.q[3][l]];
            let qn = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2] + v[3] * v[3]).sqrt();
            // (the DC colour's test is here rather than in stage 1, which does not read it)
            o.ok[l] = sc.ok[l]
                & (qn > 0.0)
                & qn.is_finite()
                & fin(g.sh0[0][l])
                & fin(g.sh0[1][l])
                & fin(g.sh0[2][l]);
            for c in 0..4 {
                q[c][l] = v[c] / qn;
            }
        }
        let mut s = [[0.0f32; BLOCK]; 3];
        for (c, sc_) in s.iter_mut().enumerate() {
            for l in 0..BLOCK {
                sc_[l] = fastmath::exp(g.ls[c][l]);
            }
        }
        let mut cov = [[0.0f32; BLOCK]; 4]; // c00, c01, c11, det_orig
        for l in 0..BLOCK {
            let (qw, qx, qy, qz) = (q[0][l], q[1][l], q[2][l], q[3][l]);
            let rq = quat_rotation(qw, qx, qy, qz);
            // T = W R S (3x3)
            let mut t = [[0.0f32; 3]; 3];
            for r in 0..3 {
                for c in 0..3 {
                    let w = &self.rot32[r];
                    t[r][c] = (w[0] * rq[0][c] + w[1] * rq[1][c] + w[2] * rq[2][c]) * s[c][l];
                }
            }
            // A = J T (2x3); Sigma_2d = A A^T
            let j = [sc.j[0][l], sc.j[1][l], sc.j[2][l], sc.j[3][l]];
            let (_, _, [c00, c01, c11]) = cov2d(j, &t);
            cov[0][l] = c00;
            cov[1][l] = c01;
            cov[2][l] = c11;
            cov[3][l] = c00 * c11 - c01 * c01;
        }
        let mut det = [0.0f32; BLOCK];
        for l in 0..BLOCK {
            let (c00, c01, c11) = (cov[0][l] + EPS2D, cov[1][l], cov[2][l] + EPS2D);
            det[l] = c00 * c11 - c01 * c01;
            o.ok[l] &= (det[l] > 0.0) & det[l].is_finite();
            let inv = 1.0 / det[l];
            o.conic[0][l] = c11 * inv;
            o.conic[1][l] = -c01 * inv;
            o.conic[2][l] = c00 * inv;
            o.c00[l] = c00;
            o.c11[l] = c11;
        }
        for l in 0..BLOCK {
            let mut opacity = 1.0 / (1.0 + fastmath::exp(-g.logit[l]));
            if self.antialiased {
                opacity *= (cov[3][l] / det[l]).max(0.005 * 0.005).sqrt();
            }
            // also rejects a NaN opacity (and so a NaN logit's)
            o.ok[l] &= (opacity >= ALPHA_THRESHOLD) & g.logit[l].is_finite();
            o.opacity[l] = opacity;
        }
        for l in 0..BLOCK {
            o.ln_over[l] = fastmath::ln(o.opacity[l] / ALPHA_THRESHOLD);
        }
        for l in 0..BLOCK {
            let extent = (2.0 * o.ln_over[l]).sqrt().min(3.33);
            let r0 = (extent * o.c00[l].sqrt()).ceil();
            let r1 = (extent * o.c11[l].sqrt()).ceil();
            let (px, py) = (sc.xy[0][l], sc.xy[1][l]);
            o.ok[l] &= (r0 > 0.0)
                & (r1 > 0.0)
                & (px + r0 > 0.0)
                & (px - r0 < self.width)
                & (py + r1 > 0.0)
                & (py - r1 < self.height);
            o.radius[0][l] = r0;
            o.radius[1][l] = r1;
        }
        o
    }

    /// Stage 3 for a block of survivors (`block[l]` in lane l, `g`, `sc` and `fp` their
    /// stages' lanes): the SH colour along the view direction (the basis in lanes, the sum per
    /// Gaussian; or the colour another scene recorded this frame) and the splats' blend
    /// constants in lanes; the finite splats go to `out` (and their indices to `ids`) in lane
    /// order. Returns the lanes written, as a mask. A lane is dropped when any stored value of
    /// its Gaussian is non-finite: stage 2 rejects non-finite means, scales, opacities, DC
    /// colours and quaternions (a quaternion with a non-finite value has a non-finite norm),
    /// this stage the higher SH bands, including those the render does not use.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn finish_block<const X: bool>(
        &self,
        scene: &SceneView<'_>,
        block: &[usize],
        g: &Lanes,
        sc: &ScreenLanes,
        fp: &FootLanes,
        colours: &mut ChunkColours<'_>,
        out: &mut Vec<Splat>,
        ids: Option<&mut Vec<u32>>,
    ) -> [bool; BLOCK] {
        let n = block.len();
        let mut ok = [false; BLOCK];
        ok[..n].copy_from_slice(&fp.ok[..n]);
        let degree = self.sh_degree;
        // colour along the view direction mean - camera centre, first for every lane
        let mut basis = [[0.0f32; BLOCK]; 16];
        if degree > 0 {
            let mut dir = [[0.0f32; BLOCK]; 3];
            for l in 0..BLOCK {
                let d = [0, 1, 2].map(|c| (g.mean[c][l] as f64 - self.center[c]) as f32);
                let dn = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                for c in 0..3 {
                    dir[c][l] = if dn > 0.0 { d[c] / dn } else { 0.0 };
                }
            }
            sh::basis_lanes(degree, &dir, &mut basis);
        } else {
            basis[0] = [0.282_094_8; BLOCK];
        }
        let mut rgb = [[0.0f32; BLOCK]; 3];
        for ch in 0..3 {
            for l in 0..BLOCK {
                // (degree 0's colour, as `sh::color_from_basis` computes it)
                rgb[ch][l] = (basis[0][l] * g.sh0[ch][l] + 0.5).max(0.0);
            }
        }
        let k = scene.sh_rest_k() * 3;
        for l in 0..n {
            if !ok[l] {
                continue;
            }
            let i = block[l];
            let c = match colours.lookup(i) {
                // another scene's Gaussian with this mean and these SH bits (so finite SH) got
                // this colour this frame
                Some(c) => c,
                None => {
                    let rest = &scene.sh_rest[i * k..i * k + k];
                    // every stored value must be finite, including SH bands this render does
                    // not use
                    if !all_finite(rest) {
                        ok[l] = false;
                        continue;
                    }
                    let c = if degree > 0 {
                        let b = std::array::from_fn(|j| basis[j][l]);
                        let sh0 = [g.sh0[0][l], g.sh0[1][l], g.sh0[2][l]];
                        sh::color_from_basis(degree, &b, sh0, rest)
                    } else {
                        [rgb[0][l], rgb[1][l], rgb[2][l]]
                    };
                    colours.record(i, c);
                    c
                }
            };
            for ch in 0..3 {
                rgb[ch][l] = c[ch];
            }
        }
        // the splats' 16 values in lanes, in `Splat`'s field order
        let mut f = [[0.0f32; BLOCK]; 16];
        for l in 0..BLOCK {
            let conic = [fp.conic[0][l], fp.conic[1][l], fp.conic[2][l]];
            let level = fp.ln_over[l] * 1.0001 + 1e-4;
            f[0][l] = sc.xy[0][l];
            f[1][l] = sc.xy[1][l];
            f[2][l] = conic[0];
            f[3][l] = conic[1];
            f[4][l] = conic[2];
            f[5][l] = fastmath::ln(fp.opacity[l]);
            f[6][l] = rgb[0][l];
            f[7][l] = rgb[1][l];
            f[8][l] = rgb[2][l];
            f[9][l] = sc.z[l];
            f[10][l] = fp.radius[0][l];
            f[11][l] = fp.radius[1][l];
            f[12][l] = 2.0 * conic[0] * level;
            f[13][l] = conic[0] * conic[2] - conic[1] * conic[1];
            f[14][l] = 1.0 / conic[0];
            // sqrt(2 level a / det) = sqrt(2 level Sigma_yy), the robust form
            f[15][l] = (2.0 * level * fp.c11[l]).sqrt();
        }
        let mut big = [0u32; BLOCK];
        for v in &f {
            for l in 0..BLOCK {
                big[l] = big[l].max(v[l].to_bits() & 0x7FFF_FFFF);
            }
        }
        for l in 0..BLOCK {
            ok[l] &= big[l] < 0x7F80_0000;
        }
        write_splats::<X>(&f, &ok, block, out, ids);
        ok
    }
}

/// Whether a float is finite (a bit test that vectorises).
#[inline(always)]
fn fin(v: f32) -> bool {
    v.to_bits() & 0x7FFF_FFFF < 0x7F80_0000
}

/// Gaussians per vectorised block of the projection.
const BLOCK: usize = 16;

/// Stage-1 survivors from which a block goes to stage 2 as it is rather than gathered with
/// other blocks' survivors.
const DENSE: usize = 8;

/// Lane l of `dst[c]` = `src[(i0 + l) * C + c]` for the `n <= BLOCK` Gaussians from `i0` (a
/// full block as one contiguous slice, so the compiler can shuffle it into lanes).
#[inline(always)]
fn deinterleave<const X: bool, const C: usize>(
    src: &[f32],
    i0: usize,
    n: usize,
    dst: &mut [[f32; BLOCK]; C],
) {
    #[cfg(target_arch = "x86_64")]
    if X && n == BLOCK && matches!(C, 1 | 3 | 4) {
        // SAFETY: `X` is true only in the build compiled for AVX-512 (on a CPU that has it)
        unsafe { avx512::deinterleave(&src[i0 * C..(i0 + BLOCK) * C], dst) };
        return;
    }
    if n == BLOCK {
        let v = &src[i0 * C..(i0 + BLOCK) * C];
        for l in 0..BLOCK {
            for c in 0..C {
                dst[c][l] = v[l * C + c];
            }
        }
    } else {
        for l in 0..n {
            for c in 0..C {
                dst[c][l] = src[(i0 + l) * C + c];
            }
        }
    }
}

/// A block's stored inputs, one array per value so loops over lanes vectorise. Unused lanes
/// hold zeros (their results are ignored).
#[derive(Default)]
struct Lanes {
    mean: [[f32; BLOCK]; 3],
    q: [[f32; BLOCK]; 4],
    ls: [[f32; BLOCK]; 3],
    logit: [f32; BLOCK],
    sh0: [[f32; BLOCK]; 3],
}

impl Lanes {
    /// Load Gaussian `i` into lane `l`.
    #[inline(always)]
    fn set(&mut self, l: usize, scene: &SceneView<'_>, i: usize) {
        for c in 0..3 {
            self.mean[c][l] = scene.means[i * 3 + c];
            self.ls[c][l] = scene.log_scales[i * 3 + c];
            self.sh0[c][l] = scene.sh0[i * 3 + c];
        }
        for c in 0..4 {
            self.q[c][l] = scene.quats[i * 4 + c];
        }
        self.logit[l] = scene.opacity_logits[i];
    }
}

/// Stage 1 results of a block.
#[derive(Default)]
struct ScreenLanes {
    ok: [bool; BLOCK],
    z: [f32; BLOCK],
    xy: [[f32; BLOCK]; 2],
    /// j00, j02, j11, j12
    j: [[f32; BLOCK]; 4],
}

/// Stage 2 results of a block.
#[derive(Default)]
struct FootLanes {
    ok: [bool; BLOCK],
    conic: [[f32; BLOCK]; 3],
    c00: [f32; BLOCK],
    c11: [f32; BLOCK],
    opacity: [f32; BLOCK],
    ln_over: [f32; BLOCK],
    radius: [[f32; BLOCK]; 2],
}

/// A = J T (J the EWA Jacobian [j00, j02, j11, j12] of its two non-zero rows, T = W R S) and
/// the 2D covariance A A^T without eps2d: (A's rows, [c00, c01, c11]). The forward and the
/// backward (which recomputes it) share it, so they round alike.
#[inline(always)]
pub(crate) fn cov2d(
    [j00, j02, j11, j12]: [f32; 4],
    t: &[[f32; 3]; 3],
) -> ([f32; 3], [f32; 3], [f32; 3]) {
    let mut a0 = [0.0f32; 3];
    let mut a1 = [0.0f32; 3];
    for c in 0..3 {
        a0[c] = j00 * t[0][c] + j02 * t[2][c];
        a1[c] = j11 * t[1][c] + j12 * t[2][c];
    }
    let c00 = a0[0] * a0[0] + a0[1] * a0[1] + a0[2] * a0[2];
    let c01 = a0[0] * a1[0] + a0[1] * a1[1] + a0[2] * a1[2];
    let c11 = a1[0] * a1[0] + a1[1] * a1[1] + a1[2] * a1[2];
    (a0, a1, [c00, c01, c11])
}

/// An upper bound of the largest singular value of `m`: 1 (plus rounding slack) for a rotation,
/// else the Frobenius norm, so the off-screen early out stays conservative for any matrix.
/// Rotation matrix of a unit quaternion (w, x, y, z), row-major: the one formula the forward,
/// the backward and densification share (same operations, so the same bits everywhere).
#[inline(always)]
pub(crate) fn quat_rotation(qw: f32, qx: f32, qy: f32, qz: f32) -> [[f32; 3]; 3] {
    [
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
    ]
}

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

/// Append lane l's splat (`f[c][l]` its c-th value in field order) to `out`, and `block[l]` to
/// `ids`, for every lane with `ok[l]`, in lane order. `X`: the caller is compiled for AVX-512
/// (the transposition in shuffles; the same values either way).
#[inline(always)]
fn write_splats<const X: bool>(
    f: &[[f32; BLOCK]; 16],
    ok: &[bool; BLOCK],
    block: &[usize],
    out: &mut Vec<Splat>,
    ids: Option<&mut Vec<u32>>,
) {
    let mut rows = Rows([[0.0; 16]; BLOCK]);
    #[cfg(target_arch = "x86_64")]
    if X {
        // SAFETY: `X` is true only in the build compiled for AVX-512 (`project_range_avx512`,
        // called on a CPU that has it).
        unsafe { avx512::transpose(f, &mut rows) };
    } else {
        transpose(f, &mut rows);
    }
    #[cfg(not(target_arch = "x86_64"))]
    transpose(f, &mut rows);
    // every lane written to the next free slot, which only a kept lane takes (no branches)
    out.reserve(BLOCK);
    let (n, len) = (block.len(), out.len());
    let spare = &mut out.spare_capacity_mut()[..BLOCK];
    let mut m = 0;
    for l in 0..n {
        // SAFETY: a row holds a `Splat`'s 16 floats in field order (`Splat` is `repr(C)`, 16
        // f32 fields, 64 bytes, no padding).
        spare[m].write(unsafe { std::mem::transmute::<[f32; 16], Splat>(rows.0[l]) });
        m += ok[l] as usize;
    }
    // SAFETY: the first m spare slots were written above.
    unsafe { out.set_len(len + m) };
    if let Some(ids) = ids {
        for (l, &i) in block.iter().enumerate() {
            if ok[l] {
                ids.push(i as u32);
            }
        }
    }
}

/// Splats as rows of 16 floats, aligned as `Splat`.
#[repr(C, align(64))]
struct Rows([[f32; 16]; BLOCK]);

/// `rows[l][c] = f[c][l]`.
#[inline(always)]
fn transpose(f: &[[f32; BLOCK]; 16], rows: &mut Rows) {
    for (l, row) in rows.0.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = f[c][l];
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod avx512 {
    use super::{Rows, BLOCK};
    use std::arch::x86_64::*;

    /// [`super::Projector::any_in_depth`]: the same float64 operations in the same order (no
    /// fused multiply-add), 8 lanes per vector (LLVM's own code for it read the lane arrays
    /// across their stores, stalling on store forwarding).
    #[target_feature(enable = "avx512f")]
    #[inline]
    pub(super) unsafe fn any_in_depth(
        rot: &[f64; 3],
        tr: f64,
        near: f64,
        far: f64,
        mean: &[[f32; BLOCK]; 3],
    ) -> bool {
        let mut any = 0u8;
        for h in 0..2 {
            // SAFETY: lanes 8 h .. 8 h + 8 of each 16-lane array
            let ld =
                |c: usize| _mm512_cvtps_pd(unsafe { _mm256_loadu_ps(mean[c].as_ptr().add(8 * h)) });
            let z = _mm512_add_pd(
                _mm512_add_pd(
                    _mm512_add_pd(
                        _mm512_mul_pd(_mm512_set1_pd(rot[0]), ld(0)),
                        _mm512_mul_pd(_mm512_set1_pd(rot[1]), ld(1)),
                    ),
                    _mm512_mul_pd(_mm512_set1_pd(rot[2]), ld(2)),
                ),
                _mm512_set1_pd(tr),
            );
            let m = _mm512_cmp_pd_mask::<_CMP_GT_OQ>(z, _mm512_set1_pd(near));
            any |= _mm512_mask_cmp_pd_mask::<_CMP_LT_OQ>(m, z, _mm512_set1_pd(far));
        }
        any != 0
    }

    /// [`super::deinterleave`] of a full block `v` (16 Gaussians of C = 1, 3 or 4 values) in
    /// two-source permutes.
    #[target_feature(enable = "avx512f")]
    #[inline]
    pub(super) unsafe fn deinterleave<const C: usize>(v: &[f32], dst: &mut [[f32; BLOCK]; C]) {
        assert_eq!(v.len(), C * BLOCK);
        // SAFETY: v holds C * 16 floats (asserted); the index tables hold 16 i32 each; each
        // `dst[c]` holds 16 floats
        let ld = |k: usize| unsafe { _mm512_loadu_ps(v.as_ptr().add(16 * k)) };
        let ix = |t: &[i32; 16]| unsafe { _mm512_loadu_epi32(t.as_ptr()) };
        let st = |d: &mut [f32; BLOCK], x: __m512| unsafe { _mm512_storeu_ps(d.as_mut_ptr(), x) };
        match C {
            1 => st(&mut dst[0], ld(0)),
            3 => {
                let (a, b, c) = (ld(0), ld(1), ld(2));
                for (d, [i1, i2]) in dst.iter_mut().zip(&IDX3) {
                    let t = _mm512_permutex2var_ps(a, ix(i1), b);
                    st(d, _mm512_permutex2var_ps(t, ix(i2), c));
                }
            }
            4 => {
                let (a, b, c, e) = (ld(0), ld(1), ld(2), ld(3));
                for (d, i) in dst.iter_mut().zip(&IDX4) {
                    let lo = _mm512_permutex2var_ps(a, ix(i), b);
                    let hi = _mm512_permutex2var_ps(c, ix(i), e);
                    st(d, _mm512_mask_blend_ps(0xFF00, lo, hi));
                }
            }
            _ => unreachable!("deinterleave of {C} values"),
        }
    }

    /// Value c of lane l of a 3-value block is at 3 l + c: lanes up to 10 come from the first
    /// two vectors (first table), the others from the third (second table, indices 16 + p - 32).
    const IDX3: [[[i32; 16]; 2]; 3] = [idx3(0), idx3(1), idx3(2)];
    const fn idx3(c: usize) -> [[i32; 16]; 2] {
        let mut o = [[0i32; 16]; 2];
        let mut l = 0;
        while l < 16 {
            let p = 3 * l + c;
            if p < 32 {
                o[0][l] = p as i32;
                o[1][l] = l as i32;
            } else {
                o[1][l] = (p - 16) as i32;
            }
            l += 1;
        }
        o
    }

    /// Value c of lane l of a 4-value block is at 4 l + c: lanes 0-7 from the first two
    /// vectors, lanes 8-15 from the last two, the same indices modulo 32.
    const IDX4: [[i32; 16]; 4] = [idx4(0), idx4(1), idx4(2), idx4(3)];
    const fn idx4(c: usize) -> [i32; 16] {
        let mut o = [0i32; 16];
        let mut l = 0;
        while l < 16 {
            o[l] = ((4 * l + c) % 32) as i32;
            l += 1;
        }
        o
    }

    /// [`super::transpose`] in 64 shuffles (unpacks of floats, then of pairs, then 128-bit
    /// blocks twice).
    #[target_feature(enable = "avx512f")]
    #[inline]
    pub(super) unsafe fn transpose(f: &[[f32; BLOCK]; 16], rows: &mut Rows) {
        // SAFETY: each `f[c]` holds 16 floats
        let r: [__m512; 16] = std::array::from_fn(|c| unsafe { _mm512_loadu_ps(f[c].as_ptr()) });
        let mut t = [_mm512_setzero_ps(); 16];
        for i in 0..8 {
            t[2 * i] = _mm512_unpacklo_ps(r[2 * i], r[2 * i + 1]);
            t[2 * i + 1] = _mm512_unpackhi_ps(r[2 * i], r[2 * i + 1]);
        }
        let pd = |v: __m512| _mm512_castps_pd(v);
        let ps = |v: __m512d| _mm512_castpd_ps(v);
        let mut u = [_mm512_setzero_ps(); 16];
        for i in 0..4 {
            let b = 4 * i;
            u[b] = ps(_mm512_unpacklo_pd(pd(t[b]), pd(t[b + 2])));
            u[b + 1] = ps(_mm512_unpackhi_pd(pd(t[b]), pd(t[b + 2])));
            u[b + 2] = ps(_mm512_unpacklo_pd(pd(t[b + 1]), pd(t[b + 3])));
            u[b + 3] = ps(_mm512_unpackhi_pd(pd(t[b + 1]), pd(t[b + 3])));
        }
        // u[4 i + j] holds, in each 128-bit block, column j of rows 4 i .. 4 i + 4
        for h in 0..2 {
            for j in 0..4 {
                let (a, b) = (u[8 * h + j], u[8 * h + 4 + j]);
                t[8 * h + j] = _mm512_shuffle_f32x4::<0x88>(a, b);
                t[8 * h + 4 + j] = _mm512_shuffle_f32x4::<0xdd>(a, b);
            }
        }
        for j in 0..8 {
            let (a, b) = (t[j], t[8 + j]);
            let lo = _mm512_shuffle_f32x4::<0x88>(a, b);
            let hi = _mm512_shuffle_f32x4::<0xdd>(a, b);
            // SAFETY: each row holds 16 floats, 64-byte aligned (`Rows` is)
            unsafe {
                _mm512_store_ps(rows.0[j].as_mut_ptr(), lo);
                _mm512_store_ps(rows.0[8 + j].as_mut_ptr(), hi);
            }
        }
    }
}

/// Gaussians per projection work unit, as a shift: chunk c holds Gaussians
/// [c << PROJECT_CHUNK_BITS, (c + 1) << PROJECT_CHUNK_BITS).
pub(crate) const PROJECT_CHUNK_BITS: u32 = 13;

/// The visible splats of one view, per projection chunk, each in Gaussian-index order.
#[cfg(test)]
pub(crate) fn project_visible(scene: &SceneView<'_>, proj: &Projector) -> Vec<Vec<Splat>> {
    let mut parts = Vec::new();
    let n = project_visible_into(scene, proj, FrameColours::Off, &mut parts);
    parts.truncate(n);
    parts
}

/// [`project_visible`] into reused buffers, recording or reusing the frame's shared colours
/// (see [`super::share`]; the splats are the same bits either way): chunk c's visible splats go
/// to `parts[c]`, for the returned number of chunks (`parts` may hold more, left from a larger
/// scene, so their capacity survives too). A recording buffer holds at least one slot per
/// Gaussian.
pub(crate) fn project_visible_into(
    scene: &SceneView<'_>,
    proj: &Projector,
    colours: FrameColours<'_>,
    parts: &mut Vec<Vec<Splat>>,
) -> usize {
    let n = scene.len();
    let chunks = n.div_ceil(PROJECT_CHUNK);
    if parts.len() < chunks {
        parts.resize_with(chunks, Vec::new);
    }
    let run = |c: usize, out: &mut Vec<Splat>, mut cc: ChunkColours<'_>| {
        let lo = c * PROJECT_CHUNK;
        let hi = (lo + PROJECT_CHUNK).min(n);
        out.clear();
        proj.project_range_sharing(scene, lo, hi, out, None, &mut cc);
    };
    let parts = parts[..chunks].par_iter_mut().enumerate();
    match colours {
        FrameColours::Record(slots, stamp) => slots[..n]
            .par_chunks_mut(PROJECT_CHUNK)
            .zip(parts)
            .for_each(|(part, (c, out))| {
                run(c, out, ChunkColours::Record(part, c * PROJECT_CHUNK, stamp))
            }),
        FrameColours::Reuse(map, slots, stamp) => {
            parts.for_each(|(c, out)| run(c, out, ChunkColours::Reuse(map, slots, stamp)))
        }
        FrameColours::Off => parts.for_each(|(c, out)| run(c, out, ChunkColours::Off)),
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
    let chunks = project_visible_into(scene, &proj, FrameColours::Off, parts);
    Ok(parts[..chunks].iter().map(Vec::len).sum())
}

/// [`project_visible`] into reused buffers, with the Gaussian index of every splat:
/// `parts[c]` and `ids[c]` hold chunk c's visible splats and their indices.
pub(crate) fn project_visible_with_ids(
    scene: &SceneView<'_>,
    proj: &Projector,
    parts: &mut Vec<Vec<Splat>>,
    ids: &mut Vec<Vec<u32>>,
) {
    let n = scene.len();
    let chunks = n.div_ceil(PROJECT_CHUNK);
    parts.resize_with(chunks, Vec::new);
    ids.resize_with(chunks, Vec::new);
    parts
        .par_iter_mut()
        .zip(ids.par_iter_mut())
        .enumerate()
        .for_each(|(c, (out, id))| {
            out.clear();
            id.clear();
            let lo = c * PROJECT_CHUNK;
            let hi = (lo + PROJECT_CHUNK).min(n);
            proj.project_range(scene, lo, hi, out, Some(id));
        });
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Scene;

    /// A cloud around and behind a camera at the origin looking down +z, with the hard cases
    /// mixed in: non-finite values in every field, zero quaternions, tiny and huge scales,
    /// opacities around the cull, Gaussians behind the camera and far off-screen.
    fn scene(n: usize, degree: u8) -> Scene {
        let mut s = Scene::empty(degree);
        let k = s.sh_rest_k() * 3;
        let mut h = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = || {
            h ^= h << 13;
            h ^= h >> 7;
            h ^= h << 17;
            (h >> 40) as f32 / (1u64 << 24) as f32
        };
        for i in 0..n {
            s.means
                .extend([next() * 8.0 - 4.0, next() * 6.0 - 3.0, next() * 12.0 - 2.0]);
            s.quats
                .extend([next() - 0.5, next() - 0.5, next() - 0.5, next() - 0.5]);
            let big = if i % 97 == 0 { 4.0 } else { 0.0 };
            s.log_scales.extend([
                -6.0 + 5.0 * next() + big,
                -6.0 + 5.0 * next(),
                -6.0 + 5.0 * next(),
            ]);
            s.opacity_logits.push(next() * 16.0 - 8.0);
            s.sh0.extend([next() - 0.5, next() - 0.5, next() - 0.5]);
            s.sh_rest.extend((0..k).map(|_| next() - 0.5));
        }
        for (j, field) in (0..n).step_by(53).zip(0..) {
            match field % 6 {
                0 => s.means[j * 3 + 1] = f32::NAN,
                1 => s.quats[j * 4..j * 4 + 4].fill(0.0),
                2 => s.log_scales[j * 3 + 2] = f32::INFINITY,
                3 => s.opacity_logits[j] = f32::NAN,
                4 => s.sh0[j * 3] = f32::NEG_INFINITY,
                _ if k > 0 => s.sh_rest[j * k + k - 1] = f32::NAN,
                _ => s.quats[j * 4] = f32::NAN,
            }
        }
        s
    }

    fn bits(v: &[Splat]) -> Vec<u32> {
        v.iter()
            .flat_map(|s| {
                let mut f = vec![s.xy[0], s.xy[1], s.ln_opacity, s.depth];
                f.extend(s.conic.iter().chain(&s.rgb).chain(&s.radius));
                f.extend([s.two_a_level, s.conic_det, s.inv_a, s.half_height]);
                f.into_iter().map(f32::to_bits)
            })
            .collect()
    }

    /// The projection of one Gaussian as the code before the vectorised stage 3 computed it
    /// (stages 1 and 2 in a one-lane block, then the colour and the splat per Gaussian, in
    /// scalar code): the reference the block code must match bit for bit.
    fn reference(proj: &Projector, scene: &SceneView<'_>, i: usize) -> Option<Splat> {
        let mut g = Lanes::default();
        g.set(0, scene, i);
        let sc = proj.screen(&g);
        let fp = proj.footprint(&g, &sc);
        if !(sc.ok[0] && fp.ok[0]) {
            return None;
        }
        let (l, q) = (0, &scene.quats[i * 4..i * 4 + 4]);
        let mean = &scene.means[i * 3..i * 3 + 3];
        let (dir, _) = proj.view_dir([mean[0], mean[1], mean[2]]);
        let k = scene.sh_rest_k() * 3;
        let rest = &scene.sh_rest[i * k..i * k + k];
        if !rest.iter().chain(q).all(|v| v.is_finite()) {
            return None;
        }
        let rgb = sh::color(proj.sh_degree, dir, &scene.sh0[i * 3..i * 3 + 3], rest);
        let conic = [fp.conic[0][l], fp.conic[1][l], fp.conic[2][l]];
        let level = fp.ln_over[l] * 1.0001 + 1e-4;
        let s = Splat {
            xy: [sc.xy[0][l], sc.xy[1][l]],
            conic,
            ln_opacity: fastmath::ln(fp.opacity[l]),
            rgb,
            depth: sc.z[l],
            radius: [fp.radius[0][l], fp.radius[1][l]],
            two_a_level: 2.0 * conic[0] * level,
            conic_det: conic[0] * conic[2] - conic[1] * conic[1],
            inv_a: 1.0 / conic[0],
            half_height: (2.0 * level * fp.c11[l]).sqrt(),
        };
        bits(&[s])
            .iter()
            .all(|b| b & 0x7FFF_FFFF < 0x7F80_0000)
            .then_some(s)
    }

    /// Blocks of 16 with survivor compaction and the vectorised stage 3, in every build
    /// (AVX-512, AVX2, plain: `RenderOptions::simd` picks it), give the reference's splats bit
    /// for bit, whatever the neighbours in a block: SH degrees 0-3 (and degree 0 rendered from
    /// a degree-3 scene), antialiasing on and off, Gaussians behind the camera, beyond a far
    /// plane, clamped to the frustum, culled by opacity and with non-finite values in every
    /// field; the one-Gaussian path and the recorded shared colours agree too.
    #[test]
    fn vectorised_range_gives_the_reference_splats_bit_for_bit() {
        let mut m = [[0.0; 4]; 4];
        for (i, row) in m.iter_mut().enumerate() {
            row[i] = 1.0;
        }
        let near = Camera::new(300.0, 280.0, 160.0, 110.0, 333, 217, m);
        let far = Camera { far: 6.5, ..near };
        for (scene_degree, degree) in [(0, 0), (1, 1), (2, 2), (3, 3), (3, 0)] {
            let s = scene(5000, scene_degree);
            let view = s.view();
            for (cam, antialiased) in [(near, false), (near, true), (far, false)] {
                let want_proj = Projector::new(
                    &cam,
                    &RenderOptions {
                        antialiased,
                        ..Default::default()
                    },
                    degree,
                );
                let want: Vec<Splat> = (0..s.len())
                    .filter_map(|i| reference(&want_proj, &view, i))
                    .collect();
                assert!(want.len() > 500 && want.len() < 4500, "{}", want.len());
                let one: Vec<Splat> = (0..s.len())
                    .filter_map(|i| want_proj.project_with_opacity(&view, i).map(|p| p.0))
                    .collect();
                assert_eq!(bits(&one), bits(&want), "degree {degree}, one by one");
                for simd in [Simd::Avx512, Simd::Avx2, Simd::Scalar] {
                    if simd.resolve() != simd {
                        continue;
                    }
                    let opts = RenderOptions {
                        antialiased,
                        simd,
                        ..Default::default()
                    };
                    let proj = Projector::new(&cam, &opts, degree);
                    // ranges that start and end inside 16-Gaussian blocks
                    let ranges = [(0, 7), (7, 1000), (1000, 4093), (4093, 5000)];
                    let mut got = Vec::new();
                    let mut ids = Vec::new();
                    let mut slots = super::super::share::slots(s.len());
                    for (lo, hi) in ranges {
                        let mut cc = ChunkColours::Record(&mut slots[lo..hi], lo, 7);
                        proj.project_range_sharing(
                            &view,
                            lo,
                            hi,
                            &mut got,
                            Some(&mut ids),
                            &mut cc,
                        );
                    }
                    let what = format!("degree {degree}/{scene_degree}, {}", simd.name());
                    assert_eq!(bits(&got), bits(&want), "{what}");
                    // the indices, and every visible Gaussian's colour recorded
                    let want_ids: Vec<u32> = (0..s.len() as u32)
                        .filter(|&i| reference(&want_proj, &view, i as usize).is_some())
                        .collect();
                    assert_eq!(ids, want_ids, "{what}");
                    for (sp, &i) in got.iter().zip(&ids) {
                        let slot = slots[i as usize];
                        assert_eq!(slot[3], 7, "{what}");
                        assert_eq!(&slot[..3], &sp.rgb.map(f32::to_bits), "{what}");
                    }
                }
            }
        }
    }

    /// The AVX-512 transposition of splat lanes into rows is the plain one.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx512_transpose_is_the_plain_one() {
        if Simd::Avx512.resolve() != Simd::Avx512 {
            return;
        }
        let f: [[f32; BLOCK]; 16] =
            std::array::from_fn(|c| std::array::from_fn(|l| (c * 100 + l) as f32));
        let (mut want, mut got) = (Rows([[0.0; 16]; BLOCK]), Rows([[0.0; 16]; BLOCK]));
        transpose(&f, &mut want);
        // SAFETY: the CPU has AVX-512 (checked above).
        unsafe { avx512::transpose(&f, &mut got) };
        assert_eq!(got.0, want.0);
    }

    /// The AVX-512 loads of a full block into lanes are the plain ones (1, 3 and 4 values per
    /// Gaussian, at an offset).
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx512_deinterleave_is_the_plain_one() {
        if Simd::Avx512.resolve() != Simd::Avx512 {
            return;
        }
        let src: Vec<f32> = (0..200).map(|v| v as f32 * 0.5 - 7.0).collect();
        fn both<const C: usize>(src: &[f32]) {
            let (mut want, mut got) = ([[0.0; BLOCK]; C], [[0.0; BLOCK]; C]);
            deinterleave::<false, C>(src, 3, BLOCK, &mut want);
            deinterleave::<true, C>(src, 3, BLOCK, &mut got);
            assert_eq!(got, want, "{C} values");
            assert_eq!(want[C - 1][BLOCK - 1], src[(3 + BLOCK) * C - 1]);
        }
        both::<1>(&src);
        both::<3>(&src);
        both::<4>(&src);
    }
}
