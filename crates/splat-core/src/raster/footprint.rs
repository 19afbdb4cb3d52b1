//! Exact ellipse-tile binning (issue 21, fifth pass): which tiles of a splat's box the blend
//! kernels' per-row 1/255 contour test can reach, tile row by tile row.
//!
//! Every blend kernel (forward and backward; plain, AVX2, AVX-512) evaluates a splat on the
//! pixel row with centre `yc` of a tile whose pixel-centre columns are `x0 + 0.5 ..= x0 + 15.5`
//! only when, in float32,
//!
//! ```text
//! dy = my - yc,  disc = 2 a level - dy^2 det >= 0,
//! left = mx - (sqrt(disc) - b dy) / a <= x0 + 15.5  and  right = mx + (sqrt(disc) + b dy) / a >= x0 + 0.5
//! ```
//!
//! (and the row lies in `row_span`, a further restriction ignored here). On a tile where no row
//! passes, every kernel does nothing useful with the splat, yet its list entry costs the
//! forward's phase 1 and the backward's slot. This module gives, for each tile row of the box
//! (gsplat's opacity-aware box, [`tile_box_f`]), the tile columns `[tx0, tx1)` on which some row
//! may pass: a superset of the kernels' answer, never a tile they reach.
//!
//! With the stored float32 values T = `two_a_level`, D = `conic_det`, b = `conic[1]` and a real
//! dy, R(dy) = b dy + sqrt(T - D dy^2) (the right end, times a) is concave on |dy| <= h =
//! sqrt(T / D) and L(dy) = b dy - sqrt(T - D dy^2) convex. So over a tile row's pixel-centre dys
//! (those of its first and last rows bound every row's: float subtraction is monotone) the
//! right end is at most R's maximum w = sqrt(T (D + b^2) / D), reached at dy* = b sqrt(T / (D
//! (D + b^2))), when dy* lies in the band, else the larger of R at the band's ends clipped to
//! [-h, h]; the left end likewise mirrored (-w at -dy*). Tile columns meeting [mx + L / a - m,
//! mx + R / a + m] are kept, tile rows whose dys miss [-h, h] (widened) are empty.
//!
//! The margin m covers the rounding of the kernels and of this float32 computation: near the
//! contour's top and bottom a sqrt of a rounded `disc` (absolute error a few ulps of T) is off
//! by up to about 5e-4 sqrt(T), for the kernel and for this code each, and everything else by a
//! few ulps of the values involved; m = (3e-3 sqrt(T) + 1e-5 |b| h) / a + 1e-5 |mx| + 1e-4
//! pixels, with h widened by 1e-5 relative, the in-band test of dy* by 1e-4 h. Splats outside
//! the range where that reasoning holds (non-positive D, T or 1/a, contours over 1e6 pixels)
//! keep their whole box. A test holds the result against the kernels' own float32 row test on
//! many random splats.
//!
//! The arithmetic is per splat and branch-free over [`GROUP`] splats in arrays, so it
//! vectorises (compiled for AVX-512 and AVX2 too, see [`Isa`]); every operation is a correctly
//! rounded float operation without contraction, so every build gives the same tiles.
use std::mem::MaybeUninit;

use super::project::Splat;

/// Tile side in pixels (as `sort::TILE`).
const TILE: f32 = 16.0;
/// Splats per vectorised group.
pub(crate) const GROUP: usize = 16;

/// Tiles touched by a splat's box: [x0, x1) x [y0, y1), as gsplat's `isect_tiles`, from the
/// projected mean (x, y) and the box half-sizes (rx, ry), for a `tiles_x` x `tiles_y` grid;
/// floats holding the integers (`sort::tile_range`'s bounds, checked by the tests).
#[inline(always)]
fn tile_box_f(x: f32, y: f32, rx: f32, ry: f32, tiles_x: f32, tiles_y: f32) -> [f32; 4] {
    let t = TILE;
    let clamp = |v: f32, n: f32| fmin(fmax(v, 0.0), n);
    [
        clamp(x / t - rx / t, tiles_x).floor(),
        clamp(x / t + rx / t, tiles_x).ceil(),
        clamp(y / t - ry / t, tiles_y).floor(),
        clamp(y / t + ry / t, tiles_y).ceil(),
    ]
}

/// The integer an integer-valued float in [0, 2^23) holds, from its bits after adding 2^23
/// (an `as` cast would saturate, which does not vectorise).
#[inline(always)]
fn int_bits(v: f32) -> u32 {
    (v + 8_388_608.0).to_bits() & 0x7f_ffff
}

/// `if a > b { a } else { b }` (one `maxps`; the operands are never NaN where it matters).
#[inline(always)]
fn fmax(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

#[inline(always)]
fn fmin(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

/// The per-splat constants of the test.
#[derive(Clone, Copy)]
struct Consts {
    mx: f32,
    my: f32,
    b: f32,
    t: f32,
    d: f32,
    ia: f32,
    /// The contour's half-height sqrt(T / D), and that widened.
    h: f32,
    hh: f32,
    /// R's maximiser and maximum.
    dstar: f32,
    w: f32,
    /// The x margin and the slack of the in-band test of dy*.
    m: f32,
    eps: f32,
    /// The test applies (else the whole box row).
    ok: bool,
    /// The box's columns.
    x0: f32,
    x1: f32,
}

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn consts(mx: f32, my: f32, b: f32, t: f32, d: f32, ia: f32, x0: f32, x1: f32) -> Consts {
    let h = (t / d).sqrt();
    let q = d + b * b;
    let dq = d * q;
    let g = (t / dq).sqrt();
    let w = g * q;
    let st = t.sqrt();
    let bh = b.abs() * h;
    // comparisons are false for NaN: such splats keep their box; w >= sqrt(T) always holds in
    // exact arithmetic (q >= D), so a smaller w means g underflowed
    let ok = (d > 0.0)
        & (t > 0.0)
        & (ia > 0.0)
        & (dq < f32::MAX)
        & (h < 1e6)
        & (w * ia < 1e6)
        & (w >= 0.999 * st);
    Consts {
        mx,
        my,
        b,
        t,
        d,
        ia,
        h,
        hh: h * (1.0 + 1e-5) + 1e-6,
        dstar: b * g,
        w,
        m: ia * (3e-3 * st + 1e-5 * bh) + 1e-5 * mx.abs() + 1e-4,
        eps: 1e-4 * h + 1e-6,
        ok,
        x0,
        x1,
    }
}

/// Tile columns [tx0, tx1) (as floats holding integers in [x0, x1]) of tile row `ty` that the
/// kernels' row test may reach: the box row when the test does not apply, empty when no row
/// of the tile row reaches the contour.
#[inline(always)]
fn band(c: &Consts, ty: f32) -> (f32, f32) {
    let yt = ty * TILE + 0.5;
    // the dys of the tile row's first and last pixel rows, as the kernels round them
    let dhi = c.my - yt;
    let dlo = c.my - (yt + (TILE - 1.0));
    let reach = (dlo <= c.hh) & (dhi >= -c.hh);
    let lo = fmin(fmax(dlo, -c.h), c.h);
    let hi = fmin(fmax(dhi, -c.h), c.h);
    let slo = fmax(c.t - c.d * lo * lo, 0.0).sqrt();
    let shi = fmax(c.t - c.d * hi * hi, 0.0).sqrt();
    let (blo, bhi) = (c.b * lo, c.b * hi);
    let r_edge = fmax(blo + slo, bhi + shi);
    let l_edge = fmin(blo - slo, bhi - shi);
    let (lo_e, hi_e) = (lo - c.eps, hi + c.eps);
    let r = if (c.dstar >= lo_e) & (c.dstar <= hi_e) {
        c.w
    } else {
        r_edge
    };
    let l = if (-c.dstar >= lo_e) & (-c.dstar <= hi_e) {
        -c.w
    } else {
        l_edge
    };
    let xr = c.mx + c.ia * r + c.m;
    let xl = c.mx + c.ia * l - c.m;
    // tile tx is reached when xl <= 16 tx + 15.5 and xr >= 16 tx + 0.5 (rounding of the
    // subtractions only widens the range: float rounding is monotone and the bounds exact)
    let a = fmin(fmax((xl - (TILE - 0.5)) * (1.0 / TILE), c.x0), c.x1).ceil();
    let e = fmin(fmax((xr - 0.5) * (1.0 / TILE) + 1.0, c.x0), c.x1).floor();
    let e = fmax(e, a);
    if !c.ok {
        (c.x0, c.x1)
    } else if reach {
        (a, e)
    } else {
        (a, a)
    }
}

/// Whether the test runs (exact binning) or every box row is kept whole (gsplat's lists).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Mode {
    Exact,
    Box,
}

impl Mode {
    /// Exact, unless `MORPHGS_BIN_BOX` is set (a measuring switch: the same build with and
    /// without the test; read once per frame).
    pub(crate) fn current() -> Mode {
        if std::env::var_os("MORPHGS_BIN_BOX").is_some() {
            Mode::Box
        } else {
            Mode::Exact
        }
    }
}

/// A group of up to [`GROUP`] splats' values, one array per value (so lane loops vectorise).
#[derive(Default)]
pub(crate) struct Group {
    mx: [f32; GROUP],
    my: [f32; GROUP],
    b: [f32; GROUP],
    t: [f32; GROUP],
    d: [f32; GROUP],
    ia: [f32; GROUP],
    rx: [f32; GROUP],
    ry: [f32; GROUP],
}

impl Group {
    /// Put `splats` (at most [`GROUP`]) in lanes 0.., zeros in the others.
    #[inline(always)]
    pub(crate) fn fill(&mut self, splats: &[Splat]) {
        if splats.len() < GROUP {
            *self = Group::default();
        }
        for (l, s) in splats.iter().enumerate() {
            self.set(l, s);
        }
    }

    /// Put splat `s` in lane `l`.
    #[inline(always)]
    pub(crate) fn set(&mut self, l: usize, s: &Splat) {
        self.mx[l] = s.xy[0];
        self.my[l] = s.xy[1];
        self.b[l] = s.conic[1];
        self.t[l] = s.two_a_level;
        self.d[l] = s.conic_det;
        self.ia[l] = s.inv_a;
        self.rx[l] = s.radius[0];
        self.ry[l] = s.radius[1];
    }

    /// Write the boxes of lanes 0..out.boxes.len() to `out.boxes` ([`tile_box_f`]) and the
    /// tiles of their box rows the test keeps to `out.masks`, or, for a [`TALL`] splat, each
    /// row's column range to `tall` (appended, row by row).
    #[inline(always)]
    pub(crate) fn emit(
        &self,
        tiles: (u32, u32),
        mode: Mode,
        out: Out<'_>,
        tall: &mut Vec<[u16; 2]>,
    ) {
        let (tiles_x, tiles_y) = (tiles.0 as f32, tiles.1 as f32);
        let n = out.boxes.len();
        // the boxes as floats holding integers (one array per bound, so the lanes vectorise)
        let (mut x0, mut x1, mut y0, mut y1) =
            ([0.0f32; GROUP], [0.0; GROUP], [0.0; GROUP], [0.0; GROUP]);
        for l in 0..GROUP {
            [x0[l], x1[l], y0[l], y1[l]] = tile_box_f(
                self.mx[l], self.my[l], self.rx[l], self.ry[l], tiles_x, tiles_y,
            );
        }
        let mut is_tall = [false; GROUP];
        let mut rows = [0.0f32; GROUP];
        for l in 0..GROUP {
            let h = y1[l] - y0[l];
            is_tall[l] = (h > MASK_ROWS as f32) | (x1[l] - x0[l] > MASK_COLS as f32);
            rows[l] = if is_tall[l] { 0.0 } else { h };
        }
        // row j's tiles x0 + i in bits 16 j + i (rows beyond the box's own stay empty)
        let mut masks = [0u64; GROUP];
        let mut cl = ConstLanes::default();
        if mode == Mode::Box {
            // the whole box, without the test's arithmetic
            for j in 0..MASK_ROWS {
                for l in 0..GROUP {
                    let w = int_bits(x1[l] - x0[l]);
                    let bits = if (j as f32) < rows[l] {
                        (1u32 << w) - 1
                    } else {
                        0
                    };
                    masks[l] |= u64::from(bits) << (16 * j);
                }
            }
        } else {
            for l in 0..GROUP {
                let c = consts(
                    self.mx[l], self.my[l], self.b[l], self.t[l], self.d[l], self.ia[l], x0[l],
                    x1[l],
                );
                cl.set(l, &c);
            }
            let k_max = rows.iter().fold(0.0f32, |a, &b| fmax(a, b)) as usize;
            for j in 0..k_max {
                for l in 0..GROUP {
                    let (a, e) = band(&cl.get(self, l), y0[l] + j as f32);
                    let (a, e) = (int_bits(a - x0[l]), int_bits(e - x0[l]));
                    let bits = if (j as f32) < rows[l] {
                        (1u32 << e) - (1u32 << a)
                    } else {
                        0
                    };
                    masks[l] |= u64::from(bits) << (16 * j);
                }
            }
        }
        let mut packed = [0u64; GROUP];
        for l in 0..GROUP {
            if is_tall[l] {
                masks[l] = TALL;
            }
            let v = [x0[l], x1[l], y0[l], y1[l]].map(|v| u64::from(int_bits(v)));
            packed[l] = v[0] | v[1] << 16 | v[2] << 32 | v[3] << 48;
        }
        for l in 0..n {
            let v = packed[l];
            out.boxes[l].write([
                v as u16,
                (v >> 16) as u16,
                (v >> 32) as u16,
                (v >> 48) as u16,
            ]);
            out.masks[l].write(masks[l]);
        }
        for l in 0..n {
            if is_tall[l] {
                let k = int_bits(y1[l] - y0[l]) as usize;
                if mode == Mode::Box {
                    let r = [x0[l], x1[l]].map(|v| int_bits(v) as u16);
                    tall.extend(std::iter::repeat_n(r, k));
                } else {
                    tall_rows(&cl.get(self, l), y0[l], k, tall);
                }
            }
        }
    }
}

/// Tile rows and columns a tile mask holds (16 bits per row, row j in bits 16 j..16 j + 16;
/// a box is at most 15 tiles wide, so bit 15 of a row is never set).
pub(crate) const MASK_ROWS: usize = 4;
pub(crate) const MASK_COLS: usize = 15;
/// The mask of a splat whose box is taller or wider than a mask holds: its rows' column
/// ranges are in the chunk's `tall` list instead.
pub(crate) const TALL: u64 = u64::MAX;

/// Where a group's results go: its splats' boxes and tile masks.
pub(crate) struct Out<'a> {
    pub(crate) boxes: &'a mut [MaybeUninit<[u16; 4]>],
    pub(crate) masks: &'a mut [MaybeUninit<u64>],
}

/// Append the column ranges of rows y0..y0 + k of one splat to `tall`, 16 rows at a time.
#[inline(always)]
fn tall_rows(c: &Consts, y0: f32, k: usize, tall: &mut Vec<[u16; 2]>) {
    let mut j0 = 0;
    while j0 < k {
        let mut r = [[0u16; 2]; 16];
        for (j, v) in r.iter_mut().enumerate() {
            let (a, e) = band(c, y0 + (j0 + j) as f32);
            *v = [int_bits(a) as u16, int_bits(e) as u16];
        }
        tall.extend_from_slice(&r[..16.min(k - j0)]);
        j0 += 16;
    }
}

/// A group's [`Consts`] beyond its inputs, one array per value.
#[derive(Default)]
struct ConstLanes {
    h: [f32; GROUP],
    hh: [f32; GROUP],
    dstar: [f32; GROUP],
    w: [f32; GROUP],
    m: [f32; GROUP],
    eps: [f32; GROUP],
    ok: [bool; GROUP],
    x0: [f32; GROUP],
    x1: [f32; GROUP],
}

impl ConstLanes {
    #[inline(always)]
    fn set(&mut self, l: usize, c: &Consts) {
        self.h[l] = c.h;
        self.hh[l] = c.hh;
        self.dstar[l] = c.dstar;
        self.w[l] = c.w;
        self.m[l] = c.m;
        self.eps[l] = c.eps;
        self.ok[l] = c.ok;
        self.x0[l] = c.x0;
        self.x1[l] = c.x1;
    }

    #[inline(always)]
    fn get(&self, g: &Group, l: usize) -> Consts {
        Consts {
            mx: g.mx[l],
            my: g.my[l],
            b: g.b[l],
            t: g.t[l],
            d: g.d[l],
            ia: g.ia[l],
            h: self.h[l],
            hh: self.hh[l],
            dstar: self.dstar[l],
            w: self.w[l],
            m: self.m[l],
            eps: self.eps[l],
            ok: self.ok[l],
            x0: self.x0[l],
            x1: self.x1[l],
        }
    }
}

/// The widest vector extension the CPU has, for the group arithmetic.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Isa {
    Avx512,
    Avx2,
    Plain,
}

impl Isa {
    /// The build for a kernel level ([`Simd::resolve`]d here: its features include the build's),
    /// so `MORPHGS_SIMD` / `RenderOptions::simd` also pick the code [`per_isa!`] compiles.
    pub(crate) fn of(simd: crate::raster::Simd) -> Isa {
        match simd.resolve() {
            crate::raster::Simd::Avx512 => Isa::Avx512,
            crate::raster::Simd::Avx2 => Isa::Avx2,
            _ => Isa::Plain,
        }
    }

    pub(crate) fn detect() -> Isa {
        #[cfg(target_arch = "x86_64")]
        {
            if std::is_x86_feature_detected!("avx512f")
                && std::is_x86_feature_detected!("avx512dq")
                && std::is_x86_feature_detected!("avx512vl")
                && std::is_x86_feature_detected!("avx2")
            {
                return Isa::Avx512;
            }
            if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
                return Isa::Avx2;
            }
        }
        Isa::Plain
    }
}

/// Define `$name`, calling `$imp` (an `#[inline(always)]` function with the same arguments)
/// compiled for the given [`Isa`]: its AVX-512 and AVX2 copies are separate functions with
/// those target features, so the lane loops inlined into them use the wide vectors.
macro_rules! per_isa {
    ($(#[$doc:meta])* $vis:vis fn $name:ident($($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)? => $imp:path) => {
        $(#[$doc])*
        $vis fn $name(isa: $crate::raster::footprint::Isa, $($arg: $ty),*) $(-> $ret)? {
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx512f,avx512dq,avx512vl,avx2")]
            fn avx512($($arg: $ty),*) $(-> $ret)? {
                $imp($($arg),*)
            }
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2,fma")]
            fn avx2($($arg: $ty),*) $(-> $ret)? {
                $imp($($arg),*)
            }
            match isa {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: `Isa::detect` only yields Avx512 when the CPU has these features.
                $crate::raster::footprint::Isa::Avx512 => unsafe { avx512($($arg),*) },
                #[cfg(target_arch = "x86_64")]
                // SAFETY: `Isa::detect` only yields Avx2 when the CPU has AVX2 and FMA.
                $crate::raster::footprint::Isa::Avx2 => unsafe { avx2($($arg),*) },
                _ => $imp($($arg),*),
            }
        }
    };
}
pub(crate) use per_isa;

per_isa! {
    /// The footprints of `splats` (as [`Group::emit`] gives them) into `fp` (cleared first),
    /// computed with `isa`.
    pub(crate) fn of_splats(
        splats: &[Splat],
        tiles: (u32, u32),
        mode: Mode,
        fp: &mut ChunkFootprints,
    ) => of_splats_impl
}

#[inline(always)]
fn of_splats_impl(splats: &[Splat], tiles: (u32, u32), mode: Mode, fp: &mut ChunkFootprints) {
    let n = splats.len();
    fp.clear();
    fp.boxes.reserve(n);
    fp.masks.reserve(n);
    let boxes = &mut fp.boxes.spare_capacity_mut()[..n];
    let masks = &mut fp.masks.spare_capacity_mut()[..n];
    let mut groups = [Group::default(), Group::default()];
    let parts: Vec<&[Splat]> = splats.chunks(GROUP).collect();
    if let Some(first) = parts.first() {
        groups[0].fill(first);
    }
    for (g, (b, m)) in boxes
        .chunks_mut(GROUP)
        .zip(masks.chunks_mut(GROUP))
        .enumerate()
    {
        // the next group's lanes are written a group ahead of their (vector) reads
        let [a, c] = &mut groups;
        let (cur, next) = if g % 2 == 0 { (a, c) } else { (c, a) };
        if let Some(p) = parts.get(g + 1) {
            next.fill(p);
        }
        cur.emit(tiles, mode, Out { boxes: b, masks: m }, &mut fp.tall);
    }
    // SAFETY: the groups above wrote every element of the reserved spare capacity.
    unsafe {
        fp.boxes.set_len(n);
        fp.masks.set_len(n);
    }
}

/// One binning chunk's footprints, owned (as `sort::TileBins::rebuild` computes them).
#[derive(Default)]
pub(crate) struct ChunkFootprints {
    pub(crate) boxes: Vec<[u16; 4]>,
    pub(crate) masks: Vec<u64>,
    pub(crate) tall: Vec<[u16; 2]>,
}

impl ChunkFootprints {
    fn clear(&mut self) {
        self.boxes.clear();
        self.masks.clear();
        self.tall.clear();
    }
}

#[cfg(test)]
pub(crate) mod tests;
