//! SSIM and its gradient, INRIA 3DGS's variant (`utils/loss_utils.py::ssim`): an 11x11 Gaussian
//! window of sigma 1.5 (normalised to sum 1), C1 = 0.01^2, C2 = 0.03^2, each channel on its own,
//! and **'same' zero padding**: the local statistics are taken with `conv2d(padding=5)`, so every
//! pixel has an SSIM value and the score is the mean over H x W x 3. (gsplat's trainer uses
//! fused-ssim with 'valid' padding, the mean over the (H-10) x (W-10) interior; see docs/fit.md.)
//!
//! The window is separable, so each local mean is a horizontal then a vertical 11-tap pass. With
//! mu_x = G*x, e_xx = G*(x^2), e_xy = G*(xy) and S the SSIM map, the gradient of sum_p g S(p)
//! with respect to the prediction x is
//!
//! ```text
//! dL/dx = G*(g dS/dmu_x) + 2 x G*(g dS/de_xx) + y G*(g dS/de_xy)
//! dS/dmu_x = S (2 mu_y / A1 - 2 mu_y / A2 - 2 mu_x / B1 + 2 mu_x / B2)
//! dS/de_xx = -S / B2,   dS/de_xy = 2 S / A2
//! ```
//!
//! (A1 = 2 mu_x mu_y + C1, A2 = 2 s_xy + C2, B1 = mu_x^2 + mu_y^2 + C1, B2 = s_xx + s_yy + C2;
//! the zero-padded blur is its own adjoint because the window is symmetric).
//!
//! With inv = 1 / (B1 B2) the map and the partials take one division per value instead of
//! seven: S = A1 A2 inv, S / A1 = A2 inv, S / A2 = A1 inv, S / B1 = S B2 inv, S / B2 = S B1 inv,
//! so dS/dmu_x = 2 inv (mu_y (A2 - A1) - mu_x S (B2 - B1)), dS/de_xx = -S B1 inv and
//! dS/de_xy = 2 A1 inv.
//!
//! Three stages stream down the image in row bands, one band per task (`band_rows`): (A) split
//! the channels and blur x, y, x^2, y^2, xy horizontally; (B) blur them vertically, form S and
//! the three partials, and blur the partials horizontally; (C) blur those vertically and
//! combine into the gradient, adding the L1 term's part (`SsimWorkspace::ssim_l1`). Each stage
//! keeps its last 12 rows in a ring, so no whole plane is written; B and C form two rows at a
//! time, loading each ring row once for both (`vblur2`). A band recomputes its halo rows, with
//! the same arithmetic. Every value is computed in a fixed order with plain IEEE multiplies,
//! adds and divisions (no FMA contraction, no approximate reciprocals), so the AVX-512, AVX2
//! and plain builds, any banding and any thread count give the same bits (those of the
//! whole-plane passes this replaced, see the tests). The mean is summed per channel row into 16
//! float64 lane accumulators (value i into lane i % 16, lanes combined pairwise in a fixed
//! order), the same arithmetic in every kernel, and the rows are added in order.
use rayon::prelude::*;

use crate::raster::Simd;

mod rows;
#[cfg(test)]
mod tests;

use rows::*;

/// Window radius (11 taps).
pub const RADIUS: usize = 5;
const TAPS: usize = 2 * RADIUS + 1;
pub const SIGMA: f64 = 1.5;
pub const C1: f32 = 0.01 * 0.01;
pub const C2: f32 = 0.03 * 0.03;

/// Lanes of the map's row sums.
pub(crate) const LANES: usize = 16;

/// The normalised 1D Gaussian window (INRIA `gaussian(11, 1.5)`).
pub fn window() -> [f32; TAPS] {
    let mut w = [0.0f64; TAPS];
    for (i, v) in w.iter_mut().enumerate() {
        let d = i as f64 - RADIUS as f64;
        *v = (-(d * d) / (2.0 * SIGMA * SIGMA)).exp();
    }
    let s: f64 = w.iter().sum();
    w.map(|v| (v / s) as f32)
}

/// Buffers of the SSIM, reused across calls: one set of rings and row buffers per band (see
/// `band_rows`), and the per-row sums.
#[derive(Default)]
pub struct SsimWorkspace {
    bands: Vec<Band>,
    row_sums: Vec<f64>,
    l1_sums: Vec<(f64, f64)>,
    /// Rows per band; 0 picks from the image height and the thread count (any value gives
    /// the same bits).
    pub band_rows: usize,
    /// Which row kernels run (all give the same bits).
    pub simd: Simd,
}

/// What every band of one call computes.
#[derive(Clone, Copy)]
struct Job<'a> {
    pred: &'a [f32],
    target: &'a [f32],
    w: usize,
    h: usize,
    clamp: bool,
    /// The map's gradient scale (with it, stages B and C run for the gradient).
    gs: Option<f32>,
    /// The L1 term's gradient scale (with it, stage C adds the L1 term and its sums).
    gl1: Option<f32>,
}

/// One band task's rings and row buffers, kept across calls.
struct Band {
    /// Stage A's ring: 11 slots of 5 quantities x 3 channels x W.
    a: Vec<f32>,
    /// Stage B's ring: 11 slots of 3 partials x 3 channels x W (gradient only).
    b: Vec<f32>,
    sc: Scratch,
}

impl Band {
    fn new(w: usize, grad: bool) -> Self {
        Band {
            a: vec![0.0; RING * 15 * w],
            b: vec![0.0; if grad { RING * 9 * w } else { 0 }],
            sc: Scratch::new(w),
        }
    }
}

/// The two slots `s` (of `size` values each) of a ring, as disjoint slices (a `NONE` slot is
/// an empty slice).
fn two_slots(ring: &mut [f32], size: usize, s: [usize; 2]) -> [&mut [f32]; 2] {
    match s {
        [NONE, NONE] => [&mut [], &mut []],
        [a, NONE] => [&mut ring[a * size..(a + 1) * size], &mut []],
        [NONE, b] => [&mut [], &mut ring[b * size..(b + 1) * size]],
        [a, b] => {
            let (lo, hi) = (a.min(b), a.max(b));
            let (x, rest) = ring[lo * size..].split_at_mut((hi - lo) * size);
            let (x, y) = (&mut x[..size], &mut rest[..size]);
            if a < b {
                [x, y]
            } else {
                [y, x]
            }
        }
    }
}

/// One band of image rows, y0 .. y0 + sums.len(), streamed top to bottom two rows at a time:
/// stage A (horizontal blurs) runs 2 R rows ahead of stage C (the gradient rows), stage B
/// (vertical blurs, the map, the partials' horizontal blurs) R rows ahead, each stage keeping
/// its last 12 rows in a ring of slots (row r in slot r % 12), so the planes never leave the
/// cache, and stages B and C forming their rows in pairs (`vblur2`). Rows of the band's halo
/// (R or 2 R rows each side) are computed again by the neighbouring band, with the same
/// arithmetic, so every value has the bits of any other banding. Writes the map's row sums into
/// `sums` and, with the gradient, the gradient rows into `grad.0` and the L1 row sums into
/// `grad.1`.
#[inline(always)]
fn band_rows(
    job: &Job,
    y0: usize,
    sums: &mut [f64],
    mut grad: Option<(&mut [f32], &mut [(f64, f64)])>,
    k: &[f32; TAPS],
    band: &mut Band,
) {
    let (w, h) = (job.w, job.h);
    let row = 3 * w;
    let (y0, y1, hh) = (y0 as isize, (y0 + sums.len()) as isize, h as isize);
    let r_ = RADIUS as isize;
    let inside = |r: isize| r >= 0 && r < hh;
    let slot = |r: isize| if inside(r) { r as usize % RING } else { NONE };
    let lag = if grad.is_some() { 2 * r_ } else { r_ };
    // the rows each stage forms: A's and B's clipped to the image
    let (a0, a1) = ((y0 - lag).max(0), (y1 + lag).min(hh));
    let (b0, b1) = if grad.is_some() {
        ((y0 - r_).max(0), (y1 + r_).min(hh))
    } else {
        (y0, y1)
    };
    // which rows of the pair starting at `p` lie in [lo, hi): bit j for row p + j
    let pair = |p: isize, lo: isize, hi: isize| {
        (p >= lo && p < hi) as u8 | (((p + 1 >= lo) && (p + 1 < hi)) as u8) << 1
    };
    let Band { a, b, sc } = band;
    let mut r = y0 - lag;
    while r < y1 + lag {
        for ra in r..r + 2 {
            if ra >= a0 && ra < a1 {
                let (ru, s) = (ra as usize, ra as usize % RING);
                stage_a_row(
                    &job.pred[ru * row..(ru + 1) * row],
                    &job.target[ru * row..(ru + 1) * row],
                    job.clamp,
                    &mut a[s * 15 * w..(s + 1) * 15 * w],
                    k,
                    sc,
                );
            }
        }
        // stage B's pair yb, yb + 1: windows over A's rows yb - R .. yb + 1 + R
        let yb = r - r_;
        let two = pair(yb, b0, b1);
        if two != 0 {
            let slots: [usize; RING] = std::array::from_fn(|t| slot(yb - r_ + t as isize));
            let out = if job.gs.is_some() {
                two_slots(b, 9 * w, [slot(yb), slot(yb + 1)])
            } else {
                [&mut [][..], &mut []]
            };
            let s2 = stage_b_rows(a, &slots, two, job.gs, out, k, sc);
            for j in 0..2 {
                let y = yb + j as isize;
                if two & (1 << j) != 0 && y >= y0 && y < y1 {
                    sums[(y - y0) as usize] = s2[j];
                }
            }
        }
        if let Some((out, l1)) = grad.as_mut() {
            // stage C's pair yc, yc + 1: windows over B's rows yc - R .. yc + 1 + R
            let yc = r - 2 * r_;
            let two = pair(yc, y0, y1);
            if two != 0 {
                let slots: [usize; RING] = std::array::from_fn(|t| slot(yc - r_ + t as isize));
                // the pair's rows in the band (a row outside it gets an empty slice)
                let j0 = (yc - y0).max(0) as usize;
                let first = (two & 1) as usize;
                let band_out = &mut out[j0 * row..];
                let (o0, rest) = band_out.split_at_mut(row * first);
                let o1: &mut [f32] = if two & 2 != 0 {
                    &mut rest[..row]
                } else {
                    &mut []
                };
                let at = |j: isize| {
                    let y = yc + j;
                    if inside(y) {
                        y as usize * row..(y as usize + 1) * row
                    } else {
                        0..0
                    }
                };
                let s2 = stage_c_rows(
                    b,
                    &slots,
                    two,
                    [&job.pred[at(0)], &job.pred[at(1)]],
                    [&job.target[at(0)], &job.target[at(1)]],
                    job.gl1,
                    [o0, o1],
                    k,
                    sc,
                );
                for j in 0..2 {
                    if two & (1 << j) != 0 {
                        l1[(yc + j as isize - y0) as usize] = s2[j];
                    }
                }
            }
        }
        r += 2;
    }
}

/// The kernels compiled for one instruction set (the same source, so the same bits).
macro_rules! kernels {
    ($name:ident $(, $feat:literal)?) => {
        mod $name {
            use super::*;
            $(#[target_feature(enable = $feat)])?
            pub(super) unsafe fn band(job: &Job, y0: usize, sums: &mut [f64], grad: Option<(&mut [f32], &mut [(f64, f64)])>, k: &[f32; TAPS], b: &mut Band) {
                band_rows(job, y0, sums, grad, k, b)
            }
            $(#[target_feature(enable = $feat)])?
            pub(super) unsafe fn l1(g: &mut [f32], p: &[f32], t: &[f32], gl1: f32) -> (f64, f64) {
                l1_row(g, p, t, gl1)
            }
        }
    };
}

kernels!(plain);
#[cfg(target_arch = "x86_64")]
kernels!(avx2, "avx2,fma");
#[cfg(target_arch = "x86_64")]
kernels!(avx512, "avx512f,avx512vl,avx512dq,avx512bw,avx2,fma");

/// Call kernel `$f` of the resolved level.
macro_rules! dispatch {
    ($level:expr, $f:ident($($a:expr),*)) => {
        // SAFETY: a kernel runs only when the CPU has its features (`Simd::resolve` checked).
        unsafe {
            match $level {
                #[cfg(target_arch = "x86_64")]
                Simd::Avx512 => avx512::$f($($a),*),
                #[cfg(target_arch = "x86_64")]
                Simd::Avx2 => avx2::$f($($a),*),
                _ => plain::$f($($a),*),
            }
        }
    };
}

/// The L1 term over whole rows (`row` values each, in parallel): adds `gl1` sign(p - t) to
/// `g` and returns the sums of |p - t| and (p - t)^2 in float64, rows added in order.
pub(crate) fn l1_term(
    simd: Simd,
    g: &mut [f32],
    p: &[f32],
    t: &[f32],
    row: usize,
    gl1: f32,
    sums: &mut Vec<(f64, f64)>,
) -> (f64, f64) {
    let level = simd.resolve();
    g.par_chunks_mut(row.max(1))
        .zip(p.par_chunks(row.max(1)))
        .zip(t.par_chunks(row.max(1)))
        .with_min_len(4)
        .map(|((g, p), t)| dispatch!(level, l1(g, p, t, gl1)))
        .collect_into_vec(sums);
    sums.iter().fold((0.0, 0.0), |a, r| (a.0 + r.0, a.1 + r.1))
}

impl SsimWorkspace {
    /// Mean SSIM of `pred` against `target` (both H*W*3 interleaved RGB). With `grad`, also
    /// write `scale` times dSSIM_mean/d(pred) into it (H*W*3). `clamp` clamps the prediction to
    /// [0, 1] first (evaluation); the gradient is only defined without it.
    pub fn ssim(
        &mut self,
        pred: &[f32],
        target: &[f32],
        width: usize,
        height: usize,
        clamp: bool,
        grad: Option<(&mut [f32], f32)>,
    ) -> f64 {
        debug_assert!(!(clamp && grad.is_some()));
        self.run(pred, target, width, height, clamp, grad, None).0
    }

    /// The loss's SSIM and L1 terms in one streaming pass: writes `scale` dSSIM_mean/d(pred) +
    /// `gl1` sign(pred - target) into `grad` (H*W*3, the L1 part added to each value after
    /// its SSIM part) and returns (mean SSIM, sum |pred - target|, sum (pred - target)^2), the
    /// L1 sums per row in 16 float64 lanes and the rows added in order (`l1_term`'s bits).
    pub fn ssim_l1(
        &mut self,
        pred: &[f32],
        target: &[f32],
        width: usize,
        height: usize,
        grad: &mut [f32],
        scale: f32,
        gl1: f32,
    ) -> (f64, f64, f64) {
        self.run(
            pred,
            target,
            width,
            height,
            false,
            Some((grad, scale)),
            Some(gl1),
        )
    }

    fn run(
        &mut self,
        pred: &[f32],
        target: &[f32],
        width: usize,
        height: usize,
        clamp: bool,
        grad: Option<(&mut [f32], f32)>,
        gl1: Option<f32>,
    ) -> (f64, f64, f64) {
        let (w, h) = (width, height);
        let n = w * h;
        debug_assert_eq!(pred.len(), n * 3);
        debug_assert_eq!(target.len(), n * 3);
        if n == 0 {
            return (1.0, 0.0, 0.0);
        }
        let k = window();
        let level = self.simd.resolve();
        let row = 3 * w;
        let bh = match self.band_rows {
            // one band a thread: each band recomputes 2 R rows of stage A and R of stage B
            // on each side (at 648x420, 2 threads, two bands instead of four: CPU -8%)
            0 => h.div_ceil(rayon::current_num_threads()).max(2 * TAPS),
            b => b,
        }
        .min(h);
        let nb = h.div_ceil(bh);
        let g = 1.0 / (3.0 * n as f64);
        let gs = grad.as_ref().map(|(_, s)| (g * *s as f64) as f32);
        let job = Job {
            pred,
            target,
            w,
            h,
            clamp,
            gs,
            gl1: gl1.filter(|_| grad.is_some()),
        };
        let fresh = self
            .bands
            .iter()
            .any(|b| b.sc.zeros.len() != w || (gs.is_some() && b.b.len() != RING * 9 * w));
        if fresh {
            self.bands.clear();
        }
        self.bands
            .resize_with(nb.max(self.bands.len()), || Band::new(w, gs.is_some()));
        self.row_sums.resize(h, 0.0);
        let bands = &mut self.bands[..nb];
        match grad {
            Some((out, _)) => {
                self.l1_sums.resize(h, (0.0, 0.0));
                (
                    self.row_sums.par_chunks_mut(bh),
                    out.par_chunks_mut(bh * row),
                    self.l1_sums.par_chunks_mut(bh),
                    bands.par_iter_mut(),
                )
                    .into_par_iter()
                    .enumerate()
                    .for_each(|(i, (s, o, l, b))| {
                        dispatch!(level, band(&job, i * bh, s, Some((o, l)), &k, b))
                    });
            }
            None => {
                (self.row_sums.par_chunks_mut(bh), bands.par_iter_mut())
                    .into_par_iter()
                    .enumerate()
                    .for_each(|(i, (s, b))| dispatch!(level, band(&job, i * bh, s, None, &k, b)));
            }
        }
        let total: f64 = self.row_sums.iter().sum();
        let (l1, se) = if job.gl1.is_some() {
            self.l1_sums
                .iter()
                .fold((0.0, 0.0), |a, r| (a.0 + r.0, a.1 + r.1))
        } else {
            (0.0, 0.0)
        };
        (total / (3 * n) as f64, l1, se)
    }
}
