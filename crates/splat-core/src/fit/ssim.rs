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

/// A ring slot that is outside the image (its rows are zeros).
const NONE: usize = usize::MAX;

/// `out[i] = sum_t k[t] src[i + t]`, summed in tap order in a register per output value.
#[inline(always)]
fn taps(src: &[f32], out: &mut [f32], k: &[f32; TAPS]) {
    for (i, o) in out.iter_mut().enumerate() {
        let p = &src[i..i + TAPS];
        let mut s = 0.0f32;
        for t in 0..TAPS {
            s += k[t] * p[t];
        }
        *o = s;
    }
}

/// Zero-padded 11-tap blur of one row: `out[i] = sum_t k[t] src[i + t - 5]`, summed in tap
/// order in a register per output value. The interior reads the row in place; only the edges
/// go through a zero-padded copy (`pad`, at least W + 10 values), with the same sums.
#[inline(always)]
fn hblur(src: &[f32], pad: &mut [f32], out: &mut [f32], k: &[f32; TAPS]) {
    let w = src.len();
    if w < 2 * RADIUS {
        pad[..RADIUS].fill(0.0);
        pad[RADIUS..RADIUS + w].copy_from_slice(src);
        pad[RADIUS + w..RADIUS + w + RADIUS].fill(0.0);
        taps(&pad[..w + 2 * RADIUS], &mut out[..w], k);
        return;
    }
    taps(src, &mut out[RADIUS..w - RADIUS], k);
    let e = &mut pad[..3 * RADIUS];
    e[..RADIUS].fill(0.0);
    e[RADIUS..].copy_from_slice(&src[..2 * RADIUS]);
    taps(e, &mut out[..RADIUS], k);
    e[..2 * RADIUS].copy_from_slice(&src[w - 2 * RADIUS..]);
    e[2 * RADIUS..].fill(0.0);
    taps(e, &mut out[w - RADIUS..w], k);
}

/// Vertical 11-tap blur: `out[i] = sum_t k[t] rows[t][i]` (rows outside the image are zero
/// rows), summed in tap order in a register per output value.
#[inline(always)]
fn vblur(rows: &[&[f32]; TAPS], out: &mut [f32], k: &[f32; TAPS]) {
    let w = out.len();
    let r: [&[f32]; TAPS] = std::array::from_fn(|t| &rows[t][..w]);
    for (i, o) in out.iter_mut().enumerate() {
        let mut s = 0.0f32;
        for t in 0..TAPS {
            s += k[t] * r[t][i];
        }
        *o = s;
    }
}

/// Two vertical blurs at once, of the output rows whose windows are `rows[0..11]` and
/// `rows[1..12]`: each input row is loaded once for both, and each output value is summed in
/// tap order in its own register (`vblur`'s bits). Halves the loads of the vertical pass.
#[inline(always)]
fn vblur2(rows: &[&[f32]; RING], out0: &mut [f32], out1: &mut [f32], k: &[f32; TAPS]) {
    let w = out0.len();
    let out1 = &mut out1[..w];
    let r: [&[f32]; RING] = std::array::from_fn(|t| &rows[t][..w]);
    for i in 0..w {
        let mut s0 = 0.0f32;
        let mut s1 = 0.0f32;
        s0 += k[0] * r[0][i];
        for t in 1..TAPS {
            let x = r[t][i];
            s0 += k[t] * x;
            s1 += k[t - 1] * x;
        }
        s1 += k[TAPS - 1] * r[TAPS][i];
        out0[i] = s0;
        out1[i] = s1;
    }
}

/// Ring slots: a stage keeps its last 12 rows (row r in slot r % 12), the 11 rows of one
/// output row's window and one more for the second row of a pair.
const RING: usize = TAPS + 1;

/// The 12 rows of block `block` (of `blocks` blocks of W values a slot) from the ring's slots
/// `slots` (the zero row where a slot is `NONE`, outside the image).
#[inline(always)]
fn ring_rows<'a>(
    ring: &'a [f32],
    slots: &[usize; RING],
    blocks: usize,
    block: usize,
    zeros: &'a [f32],
) -> [&'a [f32]; RING] {
    let w = zeros.len();
    std::array::from_fn(|t| {
        if slots[t] == NONE {
            zeros
        } else {
            let at = (slots[t] * blocks + block) * w;
            &ring[at..at + w]
        }
    })
}

/// The vertical blurs of one block for the rows `two` selects: 0b01 the first row of the pair
/// (window `rows[0..11]`) into `out[..w]`, 0b10 the second (`rows[1..12]`) into `out[w..]`.
#[inline(always)]
fn vblur_rows(rows: &[&[f32]; RING], two: u8, out: &mut [f32], k: &[f32; TAPS]) {
    let w = out.len() / 2;
    let (o0, o1) = out.split_at_mut(w);
    match two {
        0b11 => vblur2(rows, o0, o1, k),
        0b01 => vblur(rows[..TAPS].try_into().expect("11 rows"), o0, k),
        _ => vblur(rows[1..].try_into().expect("11 rows"), o1, k),
    }
}

/// Row buffers of one task, reused across the rows it runs.
struct Scratch {
    pad: Vec<f32>,
    tmp: Vec<f32>,
    v: [Vec<f32>; 5],
    p: [Vec<f32>; 3],
    zeros: Vec<f32>,
    /// The row's prediction and target split into channel rows (3W each).
    xr: Vec<f32>,
    yr: Vec<f32>,
}

impl Scratch {
    fn new(w: usize) -> Self {
        Scratch {
            pad: vec![0.0; w + 2 * RADIUS],
            tmp: vec![0.0; w],
            v: std::array::from_fn(|_| vec![0.0; 2 * w]),
            p: std::array::from_fn(|_| vec![0.0; 2 * w]),
            zeros: vec![0.0; w],
            xr: vec![0.0; 6 * w],
            yr: vec![0.0; 6 * w],
        }
    }
}

/// Sum of a row in float64: value i into lane i % 16, then the lanes pairwise (8 + 8, 4 + 4,
/// 2 + 2, 1 + 1). Every kernel does these adds in this order, so the bits are the kernels'.
#[inline(always)]
pub(crate) fn lane_sum(v: &[f32]) -> f64 {
    let mut acc = [0.0f64; LANES];
    let mut chunks = v.chunks_exact(LANES);
    for c in &mut chunks {
        for j in 0..LANES {
            acc[j] += c[j] as f64;
        }
    }
    for (a, &x) in acc.iter_mut().zip(chunks.remainder()) {
        *a += x as f64;
    }
    fold_lanes(acc)
}

/// The lanes of a lane sum added pairwise in a fixed order.
#[inline(always)]
pub(crate) fn fold_lanes(mut acc: [f64; LANES]) -> f64 {
    let mut n = LANES;
    while n > 1 {
        n /= 2;
        for j in 0..n {
            acc[j] += acc[j + n];
        }
    }
    acc[0]
}

/// Split one interleaved RGB row into channel rows (3W): value (c, i) at c W + i.
#[inline(always)]
fn split(src: &[f32], out: &mut [f32], w: usize) {
    let (o0, rest) = out[..3 * w].split_at_mut(w);
    let (o1, o2) = rest.split_at_mut(w);
    for (((px, a), b), c) in src[..3 * w]
        .chunks_exact(3)
        .zip(o0.iter_mut())
        .zip(o1.iter_mut())
        .zip(o2.iter_mut())
    {
        *a = px[0];
        *b = px[1];
        *c = px[2];
    }
}

/// Stage A for one image row: split the channels (clamping the prediction when asked) and blur
/// x, y, x^2, y^2, xy horizontally into `slot` (5 quantities x 3 channels x W, quantity-major).
#[inline(always)]
fn stage_a_row(
    pred: &[f32],
    target: &[f32],
    clamp: bool,
    slot: &mut [f32],
    k: &[f32; TAPS],
    sc: &mut Scratch,
) {
    let w = pred.len() / 3;
    let Scratch {
        pad, tmp, xr, yr, ..
    } = sc;
    let tmp = &mut tmp[..w];
    split(pred, xr, w);
    split(target, yr, w);
    if clamp {
        for v in xr[..3 * w].iter_mut() {
            *v = v.clamp(0.0, 1.0);
        }
    }
    let block = |m: usize, c: usize| (m * 3 + c) * w..(m * 3 + c + 1) * w;
    for c in 0..3 {
        let r = c * w..(c + 1) * w;
        let (xs, ys) = (&xr[r.clone()], &yr[r]);
        hblur(xs, pad, &mut slot[block(0, c)], k);
        hblur(ys, pad, &mut slot[block(1, c)], k);
        for i in 0..w {
            tmp[i] = xs[i] * xs[i];
        }
        hblur(tmp, pad, &mut slot[block(2, c)], k);
        for i in 0..w {
            tmp[i] = ys[i] * ys[i];
        }
        hblur(tmp, pad, &mut slot[block(3, c)], k);
        for i in 0..w {
            tmp[i] = xs[i] * ys[i];
        }
        hblur(tmp, pad, &mut slot[block(4, c)], k);
    }
}

/// Stage B for one or two consecutive image rows (`two`: 0b01 the first, 0b10 the second,
/// 0b11 both; `slots` the 12 stage A rows of the pair's windows, see `ring_rows`): vertical
/// blurs, the SSIM map (returns each row's sum: per channel a lane sum, channels added in
/// order) and, with `gs`, the partials times gs, blurred horizontally into `out[j]` (3 partials
/// x 3 channels x W, partial-major) for row j of the pair.
#[inline(always)]
fn stage_b_rows(
    ring: &[f32],
    slots: &[usize; RING],
    two: u8,
    gs: Option<f32>,
    mut out: [&mut [f32]; 2],
    k: &[f32; TAPS],
    sc: &mut Scratch,
) -> [f64; 2] {
    let w = sc.zeros.len();
    let Scratch {
        pad,
        tmp,
        v,
        p,
        zeros,
        ..
    } = sc;
    let [pa, pb, pc] = p;
    let (pa, pb, pc) = (&mut pa[..w], &mut pb[..w], &mut pc[..w]);
    let srow = &mut tmp[..w];
    let mut sum = [0.0f64; 2];
    for c in 0..3 {
        for (m, o) in v.iter_mut().enumerate() {
            let rows = ring_rows(ring, slots, 15, m * 3 + c, zeros);
            vblur_rows(&rows, two, &mut o[..2 * w], k);
        }
        for (j, out) in out.iter_mut().enumerate() {
            if two & (1 << j) == 0 {
                continue;
            }
            let [v0, v1, v2, v3, v4] = &*v;
            let r = j * w..(j + 1) * w;
            let (v0, v1, v2, v3, v4) = (
                &v0[r.clone()],
                &v1[r.clone()],
                &v2[r.clone()],
                &v3[r.clone()],
                &v4[r],
            );
            match gs {
                Some(g) => {
                    for i in 0..w {
                        let (ux, uy) = (v0[i], v1[i]);
                        let sxx = v2[i] - ux * ux;
                        let syy = v3[i] - uy * uy;
                        let sxy = v4[i] - ux * uy;
                        let a1 = 2.0 * ux * uy + C1;
                        let a2 = 2.0 * sxy + C2;
                        let b1 = ux * ux + uy * uy + C1;
                        let b2 = sxx + syy + C2;
                        let inv = 1.0 / (b1 * b2);
                        let s = a1 * a2 * inv;
                        srow[i] = s;
                        let gi = g * inv;
                        pa[i] = 2.0 * gi * (uy * (a2 - a1) - ux * s * (b2 - b1));
                        pb[i] = -(gi * s * b1);
                        pc[i] = 2.0 * gi * a1;
                    }
                    let block = |m: usize| (m * 3 + c) * w..(m * 3 + c + 1) * w;
                    hblur(pa, pad, &mut out[block(0)], k);
                    hblur(pb, pad, &mut out[block(1)], k);
                    hblur(pc, pad, &mut out[block(2)], k);
                }
                None => {
                    for i in 0..w {
                        let (ux, uy) = (v0[i], v1[i]);
                        let a1 = 2.0 * ux * uy + C1;
                        let a2 = 2.0 * (v4[i] - ux * uy) + C2;
                        let b1 = ux * ux + uy * uy + C1;
                        let b2 = (v2[i] - ux * ux) + (v3[i] - uy * uy) + C2;
                        srow[i] = (a1 * a2) / (b1 * b2);
                    }
                }
            }
            sum[j] += lane_sum(srow);
        }
    }
    sum
}

/// Stage C for one or two consecutive image rows (`two` and `slots` as for `stage_b_rows`,
/// over stage B's ring): vertical blurs of the partials, combined with the row's prediction
/// and target (`pred[j]`, `target[j]`) into the gradient row `out[j]` (interleaved RGB); with
/// `gl1`, the L1 term is added to it (`l1_row`) and its row sums returned.
#[inline(always)]
fn stage_c_rows(
    ring: &[f32],
    slots: &[usize; RING],
    two: u8,
    pred: [&[f32]; 2],
    target: [&[f32]; 2],
    gl1: Option<f32>,
    out: [&mut [f32]; 2],
    k: &[f32; TAPS],
    sc: &mut Scratch,
) -> [(f64, f64); 2] {
    let w = sc.zeros.len();
    let rows_of = |j: usize| two & (1 << j) != 0;
    for j in (0..2).filter(|&j| rows_of(j)) {
        split(pred[j], &mut sc.xr[3 * w * j..3 * w * (j + 1)], w);
        split(target[j], &mut sc.yr[3 * w * j..3 * w * (j + 1)], w);
    }
    let Scratch {
        v,
        p: comb,
        zeros,
        xr,
        yr,
        ..
    } = &mut *sc;
    for (c, comb) in comb.iter_mut().enumerate() {
        for (m, o) in v[..3].iter_mut().enumerate() {
            let rows = ring_rows(ring, slots, 9, m * 3 + c, zeros);
            vblur_rows(&rows, two, &mut o[..2 * w], k);
        }
        for j in (0..2).filter(|&j| rows_of(j)) {
            let r = j * w..(j + 1) * w;
            let (v0, v1, v2) = (&v[0][r.clone()], &v[1][r.clone()], &v[2][r.clone()]);
            let at = (3 * j + c) * w..(3 * j + c + 1) * w;
            let (xc, yc) = (&xr[at.clone()], &yr[at]);
            let o = &mut comb[r];
            for i in 0..w {
                o[i] = v0[i] + 2.0 * xc[i] * v1[i] + yc[i] * v2[i];
            }
        }
    }
    let mut sums = [(0.0, 0.0); 2];
    for (j, out) in out.into_iter().enumerate() {
        if !rows_of(j) {
            continue;
        }
        let r = j * w..(j + 1) * w;
        let (r0, r1, r2) = (&comb[0][r.clone()], &comb[1][r.clone()], &comb[2][r]);
        for (i, o) in out[..3 * w].chunks_exact_mut(3).enumerate() {
            o[0] = r0[i];
            o[1] = r1[i];
            o[2] = r2[i];
        }
        if let Some(g) = gl1 {
            sums[j] = l1_row(out, pred[j], target[j], g);
        }
    }
    sums
}

/// One row of the L1 term: adds `gl1` sign(p - t) (0 where equal, like torch) to the gradient
/// and returns the row's sums of |p - t| and (p - t)^2 in float64, each in 16 lanes (value i
/// into lane i % 16) added pairwise in a fixed order, like the map's.
#[inline(always)]
fn l1_row(g: &mut [f32], p: &[f32], t: &[f32], gl1: f32) -> (f64, f64) {
    let (mut l1, mut se) = ([0.0f64; LANES], [0.0f64; LANES]);
    let n = g.len().min(p.len()).min(t.len());
    let full = n / LANES * LANES;
    for ((g, p), t) in g[..full]
        .chunks_exact_mut(LANES)
        .zip(p[..full].chunks_exact(LANES))
        .zip(t[..full].chunks_exact(LANES))
    {
        for j in 0..LANES {
            let d = p[j] - t[j];
            l1[j] += d.abs() as f64;
            se[j] += (d * d) as f64;
            let s = ((d > 0.0) as i32 - (d < 0.0) as i32) as f32;
            g[j] += gl1 * s;
        }
    }
    for j in 0..n - full {
        let d = p[full + j] - t[full + j];
        l1[j] += d.abs() as f64;
        se[j] += (d * d) as f64;
        let s = ((d > 0.0) as i32 - (d < 0.0) as i32) as f32;
        g[full + j] += gl1 * s;
    }
    (fold_lanes(l1), fold_lanes(se))
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

#[cfg(test)]
mod tests {
    use super::*;

    fn image(w: usize, h: usize, seed: u64) -> Vec<f32> {
        let mut s = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        (0..w * h * 3)
            .map(|i| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                let smooth = ((i / 3 % w) as f32 * 0.15).sin() * 0.3 + 0.5;
                smooth + ((s >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 0.2
            })
            .collect()
    }

    #[test]
    fn identical_images_score_one_and_window_sums_to_one() {
        let k = window();
        assert!((k.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        let a = image(23, 17, 1);
        let mut ws = SsimWorkspace::default();
        let s = ws.ssim(&a, &a, 23, 17, false, None);
        assert!((s - 1.0).abs() < 1e-6, "{s}");
        let b = image(23, 17, 2);
        assert!(ws.ssim(&a, &b, 23, 17, false, None) < 0.9);
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let (w, h) = (19, 13);
        let x = image(w, h, 3);
        let y = image(w, h, 4);
        let mut ws = SsimWorkspace::default();
        let mut g = vec![0.0f32; w * h * 3];
        ws.ssim(&x, &y, w, h, false, Some((&mut g, 1.0)));
        // probe pixels at the border and inside
        for &i in &[0usize, 5, 3 * w + 1, 3 * (6 * w + 9) + 2, w * h * 3 - 1] {
            let eps = 1e-2f32;
            let mut xp = x.clone();
            xp[i] += eps;
            let mut xm = x.clone();
            xm[i] -= eps;
            let fd = (ws.ssim(&xp, &y, w, h, false, None) - ws.ssim(&xm, &y, w, h, false, None))
                / (2.0 * eps as f64);
            let tol = 2e-3 * fd.abs().max(1e-4) + 1e-6;
            assert!(
                (fd - g[i] as f64).abs() < tol.max(2e-6),
                "value {i}: finite difference {fd}, analytic {}",
                g[i]
            );
        }
    }

    #[test]
    fn same_bits_for_any_thread_count_and_kernel() {
        let (w, h) = (67, 45);
        let x = image(w, h, 5);
        let y = image(w, h, 6);
        let run = |t: usize, simd: Simd| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(t)
                .build()
                .expect("pool")
                .install(|| {
                    let mut ws = SsimWorkspace {
                        simd,
                        ..SsimWorkspace::default()
                    };
                    let mut g = vec![0.0f32; w * h * 3];
                    let s = ws.ssim(&x, &y, w, h, false, Some((&mut g, 1.0)));
                    (
                        s.to_bits(),
                        g.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    )
                })
        };
        let base = run(1, Simd::Scalar);
        assert_eq!(base, run(3, Simd::Auto));
        assert_eq!(base, run(2, Simd::Avx2));
    }

    /// The plane-by-plane computation the streaming bands replace (whole planes, the same
    /// arithmetic per value): (mean SSIM, gradient with the L1 part, L1 sum, squared-error sum).
    fn reference(
        x: &[f32],
        y: &[f32],
        w: usize,
        h: usize,
        scale: f32,
        gl1: f32,
    ) -> (f64, Vec<f32>, f64, f64) {
        let k = window();
        let plane = |f: &dyn Fn(usize) -> f32| -> Vec<f32> { (0..w * h).map(f).collect() };
        let hb = |p: &[f32]| -> Vec<f32> {
            let mut o = vec![0.0f32; w * h];
            for r in 0..h {
                let mut pad = vec![0.0f32; w + 2 * RADIUS];
                pad[RADIUS..RADIUS + w].copy_from_slice(&p[r * w..(r + 1) * w]);
                taps(&pad, &mut o[r * w..(r + 1) * w], &k);
            }
            o
        };
        let vb = |p: &[f32]| -> Vec<f32> {
            let mut o = vec![0.0f32; w * h];
            for r in 0..h {
                for i in 0..w {
                    let mut s = 0.0f32;
                    for t in 0..TAPS {
                        let rr = r as isize + t as isize - RADIUS as isize;
                        let v = if rr < 0 || rr >= h as isize {
                            0.0
                        } else {
                            p[rr as usize * w + i]
                        };
                        s += k[t] * v;
                    }
                    o[r * w + i] = s;
                }
            }
            o
        };
        let gs = ((1.0 / (3.0 * (w * h) as f64)) * scale as f64) as f32;
        let mut grad = vec![0.0f32; w * h * 3];
        let mut rows = vec![0.0f64; h];
        for c in 0..3 {
            let xs = plane(&|i| x[i * 3 + c]);
            let ys = plane(&|i| y[i * 3 + c]);
            let m: Vec<Vec<f32>> = [
                xs.clone(),
                ys.clone(),
                plane(&|i| xs[i] * xs[i]),
                plane(&|i| ys[i] * ys[i]),
                plane(&|i| xs[i] * ys[i]),
            ]
            .iter()
            .map(|p| vb(&hb(p)))
            .collect();
            let (mut pa, mut pb, mut pc, mut sm) = (
                vec![0.0f32; w * h],
                vec![0.0f32; w * h],
                vec![0.0f32; w * h],
                vec![0.0f32; w * h],
            );
            for i in 0..w * h {
                let (ux, uy) = (m[0][i], m[1][i]);
                let (sxx, syy, sxy) = (m[2][i] - ux * ux, m[3][i] - uy * uy, m[4][i] - ux * uy);
                let (a1, a2) = (2.0 * ux * uy + C1, 2.0 * sxy + C2);
                let (b1, b2) = (ux * ux + uy * uy + C1, sxx + syy + C2);
                let inv = 1.0 / (b1 * b2);
                let s = a1 * a2 * inv;
                sm[i] = s;
                let gi = gs * inv;
                pa[i] = 2.0 * gi * (uy * (a2 - a1) - ux * s * (b2 - b1));
                pb[i] = -(gi * s * b1);
                pc[i] = 2.0 * gi * a1;
            }
            for r in 0..h {
                rows[r] += lane_sum(&sm[r * w..(r + 1) * w]);
            }
            let (da, db, dc) = (vb(&hb(&pa)), vb(&hb(&pb)), vb(&hb(&pc)));
            for i in 0..w * h {
                grad[i * 3 + c] = da[i] + 2.0 * xs[i] * db[i] + ys[i] * dc[i];
            }
        }
        let mut sums = Vec::new();
        let (l1, se) = l1_term(Simd::Scalar, &mut grad, x, y, 3 * w, gl1, &mut sums);
        let total: f64 = rows.iter().sum();
        (total / (3 * w * h) as f64, grad, l1, se)
    }

    #[test]
    fn streaming_bands_give_the_bits_of_whole_planes_for_any_band_height() {
        for (w, h) in [(37, 29), (8, 5), (23, 12), (12, 40), (6, 1), (9, 2)] {
            let x = image(w, h, 11);
            let y = image(w, h, 12);
            let (s0, g0, l0, e0) = reference(&x, &y, w, h, -0.2, 0.8 / (3 * w * h) as f32);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            let mut value = None;
            for band_rows in [0, 1, 2, 3, 7, 11, 16, 100] {
                for simd in [Simd::Scalar, Simd::Auto] {
                    let mut ws = SsimWorkspace {
                        band_rows,
                        simd,
                        ..SsimWorkspace::default()
                    };
                    let mut g = vec![0.0f32; w * h * 3];
                    let (s, l, e) =
                        ws.ssim_l1(&x, &y, w, h, &mut g, -0.2, 0.8 / (3 * w * h) as f32);
                    let at = format!("{w}x{h}, {band_rows} rows a band, {simd:?}");
                    assert_eq!(s.to_bits(), s0.to_bits(), "{at}");
                    assert_eq!(
                        (l.to_bits(), e.to_bits()),
                        (l0.to_bits(), e0.to_bits()),
                        "{at}"
                    );
                    assert_eq!(bits(&g), bits(&g0), "{at}");
                    // the value-only path (evaluation) on the same workspace
                    let v = ws.ssim(&x, &y, w, h, false, None);
                    assert!((v - s0).abs() < 1e-6, "{at}: {v} vs {s0}");
                    assert_eq!(v.to_bits(), *value.get_or_insert(v.to_bits()), "{at}");
                }
            }
        }
    }

    #[test]
    fn a_reused_workspace_gives_the_bits_of_a_fresh_one_across_sizes() {
        // the rings keep rows of the last call: a new size, or evaluation between two losses,
        // must not read them
        let mut kept = SsimWorkspace::default();
        for (w, h) in [(31, 40), (31, 17), (12, 9), (31, 40), (40, 31)] {
            let (x, y) = (image(w, h, 21), image(w, h, 22));
            let mut g = vec![0.0f32; w * h * 3];
            let got = kept.ssim_l1(&x, &y, w, h, &mut g, -0.2, 0.01);
            let eval = kept.ssim(&x, &y, w, h, true, None);
            let mut fresh = SsimWorkspace::default();
            let mut g0 = vec![0.0f32; w * h * 3];
            let want = fresh.ssim_l1(&x, &y, w, h, &mut g0, -0.2, 0.01);
            let eval0 = SsimWorkspace::default().ssim(&x, &y, w, h, true, None);
            assert_eq!(
                format!("{got:?} {eval}"),
                format!("{want:?} {eval0}"),
                "{w}x{h}"
            );
            assert!(
                g.iter().zip(&g0).all(|(a, b)| a.to_bits() == b.to_bits()),
                "{w}x{h}"
            );
        }
    }

    #[test]
    fn row_blur_in_place_matches_the_padded_copy_at_every_width() {
        let k = window();
        for w in 1..40 {
            let src: Vec<f32> = image(w, 1, w as u64)
                .iter()
                .step_by(3)
                .map(|v| v - 0.5)
                .collect();
            let mut padded = vec![0.0f32; w + 2 * RADIUS];
            padded[RADIUS..RADIUS + w].copy_from_slice(&src);
            let mut want = vec![0.0f32; w];
            taps(&padded, &mut want, &k);
            let mut got = vec![0.0f32; w];
            hblur(&src, &mut vec![1.0f32; w + 2 * RADIUS], &mut got, &k);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&got), bits(&want), "width {w}");
        }
    }

    #[test]
    fn l1_term_has_the_same_bits_for_any_thread_count_and_kernel() {
        // 37 values a row: two full lanes of 16 and a remainder of 5
        let (p, t) = (image(37, 9, 7), image(37, 9, 8));
        let mut p = p;
        p[4] = t[4]; // a zero difference: zero sign
        let run = |threads: usize, simd: Simd| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("pool")
                .install(|| {
                    let mut g = vec![0.5f32; p.len()];
                    let (l1, se) = l1_term(simd, &mut g, &p, &t, 37, 0.25, &mut Vec::new());
                    let gb: Vec<u32> = g.iter().map(|v| v.to_bits()).collect();
                    (l1.to_bits(), se.to_bits(), gb)
                })
        };
        let base = run(1, Simd::Scalar);
        assert_eq!(base, run(3, Simd::Auto));
        assert_eq!(base, run(2, Simd::Avx2));
        let (l1, se, g) = base;
        let want_l1: f64 = p.iter().zip(&t).map(|(a, b)| (a - b).abs() as f64).sum();
        let want_se: f64 = p
            .iter()
            .zip(&t)
            .map(|(a, b)| ((a - b) * (a - b)) as f64)
            .sum();
        assert!((f64::from_bits(l1) - want_l1).abs() < 1e-12 * want_l1.max(1.0));
        assert!((f64::from_bits(se) - want_se).abs() < 1e-12 * want_se.max(1.0));
        for (i, &gb) in g.iter().enumerate() {
            let d = p[i] - t[i];
            let want = 0.5
                + if d > 0.0 {
                    0.25
                } else if d < 0.0 {
                    -0.25
                } else {
                    0.0
                };
            assert_eq!(f32::from_bits(gb), want, "value {i}");
        }
    }
}
