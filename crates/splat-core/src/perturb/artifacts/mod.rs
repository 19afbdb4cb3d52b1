//! Corruptions of the sparse-view kind (issue 36): what a 3DGS fit from a few training views gets
//! wrong, made on a clean scene from a set of "virtual training cameras" (a subset of the capture
//! path, as a regime's S_K takes every K-th view). Each op mimics one failure and keeps the
//! training views close to clean, as a real sparse fit does, while the views between them break:
//!
//! | op | what a sparse fit does | here |
//! |---|---|---|
//! | `depth` | places a Gaussian anywhere along the rays of its training views | each Gaussian slides along the ray from its nearest training camera by a log-normal factor `f = exp(sigma z)`, its scales times `f`: the same projected footprint in that camera, parallax errors and ghosts elsewhere |
//! | `view_color` | fits colours seen from the training directions only | SH noise of sigma in bands 1-3, projected onto the null space of the basis at the directions of the 3 nearest training cameras: the same colour there, speckle and colour outliers between them |
//! | `needles` | collapses Gaussians to rank one along the training rays | a fraction of Gaussians become needles: the long axis `exp(NEEDLE_LOG_LENGTH)` times the Gaussian's mean radius along the ray of its nearest training camera, the two short axes that radius (a compact dot in that view, a streak elsewhere) |
//! | `holes` | leaves unseen regions empty | a fraction of the cells of a grid (cell edge `hole_size` x E_avg, offset by the seed) lose every Gaussian whose centre they hold: spatially coherent holes, not i.i.d. pruning |
//! | `dilate` | grows Gaussians to cover what few views constrain | every log scale + `dilate` |
//! | `floaters` | spawns semi-transparent Gaussians near the cameras that explain a training pixel | `floaters` per thousand training pixels, each on the ray of a random pixel of a random training camera, near it (depth log-uniform in [FLOATER_NEAR, FLOATER_FAR] x E_avg), a footprint of 1.5-12 pixels there, opacity 0.2-0.9, coloured from that pixel of the clean training view; of up to 8 candidates the first that no other training view sees |
//!
//! Every random draw is keyed by `(seed, op, index)` (an input Gaussian's index, a floater's own
//! index, a hole cell's coordinates), so the bytes are the same for any thread count, Gaussian `i`
//! gets the same noise whichever other ops run, and a larger fraction (of needles, holes,
//! floaters) selects a superset. Only exactly rounded float operations are used (no fused
//! multiply-add; `fastmath` for exp and ln), so the same bytes come out on every CPU.
//!
//! [`apply`] keeps every input row (holes are returned as a keep mask for the classic pass's
//! pruning, so that pass still keys its noise by the input index) and appends the floaters.
use rayon::prelude::*;

use super::{mean_extent, CHUNK};
use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::fastmath;
use crate::raster::sh;
use crate::rng::{mix64, normal_pair, op_key, Stream, GAMMA};
use crate::scene::{sh_rest_count, Scene, SceneView, SH_C0};

/// Op id of the depth slide.
pub const OP_DEPTH: u32 = 10;
/// Op id of the view-dependent colour noise.
pub const OP_VIEW_COLOR: u32 = 11;
/// Op id of the needles' selection.
pub const OP_NEEDLES: u32 = 12;
/// Op id of the holes' cells (and the grid offset).
pub const OP_HOLES: u32 = 13;
/// Op id of the floaters.
pub const OP_FLOATERS: u32 = 14;

/// A needle's long axis over its mean radius, as a natural log (ln 10).
pub const NEEDLE_LOG_LENGTH: f32 = std::f32::consts::LN_10;
/// Nearest and farthest floater depth along the training ray, in units of E_avg.
pub const FLOATER_NEAR: f32 = 0.02;
/// See [`FLOATER_NEAR`].
pub const FLOATER_FAR: f32 = 0.3;
/// Training directions a Gaussian's view-dependent colour is pinned at (its nearest cameras).
pub const VIEW_COLOR_PINS: usize = 3;
/// Default hole cell edge in units of E_avg.
pub const HOLE_SIZE: f32 = 0.05;
/// How far (pixels) a Gaussian may move in another training view that sees it: within this,
/// the views cannot tell the difference (the depth slide's and the needles' ambiguity).
pub const TOLERANCE_PX: f32 = 1.0;
/// Candidate positions a floater tries before it settles for one another training camera sees.
pub const FLOATER_TRIES: u64 = 8;

/// Parameters of the sparse-view ops; `None` (or 0) disables an op.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArtifactParams {
    /// Sigma of the natural log of the depth factor.
    pub depth: Option<f32>,
    /// Sigma of the SH noise (bands 1-3) before its projection.
    pub view_color: Option<f32>,
    /// Fraction of Gaussians made needles, in [0, 1].
    pub needles: Option<f32>,
    /// Fraction of grid cells emptied, in [0, 1].
    pub holes: Option<f32>,
    /// The hole grid's cell edge in units of E_avg (> 0).
    pub hole_size: f32,
    /// Added to every log scale (>= 0).
    pub dilate: Option<f32>,
    /// Floaters spawned per thousand training pixels (all training views together), in [0, 10].
    pub floaters: Option<f32>,
}

impl Default for ArtifactParams {
    fn default() -> Self {
        ArtifactParams {
            depth: None,
            view_color: None,
            needles: None,
            holes: None,
            hole_size: HOLE_SIZE,
            dilate: None,
            floaters: None,
        }
    }
}

fn on(v: Option<f32>) -> Option<f32> {
    v.filter(|&x| x > 0.0)
}

impl ArtifactParams {
    /// Check every field (names the bad one).
    pub fn validate(&self) -> Result<()> {
        let bad = |name: &str, v: f32, what: &str| {
            Err(Error::InvalidArgument(format!(
                "{name} must be {what}, got {v}"
            )))
        };
        for (name, v) in [
            ("depth", self.depth),
            ("view_color", self.view_color),
            ("dilate", self.dilate),
        ] {
            if let Some(v) = v {
                if !(v.is_finite() && v >= 0.0) {
                    return bad(name, v, "a finite number >= 0");
                }
            }
        }
        if let Some(v) = self.floaters {
            if !(0.0..=10.0).contains(&v) {
                return bad(
                    "floaters",
                    v,
                    "a density in [0, 10] per thousand training pixels",
                );
            }
        }
        for (name, v) in [("needles", self.needles), ("holes", self.holes)] {
            if let Some(v) = v {
                if !(0.0..=1.0).contains(&v) {
                    return bad(name, v, "a fraction in [0, 1]");
                }
            }
        }
        if !(self.hole_size.is_finite() && self.hole_size > 0.0) {
            return bad("hole_size", self.hole_size, "a finite number > 0");
        }
        if self.depth.is_some_and(|d| d > 4.0) {
            return bad(
                "depth",
                self.depth.unwrap_or(0.0),
                "at most 4 (a factor e^4 at one sigma)",
            );
        }
        if self.dilate.is_some_and(|d| d > 8.0) {
            return bad(
                "dilate",
                self.dilate.unwrap_or(0.0),
                "at most 8 (a factor e^8)",
            );
        }
        Ok(())
    }

    /// Whether an enabled op needs training cameras (every op but `holes` and `dilate`).
    pub fn needs_cameras(&self) -> bool {
        [self.depth, self.view_color, self.needles, self.floaters]
            .iter()
            .any(|v| on(*v).is_some())
    }

    /// Whether any op is enabled.
    pub fn any(&self) -> bool {
        self.needs_cameras() || on(self.holes).is_some() || on(self.dilate).is_some()
    }
}

/// The clean renders of the training cameras, every camera of size W x H: `rgb` `(K, H, W, 3)`
/// float32 in [0, 1] (the colours floaters take) and `depth` `(K, H, W)`, the expected camera z
/// (0 where nothing is hit), which tells which Gaussians a training view sees (not occluded).
#[derive(Debug, Clone, Copy)]
pub struct TrainImages<'a> {
    pub rgb: &'a [f32],
    pub depth: &'a [f32],
    pub width: u32,
    pub height: u32,
}

/// A Gaussian counts as seen by a training view unless its camera z is more than this factor
/// times the view's expected depth at its pixel: clearly behind the surface. (The expected depth
/// averages what a pixel blends, so a tighter factor would call semi-transparent layers hidden.)
pub const OCCLUSION_SLACK: f32 = 2.0;

/// One training camera's centre, world-to-camera rotation and intrinsics (f32 as the scene).
#[derive(Debug, Clone, Copy)]
pub(super) struct Train {
    pub(super) centre: [f32; 3],
    pub(super) rot: [[f32; 3]; 3],
    pub(super) fx: f32,
    pub(super) fy: f32,
    pub(super) cx: f32,
    pub(super) cy: f32,
    pub(super) width: u32,
    pub(super) height: u32,
}

impl Train {
    /// The pixel of world point `p` and its depth, when it lies in front of the camera and
    /// within the image widened by `margin` pixels.
    fn sees(&self, p: [f32; 3], margin: f32) -> Option<[f32; 3]> {
        let d = sub(p, self.centre);
        let z = dot(self.rot[2], d);
        if z.is_nan() || z <= 1e-6 {
            return None;
        }
        let u = self.fx * dot(self.rot[0], d) / z + self.cx;
        let v = self.fy * dot(self.rot[1], d) / z + self.cy;
        let (w, h) = (self.width as f32, self.height as f32);
        ((-margin..w + margin).contains(&u) && (-margin..h + margin).contains(&v))
            .then_some([u, v, z])
    }

    pub(super) fn of(cam: &Camera) -> Train {
        let c = cam.center();
        let r = cam.rotation();
        let f = |v: f64| v as f32;
        Train {
            centre: [f(c[0]), f(c[1]), f(c[2])],
            rot: r.map(|row| row.map(f)),
            fx: f(cam.fx),
            fy: f(cam.fy),
            cx: f(cam.cx),
            cy: f(cam.cy),
            width: cam.width,
            height: cam.height,
        }
    }
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The unit vector of `v` (None for a zero or non-finite one).
fn unit(v: [f32; 3]) -> Option<[f32; 3]> {
    let n = dot(v, v).sqrt();
    (n.is_finite() && n > 0.0).then(|| [v[0] / n, v[1] / n, v[2] / n])
}

/// Indices of the `m` training cameras nearest `p` (ties: the lower index), nearest first.
fn nearest(cams: &[Train], p: [f32; 3], m: usize, out: &mut [usize; VIEW_COLOR_PINS]) -> usize {
    let mut best = [(f32::INFINITY, usize::MAX); VIEW_COLOR_PINS];
    let m = m.min(VIEW_COLOR_PINS).min(cams.len());
    for (k, c) in cams.iter().enumerate() {
        let d = sub(p, c.centre);
        let d2 = dot(d, d);
        // insertion into the sorted `best[..m]` (strict <: an equal distance keeps the earlier camera)
        let mut j = m;
        while j > 0 && d2 < best[j - 1].0 {
            j -= 1;
        }
        if j < m {
            for t in (j + 1..m).rev() {
                best[t] = best[t - 1];
            }
            best[j] = (d2, k);
        }
    }
    let mut found = 0;
    for (o, (d2, k)) in out.iter_mut().zip(best.iter()).take(m) {
        if d2.is_finite() {
            *o = *k;
            found += 1;
        }
    }
    found
}

/// The quaternion (w, x, y, z) turning the local x axis onto the unit vector `d`.
fn quat_x_to(d: [f32; 3]) -> [f32; 4] {
    let w = 1.0 + d[0];
    if w < 1e-6 {
        return [0.0, 0.0, 0.0, 1.0]; // d = -x: a half turn about z
    }
    let q = [w, 0.0, -d[2], d[1]];
    let n = (q[0] * q[0] + q[2] * q[2] + q[3] * q[3]).sqrt();
    [q[0] / n, 0.0, q[2] / n, q[3] / n]
}

/// Enabled ops with their stream keys and derived constants.
struct Plan<'a> {
    cams: Vec<Train>,
    images: Option<TrainImages<'a>>,
    depth: Option<(u64, f32)>,
    view_color: Option<(u64, f32)>,
    needles: Option<(u64, f32)>,
    holes: Option<(u64, f32, f32, [f32; 3])>,
    dilate: Option<f32>,
    floaters: Option<u64>,
    extent: f32,
    k3_in: usize,
    k3_out: usize,
    /// SH degree the view-dependent noise reaches (the output's, at most 3).
    basis_degree: u8,
}

/// Apply the sparse-view ops to `view`. Returns the new scene (the input's rows in order, then
/// the floaters; SH degree at least 1 when `view_color` is on) and the keep mask of its rows
/// (false: emptied by a hole). `extras` follow the input rows (0 for floaters).
///
/// `cameras` are the virtual training cameras; `images` their clean renders (floaters' colours;
/// without them floaters are mid grey).
///
/// Errors: [`Error::InvalidArgument`] naming the field for invalid parameters, an op that needs
/// cameras without any, images that do not match the cameras, inconsistent array lengths.
pub fn apply(
    view: &SceneView<'_>,
    extras: &[(&str, &[f32])],
    params: &ArtifactParams,
    cameras: &[Camera],
    images: Option<TrainImages<'_>>,
    seed: u64,
) -> Result<(Scene, Vec<bool>)> {
    view.validate()?;
    params.validate()?;
    let n = view.len();
    super::check_extras(extras, n)?;
    if params.needs_cameras() && cameras.is_empty() {
        return Err(Error::InvalidArgument(
            "depth, view_color, needles and floaters need training cameras (none given)".into(),
        ));
    }
    if let Some(im) = images {
        let px = cameras.len() * im.width as usize * im.height as usize;
        if im.rgb.len() != px * 3
            || im.depth.len() != px
            || cameras
                .iter()
                .any(|c| c.width != im.width || c.height != im.height)
        {
            return Err(Error::InvalidArgument(format!(
                "images: expected {} renders of {}x{} (one per training camera), got {} colour and {} depth values",
                cameras.len(),
                im.width,
                im.height,
                im.rgb.len(),
                im.depth.len()
            )));
        }
    }
    let extent = mean_extent(view) as f32;
    let k3_in = view.sh_rest_k() * 3;
    let degree_out = if on(params.view_color).is_some() {
        view.sh_degree.max(1)
    } else {
        view.sh_degree
    };
    let k3_out = sh_rest_count(degree_out) * 3;
    let holes = on(params.holes).map(|p| {
        let key = op_key(seed, OP_HOLES);
        let cell = params.hole_size * extent.max(f32::MIN_POSITIVE);
        // the grid's offset: a uniform shift of up to one cell per axis, from the seed
        let s = Stream::new(key, u64::MAX);
        let off = [0u64, 1, 2].map(|w| (s.word(w) >> 40) as f32 * (1.0 / 16_777_216.0) * cell);
        (key, p, cell, off)
    });
    let plan = Plan {
        cams: cameras.iter().map(Train::of).collect(),
        images,
        depth: on(params.depth).map(|s| (op_key(seed, OP_DEPTH), s)),
        view_color: on(params.view_color).map(|s| (op_key(seed, OP_VIEW_COLOR), s)),
        needles: on(params.needles).map(|p| (op_key(seed, OP_NEEDLES), p)),
        holes,
        dilate: on(params.dilate),
        floaters: on(params.floaters).map(|_| op_key(seed, OP_FLOATERS)),
        extent,
        k3_in,
        k3_out,
        basis_degree: degree_out.min(3),
    };
    let pixels: f64 = cameras
        .iter()
        .map(|c| f64::from(c.width) * f64::from(c.height))
        .sum();
    let n_float = match on(params.floaters) {
        // f64 product, rounded half up
        Some(f) => (f64::from(f) * pixels / 1000.0 + 0.5).floor() as usize,
        None => 0,
    };
    let m = n + n_float;
    let mut out = Scene {
        means: vec![0.0; m * 3],
        quats: vec![0.0; m * 4],
        log_scales: vec![0.0; m * 3],
        opacity_logits: vec![0.0; m],
        sh0: vec![0.0; m * 3],
        sh_rest: vec![0.0; m * k3_out.max(1)],
        sh_degree: degree_out,
        extras: extras
            .iter()
            .map(|(name, v)| {
                let mut e = v.to_vec();
                e.resize(m, 0.0);
                ((*name).to_owned(), e)
            })
            .collect(),
    };
    let mut keep = vec![true; m];
    let rest_w = CHUNK * k3_out.max(1);
    (
        out.means.par_chunks_mut(CHUNK * 3),
        out.quats.par_chunks_mut(CHUNK * 4),
        out.log_scales.par_chunks_mut(CHUNK * 3),
        out.opacity_logits.par_chunks_mut(CHUNK),
        out.sh0.par_chunks_mut(CHUNK * 3),
        out.sh_rest.par_chunks_mut(rest_w),
        keep.par_chunks_mut(CHUNK),
    )
        .into_par_iter()
        .enumerate()
        .for_each(|(c, (mu, q, ls, op, s0, rest, kp))| {
            for l in 0..op.len() {
                let i = c * CHUNK + l;
                let row = Row {
                    mu: &mut mu[l * 3..l * 3 + 3],
                    q: &mut q[l * 4..l * 4 + 4],
                    ls: &mut ls[l * 3..l * 3 + 3],
                    op: &mut op[l],
                    s0: &mut s0[l * 3..l * 3 + 3],
                    rest: &mut rest[l * k3_out..(l + 1) * k3_out],
                    keep: &mut kp[l],
                };
                if i < n {
                    plan.gaussian(view, i, row);
                } else {
                    plan.floater(i - n, row);
                }
            }
        });
    out.sh_rest.truncate(m * k3_out);
    Ok((out, keep))
}

/// One output row (means 3, quats 4, log scales 3, sh0 3 and `k3_out` SH values).
struct Row<'r> {
    mu: &'r mut [f32],
    q: &'r mut [f32],
    ls: &'r mut [f32],
    op: &'r mut f32,
    s0: &'r mut [f32],
    rest: &'r mut [f32],
    keep: &'r mut bool,
}

impl Plan<'_> {
    /// Whether training view `k` sees a Gaussian of radius `radius` (world units, 3 sigma) at
    /// `p`: its footprint reaches the image and, with the clean depth maps, it is not behind the
    /// surface there (camera z <= OCCLUSION_SLACK x depth, or no surface at that pixel). Returns
    /// its pixel.
    fn sees(&self, k: usize, p: [f32; 3], radius: f32) -> Option<[f32; 2]> {
        let cam = &self.cams[k];
        let d = sub(p, cam.centre);
        let z = dot(cam.rot[2], d);
        let margin = if z > 1e-6 { radius * cam.fx / z } else { 0.0 };
        let [u, v, z] = cam.sees(p, margin)?;
        if let Some(im) = self.images {
            let (x, y) = (u.floor(), v.floor());
            if (0.0..im.width as f32).contains(&x) && (0.0..im.height as f32).contains(&y) {
                let o = (k * im.height as usize + y as usize) * im.width as usize + x as usize;
                let surface = im.depth[o];
                if surface > 0.0 && z > OCCLUSION_SLACK * surface {
                    return None;
                }
            }
        }
        Some([u, v])
    }

    /// Copy input Gaussian `i` into `row` and apply the enabled ops.
    fn gaussian(&self, view: &SceneView<'_>, i: usize, row: Row<'_>) {
        let mu0 = [
            view.means[i * 3],
            view.means[i * 3 + 1],
            view.means[i * 3 + 2],
        ];
        let mut mu = mu0;
        let mut q = [
            view.quats[i * 4],
            view.quats[i * 4 + 1],
            view.quats[i * 4 + 2],
            view.quats[i * 4 + 3],
        ];
        let mut ls = [
            view.log_scales[i * 3],
            view.log_scales[i * 3 + 1],
            view.log_scales[i * 3 + 2],
        ];
        row.s0.copy_from_slice(&view.sh0[i * 3..i * 3 + 3]);
        let kin = self.k3_in.min(self.k3_out);
        row.rest[..kin].copy_from_slice(&view.sh_rest[i * self.k3_in..i * self.k3_in + kin]);
        *row.op = view.opacity_logits[i];
        let finite = mu0.iter().all(|v| v.is_finite());
        let mut near = [0usize; VIEW_COLOR_PINS];
        let found = if finite && !self.cams.is_empty() {
            nearest(&self.cams, mu0, 1, &mut near)
        } else {
            0
        };
        if let Some((key, p, cell, off)) = self.holes {
            if finite {
                let h = (0..3).fold(0u64, |h, d| {
                    let k = ((mu0[d] + off[d]) / cell).floor() as i64;
                    mix64(h ^ (k as u64).wrapping_mul(GAMMA).wrapping_add(d as u64))
                });
                *row.keep = Stream::new(key, h).uniform() >= p;
            }
        }
        // the ray of the nearest training camera through the clean centre, and the interval of
        // log depths along it that every other training view accepts
        let ray = (found > 0)
            .then(|| unit(sub(mu0, self.cams[near[0]].centre)))
            .flatten();
        let reach = self
            .depth
            .map_or(0.0, |(_, s)| (4.0 * s).min(4.0))
            .max(NEEDLE_LOG_LENGTH);
        let radius = 3.0 * fastmath::exp(ls[0].max(ls[1]).max(ls[2]));
        let span = match ray {
            Some(_) if self.depth.is_some() || self.needles.is_some() => {
                self.ambiguity(mu0, radius, near[0], reach)
            }
            _ => (0.0, 0.0),
        };
        if let (Some((key, sigma)), Some(_)) = (self.depth, ray) {
            let z = normal_pair(Stream::new(key, i as u64).word(0)).0;
            let lf = (sigma * z).clamp(span.0, span.1);
            let f = fastmath::exp(lf);
            let c = self.cams[near[0]].centre;
            for d in 0..3 {
                mu[d] = c[d] + (mu0[d] - c[d]) * f;
                ls[d] += lf;
            }
        }
        if let (Some((key, p)), Some(d)) = (self.needles, ray) {
            if Stream::new(key, i as u64).uniform() < p {
                // smeared over the accepted depths around its centre (a symmetric interval)
                let half = fastmath::exp(span.1.min(-span.0)) - 1.0;
                let dist = dot(sub(mu, self.cams[near[0]].centre), d);
                let r = (ls[0] + ls[1] + ls[2]) / 3.0;
                let len = if half > 0.0 {
                    fastmath::ln(0.5 * half * dist)
                } else {
                    r
                };
                if len > r {
                    ls = [len.min(r + NEEDLE_LOG_LENGTH), r, r];
                    q = quat_x_to(d);
                }
            }
        }
        if let Some(dl) = self.dilate {
            for v in &mut ls {
                *v += dl;
            }
        }
        if let Some((key, sigma)) = self.view_color {
            let pins = self.pins(mu, &mut near);
            self.view_noise(key, sigma, i as u64, mu, &near[..pins], row.rest);
        }
        row.mu.copy_from_slice(&mu);
        row.q.copy_from_slice(&q);
        row.ls.copy_from_slice(&ls);
    }

    /// The interval (lo <= 0 <= hi) of log depth factors along the ray of camera `c` through
    /// `mu0`, within [-reach, reach], at which every other training camera that sees the
    /// Gaussian (at either end) sees it at both and within [`TOLERANCE_PX`] of where it was:
    /// the depths the training views cannot tell apart. Bisection on each side (the projection
    /// moves monotonically along the epipolar line).
    fn ambiguity(&self, mu0: [f32; 3], radius: f32, c: usize, reach: f32) -> (f32, f32) {
        let centre = self.cams[c].centre;
        let before: Vec<Option<[f32; 2]>> = (0..self.cams.len())
            .map(|k| self.sees(k, mu0, radius))
            .collect();
        // in its own view it keeps its footprint; seen there, it may not go behind the surface
        let own = self.cams[c].sees(mu0, 0.0).map(|p| p[2]);
        let surface = match (self.images, own, self.cams[c].sees(mu0, 0.0)) {
            (Some(im), Some(_), Some([u, v, _])) => {
                let (x, y) = (
                    (u as usize).min(im.width as usize - 1),
                    (v as usize).min(im.height as usize - 1),
                );
                im.depth[(c * im.height as usize + y) * im.width as usize + x]
            }
            _ => 0.0,
        };
        let ok = |lf: f32| {
            let f = fastmath::exp(lf);
            if let (Some(z), true) = (own, surface > 0.0) {
                // seen in its own view (at the surface): it may come forward, never go back
                if z <= OCCLUSION_SLACK * surface && f > 1.0 {
                    return false;
                }
                // hidden there: it may come forward only up to the surface
                if z > OCCLUSION_SLACK * surface && z * f < surface {
                    return false;
                }
            }
            let p = [0, 1, 2].map(|d| centre[d] + (mu0[d] - centre[d]) * f);
            (0..self.cams.len()).all(|k| {
                if k == c {
                    return true;
                }
                match (before[k], self.sees(k, p, radius * f)) {
                    (None, None) => true,
                    (Some(a), Some(b)) => {
                        let (du, dv) = (a[0] - b[0], a[1] - b[1]);
                        du * du + dv * dv <= TOLERANCE_PX * TOLERANCE_PX
                    }
                    _ => false,
                }
            })
        };
        let side = |sign: f32| {
            if ok(sign * reach) {
                return sign * reach;
            }
            let (mut good, mut bad) = (0.0f32, reach);
            for _ in 0..16 {
                let mid = 0.5 * (good + bad);
                if ok(sign * mid) {
                    good = mid;
                } else {
                    bad = mid;
                }
            }
            sign * good
        };
        (side(-1.0), side(1.0))
    }

    /// The training cameras that see `mu` (in their image), nearest first, at most
    /// `VIEW_COLOR_PINS` and one fewer than the SH coefficients (some noise must remain).
    fn pins(&self, mu: [f32; 3], out: &mut [usize; VIEW_COLOR_PINS]) -> usize {
        // (only the centre counts here: the pins are directions, the colour is per Gaussian)
        let cap = VIEW_COLOR_PINS.min(sh_rest_count(self.basis_degree) - 1);
        let mut best = [(f32::INFINITY, usize::MAX); VIEW_COLOR_PINS];
        let mut n = 0;
        for (k, c) in self.cams.iter().enumerate() {
            if self.sees(k, mu, 0.0).is_none() {
                continue;
            }
            let d = sub(mu, c.centre);
            let d2 = dot(d, d);
            let mut j = n.min(cap);
            while j > 0 && d2 < best[j - 1].0 {
                j -= 1;
            }
            if j < cap {
                for t in (j + 1..cap).rev() {
                    best[t] = best[t - 1];
                }
                best[j] = (d2, k);
                n = (n + 1).min(cap);
            }
        }
        for (o, b) in out.iter_mut().zip(best.iter()).take(n) {
            *o = b.1;
        }
        n
    }

    /// SH noise of `sigma` on bands 1-3 of `rest`, projected onto the null space of the basis at
    /// the directions from the cameras `near` to `mu` (f64 Gram-Schmidt: deterministic).
    fn view_noise(
        &self,
        key: u64,
        sigma: f32,
        i: u64,
        mu: [f32; 3],
        near: &[usize],
        rest: &mut [f32],
    ) {
        let nb = sh_rest_count(self.basis_degree); // coefficients past the DC term
        let mut rows = [[0f64; 15]; VIEW_COLOR_PINS];
        let mut kept = 0;
        for &k in near {
            let Some(dir) = unit(sub(mu, self.cams[k].centre)) else {
                continue;
            };
            let mut b = [0f32; 16];
            sh::basis(self.basis_degree, dir, &mut b);
            let mut v = [0f64; 15];
            for j in 0..nb {
                v[j] = f64::from(b[j + 1]);
            }
            for prev in rows.iter().take(kept) {
                let p: f64 = (0..nb).map(|j| v[j] * prev[j]).sum();
                for j in 0..nb {
                    v[j] -= p * prev[j];
                }
            }
            let norm = (0..nb).map(|j| v[j] * v[j]).sum::<f64>().sqrt();
            if norm > 1e-6 {
                for j in 0..nb {
                    v[j] /= norm;
                }
                rows[kept] = v;
                kept += 1;
            }
        }
        let s = Stream::new(key, i);
        for ch in 0..3 {
            let mut delta = [0f64; 15];
            for (j, dj) in delta.iter_mut().enumerate().take(nb) {
                let w = (ch * 15 + j) as u64;
                let (a, b) = normal_pair(s.word(w / 2));
                *dj = f64::from(sigma * if w.is_multiple_of(2) { a } else { b });
            }
            for r in rows.iter().take(kept) {
                let p: f64 = (0..nb).map(|j| delta[j] * r[j]).sum();
                for j in 0..nb {
                    delta[j] -= p * r[j];
                }
            }
            for (j, dj) in delta.iter().enumerate().take(nb) {
                rest[j * 3 + ch] += *dj as f32;
            }
        }
    }

    /// Floater `j`: on the ray of a random pixel of a random training camera (see the module docs).
    fn floater(&self, j: usize, row: Row<'_>) {
        let Some(key) = self.floaters else { return };
        // candidate t uses words 16 t .. 16 t + 9 of the floater's stream; the first that no
        // other training camera sees wins (the views it would be seen in would reject it), else
        // the last
        let s = Stream::new(key, j as u64);
        let (lo, hi) = (fastmath::ln(FLOATER_NEAR), fastmath::ln(FLOATER_FAR));
        let mut pick = (0, 0.0f32, 0.0f32, [0f32; 3], 0.0f32, 0u64);
        for t in 0..FLOATER_TRIES {
            let u = |w: u64| (s.word(16 * t + w) >> 40) as f32 * (1.0 / 16_777_216.0);
            let k = ((u(0) * self.cams.len() as f32) as usize).min(self.cams.len() - 1);
            let cam = &self.cams[k];
            let px = u(1) * cam.width as f32;
            let py = u(2) * cam.height as f32;
            let local = [(px - cam.cx) / cam.fx, (py - cam.cy) / cam.fy, 1.0];
            // world direction R^T local (R world-to-camera), depth along the optical axis
            let dir = [0, 1, 2].map(|d| {
                cam.rot[0][d] * local[0] + cam.rot[1][d] * local[1] + cam.rot[2][d] * local[2]
            });
            let depth = self.extent * fastmath::exp(lo + u(3) * (hi - lo));
            let p = [0, 1, 2].map(|d| cam.centre[d] + dir[d] * depth);
            pick = (k, px, py, p, depth, 16 * t);
            let hidden = (0..self.cams.len()).all(|o| o == k || self.sees(o, p, 0.0).is_none());
            if hidden {
                break;
            }
        }
        let (k, px, py, p, depth, w0) = pick;
        let cam = &self.cams[k];
        let u = |w: u64| (s.word(w0 + w) >> 40) as f32 * (1.0 / 16_777_216.0);
        row.mu.copy_from_slice(&p);
        let (p_lo, p_hi) = (fastmath::ln(1.5), fastmath::ln(12.0));
        let pixels = fastmath::exp(p_lo + u(4) * (p_hi - p_lo));
        let r = fastmath::ln(depth * pixels / cam.fx);
        let z = [5u64, 6].map(|w| normal_pair(s.word(w0 + w)));
        row.ls
            .copy_from_slice(&[r + 0.35 * z[0].0, r + 0.35 * z[0].1, r + 0.35 * z[1].0]);
        let (a, b) = normal_pair(s.word(w0 + 7));
        let qn = [z[1].1, a, b, normal_pair(s.word(w0 + 8)).0];
        let norm = (qn[0] * qn[0] + qn[1] * qn[1] + qn[2] * qn[2] + qn[3] * qn[3]).sqrt();
        row.q.copy_from_slice(&if norm > 0.0 {
            qn.map(|v| v / norm)
        } else {
            [1.0, 0.0, 0.0, 0.0]
        });
        let alpha = 0.2 + 0.7 * u(9);
        *row.op = fastmath::ln(alpha / (1.0 - alpha));
        let rgb = match self.images {
            Some(im) => {
                let (x, y) = (
                    (px as usize).min(im.width as usize - 1),
                    (py as usize).min(im.height as usize - 1),
                );
                let o = ((k * im.height as usize + y) * im.width as usize + x) * 3;
                [im.rgb[o], im.rgb[o + 1], im.rgb[o + 2]]
            }
            None => [0.5; 3],
        };
        row.s0.copy_from_slice(&rgb.map(|c| (c - 0.5) / SH_C0));
        row.rest.fill(0.0);
        *row.keep = true;
    }
}

#[cfg(test)]
mod tests;
