//! The haze op (docs/artifacts.md, "Haze"; `morphgs.haze`): the faint, large Gaussians a sparse
//! fit leaves beside its cameras, appended to a clean scene from its virtual training cameras.
//!
//! Candidate `i` (0, 1, 2, ...) draws everything it needs from its own counter-based stream
//! (seed, op 17, i): the training camera it sits beside, a direction, a distance, its size, shape,
//! rotation, opacity and colour. The first `n` candidates that pass the placement test, in index
//! order, are the haze: candidates are judged in parallel chunks, so the bytes are the same for
//! any thread count, and a larger value keeps a superset (the same first candidates, and more).
//! Only exactly rounded operations and `fastmath`'s exp and ln: the same bits on every CPU.
use rayon::prelude::*;

use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::fastmath;
use crate::rng::{normal_pair, op_key, Stream};

/// Op id of the haze op's draws.
pub const OP_HAZE: u32 = 17;
/// The largest value (the strength parameterisation's limit): bounds the Gaussians asked for.
pub const MAX_VALUE: f32 = 16.0;
/// Gaussians per training view at value 1 (the measured population of a 10-12 view fit).
pub const PER_VIEW: f64 = 250.0;
/// The distance from the training camera a candidate is drawn beside, in units of D.
pub const R_LO: f32 = 0.3;
pub const R_HI: f32 = 0.6;
/// Median largest scale, in units of D, and its log-normal spread.
pub const SCALE: f64 = 0.05;
const SCALE_SD: f32 = 0.45;
/// Half-normal sds of ln(largest / middle) and ln(middle / smallest) scale.
const FLAT_MID: f32 = 0.95;
const FLAT_MIN: f32 = 2.3;
/// Median opacity, its log-normal spread and clip.
pub const OPACITY: f32 = 0.10;
const OPACITY_SD: f32 = 0.85;
/// The widest a haze Gaussian may look (3 sigma of its largest scale) in a training view that sees it.
pub const MAX_PX: f64 = 30.0;
const LUMINANCE: f32 = 0.76;
const LUMINANCE_SD: f32 = 0.2;
const CHROMA_SD: f32 = 0.08;
/// Candidates judged per kept Gaussian at most (40 rounds of 4, as the first version drew them).
const MAX_CANDIDATES_PER: usize = 160;
const CHUNK: usize = 4096;
const SH_C0: f32 = 0.282_094_8;

/// The haze Gaussians: rows in the order they were kept.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Haze {
    pub means: Vec<[f32; 3]>,
    /// (w, x, y, z), unit length
    pub quats: Vec<[f32; 4]>,
    /// largest first
    pub log_scales: Vec<[f32; 3]>,
    pub opacity_logits: Vec<f32>,
    pub sh0: Vec<[f32; 3]>,
}

impl Haze {
    pub fn len(&self) -> usize {
        self.means.len()
    }

    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }
}

/// D: the median distance from each camera centre to its nearest other (0 for fewer than two).
pub fn spacing(centres: &[[f64; 3]]) -> f64 {
    if centres.len() < 2 {
        return 0.0;
    }
    let mut nearest: Vec<f64> = centres
        .iter()
        .enumerate()
        .map(|(i, a)| {
            centres
                .iter()
                .enumerate()
                .filter(|&(j, _)| j != i)
                .map(|(_, b)| dist(a, b))
                .fold(f64::INFINITY, f64::min)
        })
        .collect();
    nearest.sort_by(f64::total_cmp);
    let m = nearest.len();
    if m % 2 == 1 {
        nearest[m / 2]
    } else {
        0.5 * (nearest[m / 2 - 1] + nearest[m / 2])
    }
}

fn dist(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    let (x, y, z) = (a[0] - b[0], a[1] - b[1], a[2] - b[2]);
    (x * x + y * y + z * z).sqrt()
}

/// Normal draws `2 w` and `2 w + 1` of a stream.
fn normals2(s: &Stream, w: u64) -> (f32, f32) {
    normal_pair(s.word(w))
}

/// A candidate that passed: its position and its largest log scale.
struct Candidate {
    p: [f64; 3],
    log_smax: f32,
}

/// What every candidate shares: the cameras, their centres, D and the logs the draws scale.
struct Frame<'a> {
    key: u64,
    cams: &'a [Camera],
    centres: &'a [[f64; 3]],
    d: f64,
    /// ln R_LO, ln R_HI and ln(SCALE x D)
    ln_lo: f32,
    ln_hi: f32,
    ln_scale: f32,
}

fn candidate(f: &Frame<'_>, i: u64) -> Option<Candidate> {
    let (key, cams, centres, d) = (f.key, f.cams, f.centres, f.d);
    let s = Stream::new(key, i);
    let nv = cams.len();
    // word 0: the camera (the top 32 bits scaled to 0..nv, exact)
    let t = (((s.word(0) >> 32) * nv as u64) >> 32) as usize;
    let (n0, n1) = normals2(&s, 1);
    let (n2, n3) = normals2(&s, 2);
    let u = (s.word(3) >> 40) as f32 * (1.0 / 16_777_216.0);
    let norm =
        ((n0 as f64) * (n0 as f64) + (n1 as f64) * (n1 as f64) + (n2 as f64) * (n2 as f64)).sqrt();
    if norm == 0.0 {
        return None;
    }
    let r = d * fastmath::exp(f.ln_lo + u * (f.ln_hi - f.ln_lo)) as f64;
    let c = centres[t];
    let p = [
        c[0] + n0 as f64 / norm * r,
        c[1] + n1 as f64 / norm * r,
        c[2] + n2 as f64 / norm * r,
    ];
    let log_smax = f.ln_scale + SCALE_SD * n3;
    let smax = fastmath::exp(log_smax) as f64;
    let need = 2.min(nv - 1);
    let mut seen = 0;
    for (v, cam) in cams.iter().enumerate() {
        let m = &cam.world_to_camera;
        let z = m[2][0] * p[0] + m[2][1] * p[1] + m[2][2] * p[2] + m[2][3];
        if z <= 0.05 * d {
            continue;
        }
        let x = cam.fx * (m[0][0] * p[0] + m[0][1] * p[1] + m[0][2] * p[2] + m[0][3]) / z + cam.cx;
        let y = cam.fy * (m[1][0] * p[0] + m[1][1] * p[1] + m[1][2] * p[2] + m[1][3]) / z + cam.cy;
        if !(x >= 0.0 && x < cam.width as f64 && y >= 0.0 && y < cam.height as f64) {
            continue;
        }
        // seen by this view: never by the camera it was drawn beside (3 views or more), and never
        // wider than MAX_PX
        if (nv >= 3 && v == t) || cam.fx * 3.0 * smax / z > MAX_PX {
            return None;
        }
        seen += 1;
    }
    (seen >= need).then_some(Candidate { p, log_smax })
}

/// The haze of `value` (>= 0) for the training cameras `cams` (at least two, one image size):
/// `round(value x PER_VIEW x V)` Gaussians, fewer where the path leaves no room for them within
/// `MAX_CANDIDATES_PER` candidates each.
pub fn haze(cams: &[Camera], value: f32, seed: u64) -> Result<Haze> {
    if !(value.is_finite() && (0.0..=MAX_VALUE).contains(&value)) {
        return Err(Error::InvalidArgument(format!(
            "haze value must be a finite number in [0, {MAX_VALUE}], got {value}"
        )));
    }
    if cams.len() < 2 {
        return Err(Error::InvalidArgument(format!(
            "haze needs at least 2 training cameras, got {}",
            cams.len()
        )));
    }
    for c in cams {
        c.validate()?;
    }
    let centres: Vec<[f64; 3]> = cams.iter().map(Camera::center).collect();
    let d = spacing(&centres);
    let n = (value as f64 * PER_VIEW * cams.len() as f64).round() as usize;
    let mut out = Haze::default();
    if n == 0 || !(d > 0.0 && d.is_finite()) {
        return Ok(out);
    }
    let key = op_key(seed, OP_HAZE);
    let frame = Frame {
        key,
        cams,
        centres: &centres,
        d,
        ln_lo: fastmath::ln(R_LO),
        ln_hi: fastmath::ln(R_HI),
        ln_scale: fastmath::ln((d * SCALE) as f32),
    };
    let limit = n.saturating_mul(MAX_CANDIDATES_PER);
    let mut kept: Vec<(u64, Candidate)> = Vec::with_capacity(n);
    let mut start = 0usize;
    while kept.len() < n && start < limit {
        let end = (start + CHUNK).min(limit);
        let found: Vec<(u64, Candidate)> = (start..end)
            .into_par_iter()
            .filter_map(|i| candidate(&frame, i as u64).map(|c| (i as u64, c)))
            .collect();
        kept.extend(found.into_iter().take(n - kept.len()));
        start = end;
    }
    for (i, c) in kept {
        let s = Stream::new(key, i);
        let (f_mid, f_min) = normals2(&s, 4);
        let (o, l) = normals2(&s, 5);
        let (c0, c1) = normals2(&s, 6);
        let (c2, q0) = normals2(&s, 7);
        let (q1, q2) = normals2(&s, 8);
        let (q3, _) = normals2(&s, 9);
        let l_mid = c.log_smax - FLAT_MID * f_mid.abs();
        out.log_scales
            .push([c.log_smax, l_mid, l_mid - FLAT_MIN * f_min.abs()]);
        out.means
            .push([c.p[0] as f32, c.p[1] as f32, c.p[2] as f32]);
        let qn = (q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3).sqrt();
        out.quats.push(if qn > 0.0 {
            [q0 / qn, q1 / qn, q2 / qn, q3 / qn]
        } else {
            [1.0, 0.0, 0.0, 0.0]
        });
        let op = (OPACITY * fastmath::exp(OPACITY_SD * o)).clamp(0.01, 0.9);
        out.opacity_logits.push(fastmath::ln(op / (1.0 - op)));
        let lum = LUMINANCE + LUMINANCE_SD * l;
        out.sh0
            .push([c0, c1, c2].map(|z| (lum + CHROMA_SD * z - 0.5) / SH_C0));
    }
    Ok(out)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// `n` cameras on 90 % of a circle of radius 3 at height 1.6, looking at the origin.
    pub(crate) fn ring(n: usize, size: (u32, u32)) -> Vec<Camera> {
        // cameras on a circle of radius 3 at height 1.6, looking at the origin (OpenCV axes)
        (0..n)
            .map(|k| {
                let a = k as f64 / n as f64 * std::f64::consts::TAU * 0.9;
                let c = [3.0 * a.cos(), 3.0 * a.sin(), 1.6];
                let f = [-c[0], -c[1], -c[2]];
                let fl = (f[0] * f[0] + f[1] * f[1] + f[2] * f[2]).sqrt();
                let fwd = [f[0] / fl, f[1] / fl, f[2] / fl];
                let up = [0.0, 0.0, 1.0];
                let mut right = [
                    fwd[1] * up[2] - fwd[2] * up[1],
                    fwd[2] * up[0] - fwd[0] * up[2],
                    fwd[0] * up[1] - fwd[1] * up[0],
                ];
                let rl = (right[0] * right[0] + right[1] * right[1] + right[2] * right[2]).sqrt();
                right = right.map(|v| v / rl);
                let down = [
                    fwd[1] * right[2] - fwd[2] * right[1],
                    fwd[2] * right[0] - fwd[0] * right[2],
                    fwd[0] * right[1] - fwd[1] * right[0],
                ];
                let rows = [right, down, fwd];
                let mut m = [[0.0; 4]; 4];
                for r in 0..3 {
                    for j in 0..3 {
                        m[r][j] = rows[r][j];
                    }
                    m[r][3] = -(rows[r][0] * c[0] + rows[r][1] * c[1] + rows[r][2] * c[2]);
                }
                m[3][3] = 1.0;
                let (w, h) = size;
                let (wf, hf) = (f64::from(w), f64::from(h));
                let k = [wf, 0.0, wf / 2.0, 0.0, wf, hf / 2.0, 0.0, 0.0, 1.0];
                let flat: Vec<f64> = m.iter().flatten().copied().collect();
                Camera::from_matrices(&flat, &k, w, h, 0.01, 1e10).expect("camera")
            })
            .collect()
    }

    #[test]
    fn the_same_bytes_for_1_2_and_8_threads_and_a_larger_value_keeps_a_superset() {
        let cams = ring(8, (96, 72));
        let run = |t: usize, v: f32| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(t)
                .build()
                .expect("pool")
                .install(|| haze(&cams, v, 7).expect("haze"))
        };
        let one = run(1, 1.0);
        assert_eq!(one.len(), 2000);
        assert_eq!(one, run(2, 1.0));
        assert_eq!(one, run(8, 1.0));
        let more = run(2, 1.5);
        assert_eq!(more.len(), 3000);
        assert_eq!(&more.means[..2000], &one.means[..]);
        assert_eq!(&more.log_scales[..2000], &one.log_scales[..]);
        assert!(haze(&cams, 0.0, 7).expect("haze").is_empty());
    }

    #[test]
    fn bad_values_and_too_few_cameras_are_errors() {
        let cams = ring(8, (96, 72));
        assert!(haze(&cams, f32::NAN, 0).is_err());
        assert!(haze(&cams, -1.0, 0).is_err());
        assert!(haze(&cams, 1e30, 0).is_err()); // no huge allocation
        assert!(haze(&cams[..1], 1.0, 0).is_err());
    }
}
