//! The `shatter` op (op 16; docs/artifacts.md): what a 3DGS fit from a few views is made of,
//! built without a fit.
//!
//! A fit from K views starts from points spread along the training rays and can only learn what
//! those views see: it reproduces each training pixel with whatever Gaussians lie on its ray, at
//! whatever depth they started. Seen from a training view the result is right; seen from between
//! them, the surfaces break into confetti of small splats at the wrong depths, coloured like the
//! pixels they were fitted to. At value v:
//!
//! - each Gaussian of the scene is removed with probability p = 1 - exp(-v) ([`removal`]);
//! - each pixel of each training view (alpha > 0.5 in its clean render, a finite positive depth)
//!   spawns, with probability q = min(p, [`BUDGET`] x the removals / ([`PER_PIXEL`] x the valid
//!   pixels)), [`PER_PIXEL`] fragments ([`fragments`]): small isotropic Gaussians on that
//!   pixel's ray (each through a uniform point of the pixel) at depth d' = d exp(sigma z),
//!   z ~ N(0, 1), sigma = [`DEPTH_SPREAD`] v, clipped to [d / c, d c], c = max([`DEPTH_CLIP`],
//!   e^sigma) (the fixed clip up to v = 4.6, one sigma beyond, so sparser regimes stay within
//!   reach), d the clean depth there; a log-normal footprint of median [`FOOTPRINT_PX`] pixel in that
//!   view; opacities that stack to the pixel's alpha;
//! - each fragment's colour is view-dependent (SH bands 0 and 1), fitted by least squares to its
//!   own pixel (weight [`OWN_WEIGHT`]) and to the pixel of every other training view whose image
//!   holds it, as a fit makes its splats match every training view they can (a ridge on band 1
//!   keeps it small where the views disagree);
//! - a fragment the views cannot agree on (a colour error above `max_error` RMS in one of them,
//!   or a footprint sigma above [`MAX_FOOTPRINT_PX`] in another view its footprint reaches: 3
//!   sigma, the centre inside the image or not) is dropped, as a fit makes
//!   what it cannot reconcile transparent (or, with `drop` off, put back onto the surface with
//!   its pixel's colour).
//!
//! Every draw is keyed by `(seed, op 16, index)`: a Gaussian's index for its removal, a training
//! pixel's index (with the top bit set) for its spawn, jitter, depth and footprint. So a larger
//! value removes a superset of the Gaussians and spawns at a superset of the pixels, the same
//! fragments spread further. Each fragment is computed from its own draws alone and the output is
//! in (view, fragment slot, pixel) order, so the bytes are the same for any thread count; only
//! exactly rounded operations and `fastmath`'s `exp`/`ln` are used, so they are the same on
//! every CPU.
use rayon::prelude::*;

use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::fastmath;
use crate::rng::{normal_pair, op_key, Stream};

/// The op's id in the seed (after the sparse-view ops 10-14 and popping's 15).
pub const OP_SHATTER: u32 = 16;
/// Fragments per spawning pixel. A sparse fit of the built-in room from 5 of 96 views (sparse:20,
/// 3000 steps, docs/artifacts.md) holds 2.6 Gaussians per training pixel.
pub const PER_PIXEL: usize = 3;
/// Log-depth spread per unit of value: at v = 2, sigma = 0.6, the spread of that fit's Gaussians
/// about the true surface along their nearest training ray (log depth ratio IQR -0.34..0.44).
pub const DEPTH_SPREAD: f32 = 0.3;
/// Fragments stay within this factor of the surface depth (that fit: 5-95 % within 3.4), or
/// within one sigma of it where that is wider (v > 4.6).
pub const DEPTH_CLIP: f64 = 4.0;
/// Median footprint sigma (pixels) in the spawning view.
pub const FOOTPRINT_PX: f32 = 0.5;
/// Log-normal sigma of the footprint.
pub const FOOTPRINT_SPREAD: f32 = 0.5;
/// The largest footprint sigma (pixels) a fragment may have in another training view that sees it.
pub const MAX_FOOTPRINT_PX: f64 = 3.0;
/// The default largest colour error (RMS over the channels) in a view the fragment is fitted to.
pub const MAX_ERROR: f64 = 0.08;
/// At most this many fragments per removed Gaussian (large training views spawn at fewer pixels).
pub const BUDGET: f64 = 4.0;
/// The weight of a fragment's own pixel in its colour fit (each other view: 1).
pub const OWN_WEIGHT: f64 = 4.0;
/// The default ridge on the band-1 coefficients of the colour fit.
pub const RIDGE: f64 = 1.0;

const SH_C0: f64 = 0.282_094_791_773_878_14;
const SH_C1: f64 = 0.488_602_511_902_919_9;
/// Marks a pixel's stream index apart from the Gaussians' (removal) indices.
const PIXEL_STREAM: u64 = 1 << 63;

/// Parameters of [`fragments`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShatterParams {
    /// The op's value v (> 0; 0 makes no fragment).
    pub value: f32,
    /// Ridge on the band-1 SH coefficients of the colour fit (>= 0).
    pub ridge: f64,
    /// The largest RMS colour error a kept fragment may have in a view it is fitted to (> 0).
    pub max_error: f64,
    /// Drop a fragment the views cannot agree on (true) or put it back on the surface (false).
    pub drop: bool,
}

impl Default for ShatterParams {
    fn default() -> Self {
        ShatterParams {
            value: 1.0,
            ridge: RIDGE,
            max_error: MAX_ERROR,
            drop: true,
        }
    }
}

impl ShatterParams {
    /// Check every field (names the bad one).
    pub fn validate(&self) -> Result<()> {
        if !(self.value.is_finite() && self.value >= 0.0) {
            return Err(Error::InvalidArgument(format!(
                "shatter value must be a finite number >= 0, got {}",
                self.value
            )));
        }
        if !(self.ridge.is_finite() && self.ridge >= 0.0) {
            return Err(Error::InvalidArgument(format!(
                "shatter ridge must be a finite number >= 0, got {}",
                self.ridge
            )));
        }
        if !(self.max_error.is_finite() && self.max_error > 0.0) {
            return Err(Error::InvalidArgument(format!(
                "shatter max_error must be a finite number > 0, got {}",
                self.max_error
            )));
        }
        Ok(())
    }
}

/// The clean renders of the training views: `rgb` (T, H, W, 3), `depth` and `alpha` (T, H, W),
/// row-major, T the number of cameras.
#[derive(Debug, Clone, Copy)]
pub struct Views<'a> {
    pub rgb: &'a [f32],
    pub depth: &'a [f32],
    pub alpha: &'a [f32],
}

/// The fragments, one row each: isotropic Gaussians (identity rotation) with SH bands 0 and 1.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Fragments {
    pub means: Vec<[f32; 3]>,
    /// The natural log of the (isotropic) scale.
    pub log_scales: Vec<f32>,
    pub opacity_logits: Vec<f32>,
    pub sh0: Vec<[f32; 3]>,
    /// Band-1 coefficients, `[coefficient][channel]` (the scene's `sh_rest` rows 0-2).
    pub sh1: Vec<[[f32; 3]; 3]>,
    /// The training view each was spawned from.
    pub view: Vec<u32>,
}

impl Fragments {
    /// Number of fragments.
    pub fn len(&self) -> usize {
        self.means.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }
}

/// The removal probability at `value`: 1 - exp(-v).
fn share(value: f32) -> f32 {
    1.0 - fastmath::exp(-value)
}

/// Which of `n` Gaussians shatter removes at `value` (true: removed): Gaussian i is removed when
/// its uniform is below 1 - exp(-v), the same uniform at every value, so a larger value removes a
/// superset.
pub fn removal(n: usize, value: f32, seed: u64) -> Vec<bool> {
    let key = op_key(seed, OP_SHATTER);
    let p = if value > 0.0 { share(value) } else { 0.0 };
    (0..n as u64)
        .into_par_iter()
        .map(|i| Stream::new(key, i).uniform() < p)
        .collect()
}

/// A training camera in the form the fragments need.
struct View {
    rot: [[f64; 3]; 3],
    trans: [f64; 3],
    centre: [f64; 3],
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    focal: f64,
}

impl View {
    fn of(cam: &Camera) -> View {
        View {
            rot: cam.rotation(),
            trans: cam.translation(),
            centre: cam.center(),
            fx: cam.fx,
            fy: cam.fy,
            cx: cam.cx,
            cy: cam.cy,
            focal: 0.5 * (cam.fx + cam.fy),
        }
    }

    /// The SH basis up to band 1 (3DGS's convention) of the direction from the camera to `p`.
    fn basis(&self, p: [f64; 3]) -> [f64; 4] {
        let d = [
            p[0] - self.centre[0],
            p[1] - self.centre[1],
            p[2] - self.centre[2],
        ];
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-12);
        let (x, y, z) = (d[0] / n, d[1] / n, d[2] / n);
        [SH_C0, -SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    }
}

/// One fragment's result (before the opacity, which depends on its pixel only).
struct Frag {
    mean: [f32; 3],
    log_scale: f32,
    sh0: [f32; 3],
    sh1: [[f32; 3]; 3],
    opacity_logit: f32,
    view: u32,
}

/// A pixel's draws for its fragment `k`: (depth normal, footprint normal, jitter x, jitter y).
fn draws(s: &Stream, k: usize) -> (f32, f32, f64, f64) {
    let (z, size) = normal_pair(s.word(1 + 2 * k as u64));
    let j = s.word(2 + 2 * k as u64);
    let u = |bits: u64| (bits & 0x00ff_ffff) as f64 * (1.0 / 16_777_216.0);
    (z, size, u(j >> 40), u(j >> 8))
}

/// The fragments of the training views `cams` (module doc), whose clean renders are `views`;
/// `removed` is how many Gaussians the op removed (the fragment budget is [`BUDGET`] times that).
///
/// Errors: invalid parameters, no cameras, cameras of different sizes, or maps of the wrong
/// length (each named).
pub fn fragments(
    params: &ShatterParams,
    cams: &[Camera],
    views: Views<'_>,
    removed: usize,
    seed: u64,
) -> Result<Fragments> {
    params.validate()?;
    let Some(first) = cams.first() else {
        return Err(Error::InvalidArgument(
            "shatter needs training cameras (none given)".into(),
        ));
    };
    let (w, h) = (first.width as usize, first.height as usize);
    if cams
        .iter()
        .any(|c| c.width != first.width || c.height != first.height)
    {
        return Err(Error::InvalidArgument(
            "shatter's training cameras must all have one size".into(),
        ));
    }
    let (t_n, px) = (cams.len(), w * h);
    for (name, got, want) in [
        ("rgb", views.rgb.len(), t_n * px * 3),
        ("depth", views.depth.len(), t_n * px),
        ("alpha", views.alpha.len(), t_n * px),
    ] {
        if got != want {
            return Err(Error::InvalidArgument(format!(
                "shatter's {name} maps hold {got} values, {want} expected for {t_n} views of {w}x{h}"
            )));
        }
    }
    let value = params.value;
    if value <= 0.0 {
        return Ok(Fragments::default());
    }
    let valid = |i: usize| {
        let d = views.depth[i];
        views.alpha[i] > 0.5 && d.is_finite() && d > 0.0
    };
    let n_valid = (0..t_n * px).filter(|&i| valid(i)).count();
    if n_valid == 0 {
        return Ok(Fragments::default());
    }
    let p = f64::from(share(value));
    let q = p.min(BUDGET * removed.max(1) as f64 / (PER_PIXEL as f64 * n_valid as f64));
    let key = op_key(seed, OP_SHATTER);
    // opacity: the fragments over a pixel (PER_PIXEL q of them, each covering about
    // 2 pi FOOTPRINT_PX^2 pixels) stack up to its alpha
    let cover =
        (PER_PIXEL as f64 * q * 2.0 * std::f64::consts::PI * f64::from(FOOTPRINT_PX).powi(2))
            .max(1.0) as f32;
    let cams: Vec<View> = cams.iter().map(View::of).collect();
    let ctx = Ctx {
        cams: &cams,
        views,
        w,
        h,
        sigma: DEPTH_SPREAD * value,
        clip: DEPTH_CLIP.max(f64::from(fastmath::exp(DEPTH_SPREAD * value))),
        cover,
        params,
        key,
    };
    // one view at a time (the scratch lists stay one view's size): its spawning pixels in order
    // (the same uniform at every value: a larger q spawns at a superset), then its fragments in
    // (slot, pixel) order, computed in parallel
    let mut out = Fragments::default();
    for t in 0..t_n {
        let pix: Vec<u32> = (0..px)
            .filter(|&i| {
                let g = t * px + i;
                valid(g) && f64::from(Stream::new(key, PIXEL_STREAM | g as u64).uniform()) < q
            })
            .map(|i| i as u32)
            .collect();
        let frags: Vec<Frag> = (0..PER_PIXEL * pix.len())
            .into_par_iter()
            .map_init(Vec::new, |seen, j| {
                ctx.fragment(t, j / pix.len(), pix[j % pix.len()] as usize, seen)
            })
            .flatten_iter()
            .collect();
        for f in frags {
            out.means.push(f.mean);
            out.log_scales.push(f.log_scale);
            out.opacity_logits.push(f.opacity_logit);
            out.sh0.push(f.sh0);
            out.sh1.push(f.sh1);
            out.view.push(f.view);
        }
    }
    Ok(out)
}

struct Ctx<'a> {
    cams: &'a [View],
    views: Views<'a>,
    w: usize,
    h: usize,
    sigma: f32,
    /// The depth clip factor, max(DEPTH_CLIP, e^sigma).
    clip: f64,
    cover: f32,
    params: &'a ShatterParams,
    key: u64,
}

impl Ctx<'_> {
    fn rgb(&self, t: usize, i: usize) -> [f64; 3] {
        let o = (t * self.w * self.h + i) * 3;
        let c = &self.views.rgb[o..o + 3];
        [f64::from(c[0]), f64::from(c[1]), f64::from(c[2])]
    }

    /// Fragment `k` of pixel `i` of view `t` (None: dropped). `seen` is scratch space.
    fn fragment(
        &self,
        t: usize,
        k: usize,
        i: usize,
        seen: &mut Vec<([f64; 4], [f64; 3])>,
    ) -> Option<Frag> {
        let px = self.w * self.h;
        let g = t * px + i;
        let s = Stream::new(self.key, PIXEL_STREAM | g as u64);
        let (z, size, jx, jy) = draws(&s, k);
        let cam = &self.cams[t];
        let d = f64::from(self.views.depth[g]);
        let (x, y) = ((i % self.w) as f64 + jx, (i / self.w) as f64 + jy);
        let sigma_px = f64::from(FOOTPRINT_PX * fastmath::exp(FOOTPRINT_SPREAD * size));
        let place = |dd: f64| -> ([f64; 3], f64) {
            let c = [(x - cam.cx) / cam.fx * dd, (y - cam.cy) / cam.fy * dd, dd];
            let v = [
                c[0] - cam.trans[0],
                c[1] - cam.trans[1],
                c[2] - cam.trans[2],
            ];
            let r = &cam.rot;
            let world = [
                r[0][0] * v[0] + r[1][0] * v[1] + r[2][0] * v[2],
                r[0][1] * v[0] + r[1][1] * v[1] + r[2][1] * v[2],
                r[0][2] * v[0] + r[1][2] * v[1] + r[2][2] * v[2],
            ];
            (world, sigma_px * dd / cam.focal)
        };
        let f = f64::from(fastmath::exp(self.sigma * z));
        let d2 = (d * f).clamp(d / self.clip, d * self.clip);
        let (mut world, mut radius) = place(d2);
        let own = self.rgb(t, i);
        let own_c = [own[0] - 0.5, own[1] - 0.5, own[2] - 0.5];
        let (sh, fits) = self.fit_colour(t, world, radius, own_c, seen);
        let (sh0, sh1) = if fits {
            ([sh[0][0], sh[0][1], sh[0][2]], [sh[1], sh[2], sh[3]])
        } else if self.params.drop {
            return None;
        } else {
            (world, radius) = place(d);
            (own_c.map(|c| c / SH_C0), [[0.0; 3]; 3])
        };
        let target = (0.98 * self.views.alpha[g]).clamp(1e-4, 0.999);
        let a = (1.0 - fastmath::exp(fastmath::ln(1.0 - target) / self.cover)).clamp(1e-3, 0.99);
        Some(Frag {
            mean: world.map(|v| v as f32),
            log_scale: fastmath::ln(radius as f32),
            sh0: sh0.map(|v| v as f32),
            sh1: sh1.map(|r| r.map(|v| v as f32)),
            opacity_logit: fastmath::ln(a / (1.0 - a)),
            view: t as u32,
        })
    }

    /// The fragment's SH up to band 1 (rows: coefficient 0..4, columns: channel), least squares
    /// over its own pixel (weight OWN_WEIGHT) and every other view whose image holds it, and
    /// whether it fits: every such view's RMS colour error within `max_error` and its footprint
    /// within MAX_FOOTPRINT_PX pixels in each.
    fn fit_colour(
        &self,
        own_view: usize,
        p: [f64; 3],
        radius: f64,
        own: [f64; 3],
        seen: &mut Vec<([f64; 4], [f64; 3])>,
    ) -> ([[f64; 3]; 4], bool) {
        seen.clear();
        let own_b = self.cams[own_view].basis(p);
        let mut spread = 0.0f64;
        for (t, cam) in self.cams.iter().enumerate() {
            if t == own_view {
                continue;
            }
            let r = &cam.rot;
            let c =
                [0, 1, 2].map(|j| r[j][0] * p[0] + r[j][1] * p[1] + r[j][2] * p[2] + cam.trans[j]);
            let z = c[2];
            if z.is_nan() || z <= 1e-6 {
                continue;
            }
            let u = cam.fx * c[0] / z + cam.cx;
            let v = cam.fy * c[1] / z + cam.cy;
            // its footprint reaches the image (3 sigma) even where its centre is outside: a
            // fragment close to another camera covers that view (and must stay small there)
            let sigma = radius * cam.focal / z;
            let (wf, hf, reach) = (self.w as f64, self.h as f64, 3.0 * sigma);
            if !(u >= -reach && u < wf + reach && v >= -reach && v < hf + reach) {
                continue;
            }
            spread = spread.max(sigma);
            if !(u >= 0.0 && u < wf && v >= 0.0 && v < hf) {
                continue;
            }
            let pix = v as usize * self.w + u as usize;
            let target = self.rgb(t, pix);
            seen.push((cam.basis(p), target.map(|x| x - 0.5)));
        }
        // normal equations: OWN_WEIGHT b b^T for its own pixel, b b^T for every other view
        let mut ata = [[0.0f64; 4]; 4];
        let mut atb = [[0.0f64; 3]; 4];
        let mut add = |b: &[f64; 4], y: &[f64; 3], wgt: f64| {
            for r in 0..4 {
                for c in 0..4 {
                    ata[r][c] += wgt * b[r] * b[c];
                }
                for c in 0..3 {
                    atb[r][c] += wgt * b[r] * y[c];
                }
            }
        };
        add(&own_b, &own, OWN_WEIGHT);
        for (b, y) in seen.iter() {
            add(b, y, 1.0);
        }
        ata[0][0] += 1e-9;
        for (j, row) in ata.iter_mut().enumerate().skip(1) {
            row[j] += self.params.ridge;
        }
        let x = solve_spd4(ata, atb);
        let err = |b: &[f64; 4], y: &[f64; 3]| {
            let mut s = 0.0;
            for c in 0..3 {
                let e = b[0] * x[0][c] + b[1] * x[1][c] + b[2] * x[2][c] + b[3] * x[3][c] - y[c];
                s += e * e;
            }
            (s / 3.0).sqrt()
        };
        let mut worst = err(&own_b, &own);
        for (b, y) in seen.iter() {
            worst = worst.max(err(b, y));
        }
        let fits = worst <= self.params.max_error && spread <= MAX_FOOTPRINT_PX;
        (x, fits)
    }
}

/// Solve the symmetric positive definite 4x4 system `a x = b` (three right-hand sides) by
/// Cholesky (a fixed order of operations: the same bits everywhere).
fn solve_spd4(a: [[f64; 4]; 4], b: [[f64; 3]; 4]) -> [[f64; 3]; 4] {
    let mut l = [[0.0f64; 4]; 4];
    for i in 0..4 {
        for j in 0..=i {
            let mut s = a[i][j];
            for k in 0..j {
                s -= l[i][k] * l[j][k];
            }
            if i == j {
                l[i][i] = s.max(1e-300).sqrt();
            } else {
                l[i][j] = s / l[j][j];
            }
        }
    }
    let mut y = [[0.0f64; 3]; 4];
    for i in 0..4 {
        for c in 0..3 {
            let mut s = b[i][c];
            for k in 0..i {
                s -= l[i][k] * y[k][c];
            }
            y[i][c] = s / l[i][i];
        }
    }
    let mut x = [[0.0f64; 3]; 4];
    for i in (0..4).rev() {
        for c in 0..3 {
            let mut s = y[i][c];
            for k in i + 1..4 {
                s -= l[k][i] * x[k][c];
            }
            x[i][c] = s / l[i][i];
        }
    }
    x
}

#[cfg(test)]
mod tests;
