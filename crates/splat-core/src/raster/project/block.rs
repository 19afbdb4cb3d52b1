//! A range of Gaussians projected 16 lanes at a time: stage 1 (camera space, Jacobian, the
//! off-screen early out), stage 2 (covariance, conic, opacity, box) and stage 3 (SH colour and
//! the splats' blend constants), each as short loops over lane arrays that the compiler
//! vectorises, then the visible lanes written out as splats. Compiled for AVX-512 and AVX2 too
//! and picked at run time; every build gives the same bits.
use super::math::{cov2d, quat_rotation};
use super::{Projector, Splat, ALPHA_THRESHOLD, EPS2D};
use crate::fastmath;
use crate::raster::share::ChunkColours;
use crate::raster::{sh, Simd};
use crate::scene::SceneView;

#[cfg(target_arch = "x86_64")]
use super::block_avx512 as avx512;

impl Projector {
    /// Project Gaussian `i`: the splat and its opacity, `None` when it is culled or holds
    /// non-finite values. The one-Gaussian form of [`Projector::project_range`] (a block with
    /// one lane), so it gives the same bits.
    pub(super) fn project_with_opacity(
        &self,
        scene: &SceneView<'_>,
        i: usize,
    ) -> Option<(Splat, f32)> {
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

    /// Project Gaussians `lo..hi` and append the visible splats to `out` in index order, and
    /// with `ids` their Gaussian indices to `ids`, recording or reusing shared colours through
    /// `colours` (see [`crate::raster::share`]; `ChunkColours::Off` for neither). Stage 1
    /// (camera space, Jacobian, the off-screen early out) runs on every Gaussian and stage 2
    /// (covariance, conic, opacity, box) on stage 1's survivors, both 16 lanes at a time as
    /// short loops over lane arrays that the compiler vectorises (this function is compiled for
    /// AVX-512 and AVX2 too and picked at run time; no FMA contraction and `fastmath`'s exp and
    /// ln, so every build gives the same bits). Stage 3 (SH colour, the splat) runs per visible
    /// Gaussian.
    pub(crate) fn project_range(
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
    pub(super) fn screen(&self, g: &Lanes) -> ScreenLanes {
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
    pub(super) fn footprint(&self, g: &Lanes, sc: &ScreenLanes) -> FootLanes {
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
pub(super) const BLOCK: usize = 16;

/// Stage-1 survivors from which a block goes to stage 2 as it is rather than gathered with
/// other blocks' survivors.
const DENSE: usize = 8;

/// Lane l of `dst[c]` = `src[(i0 + l) * C + c]` for the `n <= BLOCK` Gaussians from `i0` (a
/// full block as one contiguous slice, so the compiler can shuffle it into lanes).
#[inline(always)]
pub(super) fn deinterleave<const X: bool, const C: usize>(
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
pub(super) struct Lanes {
    mean: [[f32; BLOCK]; 3],
    q: [[f32; BLOCK]; 4],
    ls: [[f32; BLOCK]; 3],
    logit: [f32; BLOCK],
    sh0: [[f32; BLOCK]; 3],
}

impl Lanes {
    /// Load Gaussian `i` into lane `l`.
    #[inline(always)]
    pub(super) fn set(&mut self, l: usize, scene: &SceneView<'_>, i: usize) {
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
pub(super) struct ScreenLanes {
    pub(super) ok: [bool; BLOCK],
    pub(super) z: [f32; BLOCK],
    pub(super) xy: [[f32; BLOCK]; 2],
    /// j00, j02, j11, j12
    pub(super) j: [[f32; BLOCK]; 4],
}

/// Stage 2 results of a block.
#[derive(Default)]
pub(super) struct FootLanes {
    pub(super) ok: [bool; BLOCK],
    pub(super) conic: [[f32; BLOCK]; 3],
    pub(super) c00: [f32; BLOCK],
    pub(super) c11: [f32; BLOCK],
    pub(super) opacity: [f32; BLOCK],
    pub(super) ln_over: [f32; BLOCK],
    pub(super) radius: [[f32; BLOCK]; 2],
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
pub(super) struct Rows(pub(super) [[f32; 16]; BLOCK]);

/// `rows[l][c] = f[c][l]`.
#[inline(always)]
pub(super) fn transpose(f: &[[f32; BLOCK]; 16], rows: &mut Rows) {
    for (l, row) in rows.0.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = f[c][l];
        }
    }
}
