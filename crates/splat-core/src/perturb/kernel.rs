//! The per-chunk kernel: copy the surviving rows, draw each op's normals for the chunk in one
//! branch-free batch, then apply the SPEC §2 formulas in flat loops.
//!
//! Everything here uses integer arithmetic and exactly rounded float operations only (see
//! [`crate::fastmath`]), so the AVX-512 / AVX2 builds chosen at run time give the same bits as
//! the portable build. The formulas' clamps are followed by rare scalar fix-ups that move a stored
//! value by an ulp where needed so that the activation `GaussianScene` reports (float32 `exp`)
//! lands inside the clamp range.
use super::{Ops, Rows, OPACITY_MAX, OPACITY_MIN, SCALE_MIN};
use crate::fastmath;
use crate::rng::{mix64, normal_pair, Stream, GAMMA};
use crate::scene::{SceneView, SH_C0};

/// Reusable buffers of one worker: the chunk's surviving global indices, the op's stream bases,
/// up to four normal draws per row (one array per draw) and an interleaved copy of them.
#[derive(Default)]
pub(crate) struct Scratch {
    pub idx: Vec<u64>,
    base: Vec<u64>,
    z: [Vec<f32>; 4],
    flat: Vec<f32>,
}

/// Copy the rows `scratch.idx` into `out`, then apply the enabled ops in place.
pub(crate) fn run_chunk(
    view: &SceneView<'_>,
    extras: &[(&str, &[f32])],
    k3: usize,
    ops: &Ops,
    out: Rows<'_>,
    scratch: &mut Scratch,
) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx512f")
            && std::is_x86_feature_detected!("avx512dq")
            && std::is_x86_feature_detected!("avx512vl")
            && std::is_x86_feature_detected!("avx2")
        {
            // SAFETY: the CPU has the features the function is compiled for (checked above).
            return unsafe { run_chunk_avx512(view, extras, k3, ops, out, scratch) };
        }
        if std::is_x86_feature_detected!("avx2") {
            // SAFETY: as above.
            return unsafe { run_chunk_avx2(view, extras, k3, ops, out, scratch) };
        }
    }
    run_chunk_impl(view, extras, k3, ops, out, scratch)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2,bmi2")]
unsafe fn run_chunk_avx512(
    view: &SceneView<'_>,
    extras: &[(&str, &[f32])],
    k3: usize,
    ops: &Ops,
    out: Rows<'_>,
    scratch: &mut Scratch,
) {
    run_chunk_impl(view, extras, k3, ops, out, scratch)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,bmi2")]
unsafe fn run_chunk_avx2(
    view: &SceneView<'_>,
    extras: &[(&str, &[f32])],
    k3: usize,
    ops: &Ops,
    out: Rows<'_>,
    scratch: &mut Scratch,
) {
    run_chunk_impl(view, extras, k3, ops, out, scratch)
}

/// keep[l] = (uniform draw of Gaussian i0 + l in the prune op) >= p, vectorised like the chunks.
pub(crate) fn fill_keep(key: u64, i0: u64, p: f32, keep: &mut [bool]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx512f")
            && std::is_x86_feature_detected!("avx512dq")
            && std::is_x86_feature_detected!("avx512vl")
            && std::is_x86_feature_detected!("avx2")
        {
            // SAFETY: the CPU has the features the function is compiled for (checked above).
            return unsafe { fill_keep_avx512(key, i0, p, keep) };
        }
    }
    fill_keep_impl(key, i0, p, keep)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2,bmi2")]
unsafe fn fill_keep_avx512(key: u64, i0: u64, p: f32, keep: &mut [bool]) {
    fill_keep_impl(key, i0, p, keep)
}

#[inline(always)]
fn fill_keep_impl(key: u64, i0: u64, p: f32, keep: &mut [bool]) {
    for (l, k) in keep.iter_mut().enumerate() {
        *k = Stream::new(key, i0 + l as u64).uniform() >= p;
    }
}

/// Per-axis (min, max) of the (x, y, z) rows whose three values are finite; (inf, -inf) if none.
pub(crate) fn finite_bounds(means: &[f32]) -> ([f32; 3], [f32; 3]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx512f")
            && std::is_x86_feature_detected!("avx512dq")
            && std::is_x86_feature_detected!("avx512vl")
            && std::is_x86_feature_detected!("avx2")
        {
            // SAFETY: the CPU has the features the function is compiled for (checked above).
            return unsafe { finite_bounds_avx512(means) };
        }
    }
    finite_bounds_impl(means)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2,bmi2")]
unsafe fn finite_bounds_avx512(means: &[f32]) -> ([f32; 3], [f32; 3]) {
    finite_bounds_impl(means)
}

#[inline(always)]
fn finite_bounds_impl(means: &[f32]) -> ([f32; 3], [f32; 3]) {
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for p in means.chunks_exact(3) {
        let ok = p[0].is_finite() & p[1].is_finite() & p[2].is_finite();
        for d in 0..3 {
            lo[d] = lo[d].min(if ok { p[d] } else { f32::INFINITY });
            hi[d] = hi[d].max(if ok { p[d] } else { f32::NEG_INFINITY });
        }
    }
    (lo, hi)
}

#[inline(always)]
fn run_chunk_impl(
    view: &SceneView<'_>,
    extras: &[(&str, &[f32])],
    k3: usize,
    ops: &Ops,
    out: Rows<'_>,
    s: &mut Scratch,
) {
    let rows = s.idx.len();
    let first = s.idx.first().map_or(0, |&i| i as usize);
    let contiguous = s
        .idx
        .last()
        .is_some_and(|&l| l as usize == first + rows - 1);
    let idx = &s.idx;
    let span = contiguous.then_some(first);
    gather(out.means, view.means, 3, idx, span);
    gather(out.quats, view.quats, 4, idx, span);
    gather(out.log_scales, view.log_scales, 3, idx, span);
    gather(out.opacity_logits, view.opacity_logits, 1, idx, span);
    gather(out.sh0, view.sh0, 3, idx, span);
    gather(out.sh_rest, view.sh_rest, k3, idx, span);
    for (dst, (_, src)) in out.extras.into_iter().zip(extras) {
        gather(dst, src, 1, idx, span);
    }
    if rows == 0 {
        return;
    }
    s.base.resize(rows, 0);
    for z in s.z.iter_mut() {
        z.resize(rows, 0.0);
    }
    s.flat.resize(rows * 3, 0.0);

    if let Some((key, sigma)) = ops.position {
        draw_normals(key, 3, &s.idx, &mut s.base, &mut s.z);
        interleave3(&s.z, &mut s.flat);
        for (v, &z) in out.means.iter_mut().zip(&s.flat) {
            *v += sigma * z;
        }
    }
    if let Some((key, sigma)) = ops.color {
        draw_normals(key, 3, &s.idx, &mut s.base, &mut s.z);
        interleave3(&s.z, &mut s.flat);
        for (v, &z) in out.sh0.iter_mut().zip(&s.flat) {
            let c = 0.5 + SH_C0 * *v;
            *v = ((c + sigma * z).clamp(0.0, 1.0) - 0.5) / SH_C0;
        }
        for v in out.sh0.iter_mut() {
            let c = 0.5 + SH_C0 * *v;
            if !(0.0..=1.0).contains(&c) {
                *v = fix_sh0(*v);
            }
        }
    }
    if let Some((key, sigma)) = ops.opacity {
        draw_normals(key, 1, &s.idx, &mut s.base, &mut s.z);
        for (x, &z) in out.opacity_logits.iter_mut().zip(&s.z[0]) {
            let a = 1.0 / (1.0 + fastmath::exp(-*x));
            let a = (a + sigma * z).clamp(OPACITY_MIN, OPACITY_MAX);
            *x = fastmath::ln(a / (1.0 - a));
        }
        for x in out.opacity_logits.iter_mut() {
            if x.abs() > 9.1 {
                *x = fix_logit(*x);
            }
        }
    }
    if let Some((key, sigma)) = ops.scale {
        draw_normals(key, 3, &s.idx, &mut s.base, &mut s.z);
        interleave3(&s.z, &mut s.flat);
        for (v, &z) in out.log_scales.iter_mut().zip(&s.flat) {
            let sc = fastmath::exp(*v) + sigma * z;
            // written so that NaN stays NaN
            *v = fastmath::ln(if sc < SCALE_MIN { SCALE_MIN } else { sc });
        }
        for v in out.log_scales.iter_mut() {
            if *v < -13.7 {
                *v = fix_log_scale(*v);
            }
        }
    }
    if let Some((key, sigma)) = ops.rotation {
        draw_normals(key, 4, &s.idx, &mut s.base, &mut s.z);
        let [z0, z1, z2, z3] = &s.z;
        for ((((q, &a), &b), &c), &d) in out
            .quats
            .chunks_exact_mut(4)
            .zip(z0)
            .zip(z1)
            .zip(z2)
            .zip(z3)
        {
            let u = unit([q[0], q[1], q[2], q[3]]);
            let w = [
                u[0] + sigma * a,
                u[1] + sigma * b,
                u[2] + sigma * c,
                u[3] + sigma * d,
            ];
            let n2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2] + w[3] * w[3];
            let norm = n2.sqrt();
            let ok = n2 > 0.0 && n2 < f32::INFINITY;
            for k in 0..4 {
                q[k] = if ok { w[k] / norm } else { u[k] };
            }
        }
    }
    if let Some((key, sigma)) = ops.log_scale {
        draw_normals(key, 3, &s.idx, &mut s.base, &mut s.z);
        interleave3(&s.z, &mut s.flat);
        for (v, &z) in out.log_scales.iter_mut().zip(&s.flat) {
            *v += sigma * z;
        }
    }
    if let Some((key, sigma)) = ops.rotation_angle {
        draw_normals(key, 3, &s.idx, &mut s.base, &mut s.z);
        let [z0, z1, z2, _] = &s.z;
        for (((q, &a), &b), &c) in out.quats.chunks_exact_mut(4).zip(z0).zip(z1).zip(z2) {
            let r = rotate([q[0], q[1], q[2], q[3]], [sigma * a, sigma * b, sigma * c]);
            q.copy_from_slice(&r);
        }
    }
}

/// exp(omega) * unit(q): q (w, x, y, z) turned by the rotation vector omega (radians), with
/// exactly rounded operations only (so the same bits on every CPU).
#[inline(always)]
pub(crate) fn rotate(q: [f32; 4], omega: [f32; 3]) -> [f32; 4] {
    let u = unit(q);
    let theta = (omega[0] * omega[0] + omega[1] * omega[1] + omega[2] * omega[2]).sqrt();
    let (sh, dw) = sin_cos(0.5 * theta);
    // sin(theta / 2) / theta, 1/2 at theta = 0
    let k = if theta > 0.0 { sh / theta } else { 0.5 };
    let d = [omega[0] * k, omega[1] * k, omega[2] * k];
    let v = [u[1], u[2], u[3]];
    [
        dw * u[0] - (d[0] * v[0] + d[1] * v[1] + d[2] * v[2]),
        dw * v[0] + u[0] * d[0] + (d[1] * v[2] - d[2] * v[1]),
        dw * v[1] + u[0] * d[1] + (d[2] * v[0] - d[0] * v[2]),
        dw * v[2] + u[0] * d[2] + (d[0] * v[1] - d[1] * v[0]),
    ]
}

/// (sin x, cos x) for finite x >= 0: reduced to [-pi/4, pi/4] by quarter turns in float64
/// (exactly rounded operations), then [`fastmath::sin_cos_quarter`]; a non-finite x gives NaN.
#[inline(always)]
pub(crate) fn sin_cos(x: f32) -> (f32, f32) {
    let h = f64::from(x);
    let n = (h * core::f64::consts::FRAC_2_PI + 0.5).floor();
    let r = (h - n * core::f64::consts::FRAC_PI_2) as f32;
    let (s, c) = fastmath::sin_cos_quarter(r.abs());
    let s = if r < 0.0 { -s } else { s };
    // n quarter turns: 0: (s, c), 1: (c, -s), 2: (-s, -c), 3: (-c, s)
    let quadrant = if n.is_finite() {
        (n as i64 & 3) as u32
    } else {
        0
    };
    let (s, c) = match quadrant {
        0 => (s, c),
        1 => (c, -s),
        2 => (-s, -c),
        _ => (-c, s),
    };
    if x.is_finite() {
        (s, c)
    } else {
        (f32::NAN, f32::NAN)
    }
}

/// Normal draws 0..dims of every row's stream, draw j into `z[j]` (the bits of
/// [`crate::rng::Stream::normals`], computed in one branch-free batch per word).
#[inline(always)]
fn draw_normals(key: u64, dims: usize, idx: &[u64], base: &mut [u64], z: &mut [Vec<f32>; 4]) {
    for (b, &i) in base.iter_mut().zip(idx) {
        *b = mix64(key ^ i);
    }
    for w in 0..dims.div_ceil(2) {
        let inc = (w as u64 + 1).wrapping_mul(GAMMA);
        let (head, tail) = z.split_at_mut(2 * w + 1);
        let za = &mut head[2 * w];
        if 2 * w + 1 < dims {
            for ((a, b), &bs) in za.iter_mut().zip(tail[0].iter_mut()).zip(base.iter()) {
                let (x, y) = normal_pair(mix64(bs.wrapping_add(inc)));
                *a = x;
                *b = y;
            }
        } else {
            for (a, &bs) in za.iter_mut().zip(base.iter()) {
                *a = normal_pair(mix64(bs.wrapping_add(inc))).0;
            }
        }
    }
}

/// Copy rows `idx` of `src` (rows of `w` floats) into `dst`; `span` is `Some(first)` when they
/// are the whole range first..first + idx.len(). A function, not a closure, so that it inlines
/// into the feature-specific builds (row copies become a few vector moves, not memcpy calls).
#[inline(always)]
fn gather(dst: &mut [f32], src: &[f32], w: usize, idx: &[u64], span: Option<usize>) {
    // an empty destination is an array this call does not write (see `perturb_changed`)
    if dst.is_empty() || w == 0 {
        return;
    }
    if let Some(first) = span {
        dst.copy_from_slice(&src[first * w..(first + idx.len()) * w]);
        return;
    }
    match w {
        1 => gather_rows::<1>(dst, src, idx),
        3 => gather_rows::<3>(dst, src, idx),
        4 => gather_rows::<4>(dst, src, idx),
        9 => gather_rows::<9>(dst, src, idx),
        24 => gather_rows::<24>(dst, src, idx),
        45 => gather_rows::<45>(dst, src, idx),
        72 => gather_rows::<72>(dst, src, idx),
        _ => {
            for (d, &i) in dst.chunks_exact_mut(w).zip(idx) {
                let i = i as usize;
                d.copy_from_slice(&src[i * w..(i + 1) * w]);
            }
        }
    }
}

/// dst row r = src row idx[r], rows of W floats.
#[inline(always)]
fn gather_rows<const W: usize>(dst: &mut [f32], src: &[f32], idx: &[u64]) {
    // Rows wider than a cache line: prefetch a few rows ahead (the survivors' addresses are
    // known), which hides most of the read latency of the scattered SH rows.
    const AHEAD: usize = 16;
    for (r, (d, &i)) in dst.chunks_exact_mut(W).zip(idx).enumerate() {
        if W >= 16 {
            if let Some(&next) = idx.get(r + AHEAD) {
                crate::mem::prefetch_bytes(src.as_ptr().wrapping_add(next as usize * W), W * 4);
            }
        }
        let i = i as usize;
        d.copy_from_slice(&src[i * W..(i + 1) * W]);
    }
}

/// flat[3r + d] = z[d][r].
#[inline(always)]
fn interleave3(z: &[Vec<f32>; 4], flat: &mut [f32]) {
    for (((f, &a), &b), &c) in flat.chunks_exact_mut(3).zip(&z[0]).zip(&z[1]).zip(&z[2]) {
        f[0] = a;
        f[1] = b;
        f[2] = c;
    }
}

/// q / |q|; a zero quaternion becomes the identity, a non-finite one is returned as is.
#[inline(always)]
fn unit(q: [f32; 4]) -> [f32; 4] {
    let n2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
    let norm = n2.sqrt();
    let ok = n2 > 0.0 && n2 < f32::INFINITY;
    let zero = n2 == 0.0;
    let id = [1.0, 0.0, 0.0, 0.0];
    let mut u = [0.0; 4];
    for k in 0..4 {
        u[k] = if ok {
            q[k] / norm
        } else if zero {
            id[k]
        } else {
            q[k]
        };
    }
    u
}

/// One float step toward zero (for nonzero finite `v`).
#[inline]
fn toward_zero(v: f32) -> f32 {
    f32::from_bits(v.to_bits() - 1)
}

/// Move sh0 toward zero until 0.5 + C0 * sh0 (float32) is inside [0, 1].
#[cold]
fn fix_sh0(mut v: f32) -> f32 {
    for _ in 0..8 {
        let c = 0.5 + SH_C0 * v;
        if (0.0..=1.0).contains(&c) || v == 0.0 || !v.is_finite() {
            break;
        }
        v = toward_zero(v);
    }
    v
}

/// Move a logit toward zero until sigmoid (float32, libm exp) is inside the opacity clamp.
#[cold]
fn fix_logit(mut x: f32) -> f32 {
    for _ in 0..8 {
        let a = 1.0 / (1.0 + (-x).exp());
        if (OPACITY_MIN..=OPACITY_MAX).contains(&a) || x == 0.0 || !x.is_finite() {
            break;
        }
        x = toward_zero(x);
    }
    x
}

/// Move a log-scale up until exp (float32, libm) is at least the scale floor.
#[cold]
fn fix_log_scale(mut v: f32) -> f32 {
    for _ in 0..8 {
        if v.exp() >= SCALE_MIN || v == 0.0 || !v.is_finite() {
            break;
        }
        v = toward_zero(v);
    }
    v
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::{
        op_key, OP_COLOR, OP_LOG_SCALE, OP_OPACITY, OP_POSITION, OP_ROTATION, OP_ROTATION_ANGLE,
        OP_SCALE,
    };
    use crate::scene::Scene;

    /// A scene of closed-form values, with a few huge and tiny ones to reach the clamps.
    fn scene(n: usize) -> Scene {
        let f = |i: usize, j: usize| ((i * 7 + j * 13) % 97) as f32 / 97.0;
        let mut s = Scene {
            means: (0..n * 3).map(|t| f(t / 3, t % 3) * 10.0).collect(),
            quats: (0..n * 4).map(|t| f(t / 4, t % 4 + 1) - 0.5).collect(),
            log_scales: (0..n * 3)
                .map(|t| f(t / 3, t % 3 + 5) * 8.0 - 12.0)
                .collect(),
            opacity_logits: (0..n).map(|i| f(i, 9) * 16.0 - 8.0).collect(),
            sh0: (0..n * 3)
                .map(|t| f(t / 3, t % 3 + 11) * 4.0 - 2.0)
                .collect(),
            sh_rest: vec![0.0; n * 9],
            sh_degree: 1,
            extras: Vec::new(),
        };
        s.opacity_logits[0] = 30.0;
        s.log_scales[0] = -18.0;
        s
    }

    /// Every op (the paper's six and the strength ops 7 and 8) through one build of the kernel
    /// (0 portable, 1 AVX2, 2 AVX-512) over the rows not divisible by 3 (a pruned-like gather);
    /// None when the CPU lacks the build's features.
    fn run_build(build: u8, s: &Scene, ops: &Ops) -> Option<Scene> {
        #[cfg(target_arch = "x86_64")]
        let has = |f: &str| match f {
            "avx2" => std::is_x86_feature_detected!("avx2"),
            _ => {
                std::is_x86_feature_detected!("avx512f")
                    && std::is_x86_feature_detected!("avx512dq")
                    && std::is_x86_feature_detected!("avx512vl")
                    && std::is_x86_feature_detected!("avx2")
            }
        };
        let mut scratch = Scratch::default();
        scratch
            .idx
            .extend((0..s.len() as u64).filter(|i| i % 3 != 0));
        let m = scratch.idx.len();
        let mut out = Scene {
            means: vec![0.0; m * 3],
            quats: vec![0.0; m * 4],
            log_scales: vec![0.0; m * 3],
            opacity_logits: vec![0.0; m],
            sh0: vec![0.0; m * 3],
            sh_rest: vec![0.0; m * 9],
            sh_degree: 1,
            extras: Vec::new(),
        };
        let rows = Rows {
            means: &mut out.means,
            quats: &mut out.quats,
            log_scales: &mut out.log_scales,
            opacity_logits: &mut out.opacity_logits,
            sh0: &mut out.sh0,
            sh_rest: &mut out.sh_rest,
            extras: Vec::new(),
        };
        let view = s.view();
        match build {
            0 => run_chunk_impl(&view, &[], 9, ops, rows, &mut scratch),
            #[cfg(target_arch = "x86_64")]
            1 if has("avx2") => {
                // SAFETY: the CPU has the features (checked).
                unsafe { run_chunk_avx2(&view, &[], 9, ops, rows, &mut scratch) }
            }
            #[cfg(target_arch = "x86_64")]
            2 if has("avx512") => {
                // SAFETY: as above.
                unsafe { run_chunk_avx512(&view, &[], 9, ops, rows, &mut scratch) }
            }
            _ => return None,
        }
        Some(out)
    }

    #[test]
    fn every_simd_build_gives_the_portable_bits() {
        let s = scene(3000);
        let seed = 77;
        let ops = Ops {
            position: Some((op_key(seed, OP_POSITION), 0.05)),
            color: Some((op_key(seed, OP_COLOR), 0.3)),
            opacity: Some((op_key(seed, OP_OPACITY), 0.3)),
            scale: Some((op_key(seed, OP_SCALE), 0.2)),
            rotation: Some((op_key(seed, OP_ROTATION), 0.4)),
            log_scale: Some((op_key(seed, OP_LOG_SCALE), 0.9)),
            // an RMS angle of about 17 rad: many quarter-turn reductions
            rotation_angle: Some((op_key(seed, OP_ROTATION_ANGLE), 10.0)),
        };
        let portable = run_build(0, &s, &ops).expect("portable");
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let mut compared = 0;
        for build in [1, 2] {
            let Some(out) = run_build(build, &s, &ops) else {
                continue;
            };
            compared += 1;
            assert_eq!(bits(&out.means), bits(&portable.means), "build {build}");
            assert_eq!(bits(&out.quats), bits(&portable.quats), "build {build}");
            assert_eq!(
                bits(&out.log_scales),
                bits(&portable.log_scales),
                "build {build}"
            );
            assert_eq!(
                bits(&out.opacity_logits),
                bits(&portable.opacity_logits),
                "build {build}"
            );
            assert_eq!(bits(&out.sh0), bits(&portable.sh0), "build {build}");
        }
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") {
            assert!(compared >= 1);
        }
        let _ = compared;
        assert!(portable.quats.iter().all(|v| v.is_finite()));
    }
}
