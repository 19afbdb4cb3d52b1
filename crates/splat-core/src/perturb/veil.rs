//! The veil op (docs/artifacts.md, "Veil"; `morphgs.veil`): Gaussians a sparse fit places where
//! every training view that sees them shows their own colour, appended to a clean scene from its
//! virtual training cameras.
//!
//! A real object capture's sparse fit explains its training photos' backdrop with large, faint,
//! backdrop-coloured splats at the object's depth, beside its silhouette: dark on dark in every
//! training view, so nothing corrects them, and from the views between they slide over the
//! object (the committed `skull`'s sparse fits, docs/artifacts.md). The ambiguity is photometric,
//! not geometric: the training views see such a splat, but on pixels of its own colour.
//!
//! Candidate `i` (0, 1, 2, ...) draws everything from its own counter-based stream (seed, op 18,
//! i): a training camera t and a pixel of it (the splat's colour, that pixel's clean colour), a
//! depth on that pixel's ray (the clean depth of another random pixel of view t, brought forward
//! by a factor e^(-FRONT u)), a footprint in view t, a shape, a rotation and an opacity. It is kept
//! when it lies in front of what view t's pixel shows, at least [`MIN_VIEWS`] training views see
//! it, none wider than [`MAX_SIGMA_PX`], and in every training view that sees it (in the image,
//! not behind that view's surface by more than [`HIDDEN`]) the nine pixels at its centre and two
//! sigma around it are all within [`TOLERANCE`] (RMS over the channels) of its colour. The first
//! `n` kept candidates, in index order, are the veil: candidates are judged in parallel chunks,
//! so the bytes are the same for any thread count, and a larger value keeps a superset. Only
//! exactly rounded operations and `fastmath`'s exp and ln: the same bits on every CPU.
use rayon::prelude::*;

use super::artifacts::Train;
use super::haze::Haze;
use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::fastmath;
use crate::rng::{normal_pair, op_key, Stream};

/// Op id of the veil op's draws.
pub const OP_VEIL: u32 = 18;
/// The largest value (the strength parameterisation's limit): bounds the Gaussians asked for.
pub const MAX_VALUE: f32 = 16.0;
/// Gaussians per training view at value 1.
pub const PER_VIEW: f64 = 100.0;
/// The largest RMS colour difference (over the channels) between a veil Gaussian and any pixel it
/// covers in a training view that sees it (shatter's fragment test's 0.08).
pub const TOLERANCE: f32 = 0.08;
/// How far in front of the drawn content depth a candidate may sit: a factor e^(-FRONT u), u
/// uniform in [0, 1).
pub const FRONT: f32 = 0.3;
/// The footprint's sigma in view t, pixels, log-uniform in [SIGMA_PX_LO, SIGMA_PX_HI].
pub const SIGMA_PX_LO: f32 = 2.0;
/// See [`SIGMA_PX_LO`].
pub const SIGMA_PX_HI: f32 = 24.0;
/// The widest a kept Gaussian may look (sigma, pixels) in any training view that sees it.
pub const MAX_SIGMA_PX: f32 = 48.0;
/// Training views that must see a kept Gaussian (view t among them).
pub const MIN_VIEWS: usize = 2;
/// A training view does not see a point more than this factor behind its clean depth there.
pub const HIDDEN: f32 = 1.1;
/// Median opacity, its log-normal spread and clip (the skull's veils: median 0.14).
pub const OPACITY: f32 = 0.15;
const OPACITY_SD: f32 = 0.8;
/// The log-normal spread of each axis' scale around the footprint's.
const SHAPE_SD: f32 = 0.35;
/// Candidates judged per kept Gaussian at most.
const MAX_CANDIDATES_PER: usize = 400;
const CHUNK: usize = 4096;
const SH_C0: f32 = 0.282_094_8;

/// The clean renders of the training cameras (one size W x H): `rgb` `(V, H, W, 3)` in [0, 1] and
/// `depth` `(V, H, W)`, the expected camera z (0 where nothing is hit).
#[derive(Debug, Clone, Copy)]
pub struct Views<'a> {
    pub rgb: &'a [f32],
    pub depth: &'a [f32],
}

struct Frame<'a> {
    key: u64,
    cams: Vec<Train>,
    views: Views<'a>,
    w: usize,
    h: usize,
    ln_lo: f32,
    ln_hi: f32,
}

/// A candidate that passed: position, colour and its sigma (world units).
struct Candidate {
    p: [f32; 3],
    rgb: [f32; 3],
    sigma: f32,
}

fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `(word >> 32) * n >> 32`: an index in 0..n from one stream word, exactly.
fn index(word: u64, n: usize) -> usize {
    (((word >> 32) * n as u64) >> 32) as usize
}

fn unit(word: u64) -> f32 {
    (word >> 40) as f32 * (1.0 / 16_777_216.0)
}

impl Frame<'_> {
    fn rgb(&self, v: usize, x: usize, y: usize) -> [f32; 3] {
        let o = ((v * self.h + y) * self.w + x) * 3;
        [
            self.views.rgb[o],
            self.views.rgb[o + 1],
            self.views.rgb[o + 2],
        ]
    }

    fn depth(&self, v: usize, x: usize, y: usize) -> f32 {
        self.views.depth[(v * self.h + y) * self.w + x]
    }

    /// Whether every pixel of view `v` at the centre `(u, y)` and two sigma (`s` pixels) around it
    /// is within [`TOLERANCE`] of `rgb`.
    fn matches(&self, v: usize, u: f32, y: f32, s: f32, rgb: [f32; 3]) -> bool {
        let d = 2.0 * s;
        let e = d * std::f32::consts::FRAC_1_SQRT_2;
        let offsets = [
            [0.0, 0.0],
            [d, 0.0],
            [-d, 0.0],
            [0.0, d],
            [0.0, -d],
            [e, e],
            [e, -e],
            [-e, e],
            [-e, -e],
        ];
        let (wm, hm) = ((self.w - 1) as f32, (self.h - 1) as f32);
        offsets.iter().all(|o| {
            let x = (u + o[0]).floor().clamp(0.0, wm) as usize;
            let yy = (y + o[1]).floor().clamp(0.0, hm) as usize;
            let c = self.rgb(v, x, yy);
            let (a, b, g) = (c[0] - rgb[0], c[1] - rgb[1], c[2] - rgb[2]);
            (a * a + b * b + g * g) / 3.0 <= TOLERANCE * TOLERANCE
        })
    }

    fn candidate(&self, i: u64) -> Option<Candidate> {
        let s = Stream::new(self.key, i);
        let nv = self.cams.len();
        let t = index(s.word(0), nv);
        let (px, py) = (index(s.word(1), self.w), index(s.word(2), self.h));
        let q = index(s.word(3), self.w * self.h);
        let content = self.depth(t, q % self.w, q / self.w);
        if !(content > 0.0 && content.is_finite()) {
            return None;
        }
        let d = content * fastmath::exp(-FRONT * unit(s.word(4)));
        let behind = self.depth(t, px, py);
        if behind > 0.0 && d > behind {
            return None; // hidden in view t: it would not explain its pixel
        }
        let cam = &self.cams[t];
        let local = [
            (px as f32 + 0.5 - cam.cx) / cam.fx,
            (py as f32 + 0.5 - cam.cy) / cam.fy,
            1.0,
        ];
        // world point at camera depth d on the pixel's ray: centre + R^T (local d)
        let p = [0, 1, 2].map(|k| {
            cam.centre[k]
                + (cam.rot[0][k] * local[0] + cam.rot[1][k] * local[1] + cam.rot[2][k]) * d
        });
        let sigma_px = fastmath::exp(self.ln_lo + unit(s.word(5)) * (self.ln_hi - self.ln_lo));
        let sigma = d * sigma_px / cam.fx;
        let rgb = self.rgb(t, px, py);
        let mut seen = 0;
        for (v, c) in self.cams.iter().enumerate() {
            let r = [p[0] - c.centre[0], p[1] - c.centre[1], p[2] - c.centre[2]];
            let z = dot(c.rot[2], r);
            if z.is_nan() || z <= 1e-6 {
                continue;
            }
            let u = c.fx * dot(c.rot[0], r) / z + c.cx;
            let y = c.fy * dot(c.rot[1], r) / z + c.cy;
            // seen when its 3-sigma footprint reaches the image
            let s_px = sigma * c.fx / z;
            let m = 3.0 * s_px;
            if !(u >= -m && u < self.w as f32 + m && y >= -m && y < self.h as f32 + m) {
                continue;
            }
            let (wm, hm) = ((self.w - 1) as f32, (self.h - 1) as f32);
            let surface = self.depth(v, u.clamp(0.0, wm) as usize, y.clamp(0.0, hm) as usize);
            if surface > 0.0 && z > HIDDEN * surface {
                continue;
            }
            if s_px > MAX_SIGMA_PX || !self.matches(v, u, y, s_px, rgb) {
                return None;
            }
            seen += 1;
        }
        (seen >= MIN_VIEWS).then_some(Candidate { p, rgb, sigma })
    }
}

/// The veil of `value` (>= 0) for the training cameras `cams` (one image size W x H, as `views`):
/// `round(value x PER_VIEW x V)` Gaussians, fewer where the views leave no room for them within
/// `MAX_CANDIDATES_PER` candidates each. Rows as the haze op's: means, unit quats (w, x, y, z),
/// log scales, opacity logits, DC colour (no view dependence).
///
/// Errors: a bad value, fewer than [`MIN_VIEWS`] cameras, cameras of different sizes, maps that do
/// not match them.
pub fn veil(cams: &[Camera], views: Views<'_>, value: f32, seed: u64) -> Result<Haze> {
    if !(value.is_finite() && (0.0..=MAX_VALUE).contains(&value)) {
        return Err(Error::InvalidArgument(format!(
            "veil value must be a finite number in [0, {MAX_VALUE}], got {value}"
        )));
    }
    if cams.len() < MIN_VIEWS {
        return Err(Error::InvalidArgument(format!(
            "veil needs at least {MIN_VIEWS} training cameras (its Gaussians must agree with two views), got {}",
            cams.len()
        )));
    }
    let first = &cams[0];
    for c in cams {
        c.validate()?;
    }
    let (w, h) = (first.width as usize, first.height as usize);
    let px = cams.len() * w * h;
    if cams
        .iter()
        .any(|c| c.width != first.width || c.height != first.height)
        || views.rgb.len() != px * 3
        || views.depth.len() != px
    {
        return Err(Error::InvalidArgument(format!(
            "veil: expected {} renders of {w}x{h} (one per training camera, one size), got {} colour and {} depth values",
            cams.len(),
            views.rgb.len(),
            views.depth.len()
        )));
    }
    let n = (value as f64 * PER_VIEW * cams.len() as f64).round() as usize;
    let mut out = Haze::default();
    if n == 0 {
        return Ok(out);
    }
    let frame = Frame {
        key: op_key(seed, OP_VEIL),
        cams: cams.iter().map(Train::of).collect(),
        views,
        w,
        h,
        ln_lo: fastmath::ln(SIGMA_PX_LO),
        ln_hi: fastmath::ln(SIGMA_PX_HI),
    };
    let limit = n.saturating_mul(MAX_CANDIDATES_PER);
    let mut kept: Vec<(u64, Candidate)> = Vec::with_capacity(n);
    let mut start = 0usize;
    while kept.len() < n && start < limit {
        let end = (start + CHUNK).min(limit);
        let found: Vec<(u64, Candidate)> = (start..end)
            .into_par_iter()
            .filter_map(|i| frame.candidate(i as u64).map(|c| (i as u64, c)))
            .collect();
        kept.extend(found.into_iter().take(n - kept.len()));
        start = end;
    }
    for (i, c) in kept {
        let s = Stream::new(frame.key, i);
        let (a, b) = normal_pair(s.word(6));
        let (e, o) = normal_pair(s.word(7));
        let (q0, q1) = normal_pair(s.word(8));
        let (q2, q3) = normal_pair(s.word(9));
        let ls = fastmath::ln(c.sigma);
        out.log_scales
            .push([ls + SHAPE_SD * a, ls + SHAPE_SD * b, ls + SHAPE_SD * e]);
        out.means.push(c.p);
        let qn = (q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3).sqrt();
        out.quats.push(if qn > 0.0 {
            [q0 / qn, q1 / qn, q2 / qn, q3 / qn]
        } else {
            [1.0, 0.0, 0.0, 0.0]
        });
        let op = (OPACITY * fastmath::exp(OPACITY_SD * o)).clamp(0.02, 0.9);
        out.opacity_logits.push(fastmath::ln(op / (1.0 - op)));
        out.sh0.push(c.rgb.map(|x| (x - 0.5) / SH_C0));
    }
    Ok(out)
}

#[cfg(test)]
mod tests;
