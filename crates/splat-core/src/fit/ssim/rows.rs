//! The SSIM's row kernels: the 11-tap blurs, the three stages' rows and the L1 row, each a
//! fixed sequence of plain IEEE operations (no FMA contraction), compiled per SIMD level by the
//! `kernels!` macro of the parent module.

use super::{C1, C2, LANES, RADIUS, TAPS};

/// A ring slot that is outside the image (its rows are zeros).
pub(super) const NONE: usize = usize::MAX;

/// `out[i] = sum_t k[t] src[i + t]`, summed in tap order in a register per output value.
#[inline(always)]
pub(super) fn taps(src: &[f32], out: &mut [f32], k: &[f32; TAPS]) {
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
pub(super) fn hblur(src: &[f32], pad: &mut [f32], out: &mut [f32], k: &[f32; TAPS]) {
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
pub(super) fn vblur(rows: &[&[f32]; TAPS], out: &mut [f32], k: &[f32; TAPS]) {
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
pub(super) fn vblur2(rows: &[&[f32]; RING], out0: &mut [f32], out1: &mut [f32], k: &[f32; TAPS]) {
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
pub(super) const RING: usize = TAPS + 1;

/// The 12 rows of block `block` (of `blocks` blocks of W values a slot) from the ring's slots
/// `slots` (the zero row where a slot is `NONE`, outside the image).
#[inline(always)]
pub(super) fn ring_rows<'a>(
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
pub(super) fn vblur_rows(rows: &[&[f32]; RING], two: u8, out: &mut [f32], k: &[f32; TAPS]) {
    let w = out.len() / 2;
    let (o0, o1) = out.split_at_mut(w);
    match two {
        0b11 => vblur2(rows, o0, o1, k),
        0b01 => vblur(rows[..TAPS].try_into().expect("11 rows"), o0, k),
        _ => vblur(rows[1..].try_into().expect("11 rows"), o1, k),
    }
}

/// Row buffers of one task, reused across the rows it runs.
pub(super) struct Scratch {
    pub(super) pad: Vec<f32>,
    pub(super) tmp: Vec<f32>,
    pub(super) v: [Vec<f32>; 5],
    pub(super) p: [Vec<f32>; 3],
    pub(super) zeros: Vec<f32>,
    /// The row's prediction and target split into channel rows (3W each).
    pub(super) xr: Vec<f32>,
    pub(super) yr: Vec<f32>,
}

impl Scratch {
    pub(super) fn new(w: usize) -> Self {
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
pub(super) fn lane_sum(v: &[f32]) -> f64 {
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
pub(super) fn fold_lanes(mut acc: [f64; LANES]) -> f64 {
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
pub(super) fn split(src: &[f32], out: &mut [f32], w: usize) {
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
pub(super) fn stage_a_row(
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
pub(super) fn stage_b_rows(
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
pub(super) fn stage_c_rows(
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
pub(super) fn l1_row(g: &mut [f32], p: &[f32], t: &[f32], gl1: f32) -> (f64, f64) {
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
