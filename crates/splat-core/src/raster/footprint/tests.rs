//! The exact binning against the kernels' own float32 row test: it never drops a tile a row of
//! the kernels reaches, on many random splats (thin, rotated, huge, sub-pixel, centred on tile
//! edges and pixel centres, off the image), and it drops most of the tiles none reaches.
use super::*;
use crate::raster::blend::row_span;

/// A xorshift stream of floats in [0, 1).
pub(crate) fn rng(seed: u64) -> impl FnMut() -> f32 {
    let mut h = seed | 1;
    move || {
        h ^= h << 13;
        h ^= h >> 7;
        h ^= h << 17;
        (h >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// A splat as the projection makes it (its conic, box and contour constants), with a random
/// 2D covariance, opacity and centre on or around a `w` x `h` image. Every eighth has no
/// eps2d (thinner than any projected splat), every fourth its centre on a tile edge or a
/// pixel centre. Only finite splats, as the projection keeps.
pub(crate) fn random_splat(next: &mut impl FnMut() -> f32, w: f32, h: f32) -> Splat {
    loop {
        let s = try_splat(next, w, h);
        let v = [
            s.conic[0],
            s.conic[1],
            s.conic[2],
            s.two_a_level,
            s.conic_det,
            s.inv_a,
        ];
        if v.iter()
            .chain(&s.radius)
            .chain(&[s.half_height])
            .all(|x| x.is_finite())
        {
            return s;
        }
    }
}

fn try_splat(next: &mut impl FnMut() -> f32, w: f32, h: f32) -> Splat {
    let kind = (next() * 8.0) as u32;
    // sigmas from 0.02 to 2000 pixels, log-uniform, any angle
    let sig = |u: f32| 0.02 * 10f32.powf(5.0 * u);
    let (s0, s1) = (sig(next()), sig(next()));
    let th = next() * std::f32::consts::PI;
    let (c, s) = (th.cos(), th.sin());
    let eps = if kind == 0 { 0.0 } else { 0.3 };
    let c00 = c * c * s0 * s0 + s * s * s1 * s1 + eps;
    let c01 = c * s * (s0 * s0 - s1 * s1);
    let c11 = s * s * s0 * s0 + c * c * s1 * s1 + eps;
    let det = c00 * c11 - c01 * c01;
    let (mut x, mut y) = (next() * (w + 400.0) - 200.0, next() * (h + 400.0) - 200.0);
    match kind {
        1 => (x, y) = ((x / 16.0).round() * 16.0, (y / 16.0).round() * 16.0),
        2 => (x, y) = (x.floor() + 0.5, y.floor() + 0.5),
        _ => {}
    }
    let opacity = 1.0 / 255.0 + next() * (1.0 - 1.0 / 255.0);
    let ln_over = (opacity * 255.0).ln();
    let extent = (2.0 * ln_over).sqrt().min(3.33);
    let level = ln_over * 1.0001 + 1e-4;
    let conic = [c11 / det, -c01 / det, c00 / det];
    Splat {
        xy: [x, y],
        conic,
        ln_opacity: opacity.ln(),
        rgb: [0.5; 3],
        depth: 1.0,
        radius: [(extent * c00.sqrt()).ceil(), (extent * c11.sqrt()).ceil()],
        two_a_level: 2.0 * conic[0] * level,
        conic_det: conic[0] * conic[2] - conic[1] * conic[1],
        inv_a: 1.0 / conic[0],
        half_height: (2.0 * level * c11).sqrt(),
    }
}

/// Whether some pixel row of tile (tx, ty) passes the kernels' row test (the generic kernel's
/// code: `blend_tile_impl`, `blend_bwd`; the AVX2 and AVX-512 kernels compute the same values).
fn kernel_reaches(s: &Splat, tx: u32, ty: u32) -> bool {
    let (mx, my) = (s.xy[0], s.xy[1]);
    let cb = s.conic[1];
    let x0 = tx * 16;
    let (xl, xh) = (x0 as f32 + 0.5, (x0 + 15) as f32 + 0.5);
    let y0f = (ty * 16) as f32;
    let (lo, hi) = row_span(my, s.half_height, y0f);
    (lo..hi).any(|r| {
        let dy = my - (y0f + r as f32 + 0.5);
        let bdy = cb * dy;
        let disc = s.two_a_level - dy * dy * s.conic_det;
        if disc.is_nan() || disc < 0.0 {
            return false;
        }
        let sq = disc.sqrt();
        !(mx - (sq - bdy) * s.inv_a > xh || mx + (sq + bdy) * s.inv_a < xl)
    })
}

/// The boxes of `splats` computed with `isa`, and each splat's box rows' column ranges
/// decoded from its tile mask or the tall list.
fn footprints(splats: &[Splat], tiles: (u32, u32), isa: Isa) -> (Vec<[u16; 4]>, Vec<[u16; 2]>) {
    let mut fp = ChunkFootprints::default();
    of_splats(isa, splats, tiles, Mode::Exact, &mut fp);
    let mut rows = Vec::new();
    let mut k = 0;
    for (b, &mask) in fp.boxes.iter().zip(&fp.masks) {
        let h = (b[3] - b[2]) as usize;
        if mask == TALL {
            rows.extend_from_slice(&fp.tall[k..k + h]);
            k += h;
        } else {
            assert!(h <= MASK_ROWS && (b[1] - b[0]) as usize <= MASK_COLS);
            assert_eq!(mask.checked_shr(16 * h as u32).unwrap_or(0), 0);
            for j in 0..h {
                // each row's tiles are a run of bits, starting at 0 when empty
                let v = (mask >> (16 * j)) as u16;
                let (a, e) = (
                    v.trailing_zeros().min(16) as u16,
                    16 - v.leading_zeros() as u16,
                );
                let a = a.min(e);
                assert_eq!(v, ((1u32 << e) - (1u32 << a)) as u16);
                rows.push([b[0] + a, b[0] + e]);
            }
        }
    }
    assert_eq!(k, fp.tall.len());
    (fp.boxes, rows)
}

#[test]
fn exact_binning_never_drops_a_tile_the_kernels_reach() {
    let mut next = rng(0x5eed_b1a5);
    let (w, h) = (1000.0f32, 700.0f32);
    let tiles = ((w as u32).div_ceil(16), (h as u32).div_ceil(16));
    let splats: Vec<Splat> = (0..60_000).map(|_| random_splat(&mut next, w, h)).collect();
    let (boxes, rows) = footprints(&splats, tiles, Isa::detect());
    let (mut in_box, mut reached, mut kept) = (0u64, 0u64, 0u64);
    let mut k = 0;
    for (s, b) in splats.iter().zip(&boxes) {
        let [x0, x1, y0, y1] = b.map(u32::from);
        assert_eq!(
            (x0, x1, y0, y1),
            crate::raster::sort::tile_range(s, tiles.0, tiles.1)
        );
        for ty in y0..y1 {
            let [a, e] = rows[k].map(u32::from);
            k += 1;
            assert!(
                x0 <= a && a <= e && e <= x1,
                "row {ty} of {s:?}: [{a}, {e})"
            );
            for tx in x0..x1 {
                let reach = kernel_reaches(s, tx, ty);
                let keep = (a..e).contains(&tx);
                assert!(
                    keep || !reach,
                    "tile ({tx}, {ty}) reached but dropped: {s:?}"
                );
                in_box += 1;
                reached += u64::from(reach);
                kept += u64::from(keep);
            }
        }
    }
    assert_eq!(k, rows.len());
    // the test is not the box: it drops nearly every entry no row reaches
    let (droppable, dropped) = (in_box - reached, in_box - kept);
    eprintln!("box entries {in_box}, reached {reached}, kept {kept}");
    assert!(droppable > in_box / 10, "{droppable} of {in_box}");
    assert!(
        dropped * 100 >= droppable * 95,
        "dropped {dropped} of {droppable}"
    );
}

/// Splats right at the edge of reaching a tile: a contour whose right end lies within a
/// rounding error of a tile's first pixel centre, in both directions, at many scales.
#[test]
fn exact_binning_keeps_contours_grazing_a_tile() {
    let mut next = rng(77);
    let tiles = (40, 30);
    let mut splats = Vec::new();
    for _ in 0..20_000 {
        let mut s = random_splat(&mut next, 640.0, 480.0);
        // move the centre so the widest point of the contour, mx + w / a, lands on the first
        // pixel centre of a tile column, nudged by a few ulps either way
        let (a, b, d) = (s.conic[0], s.conic[1], s.conic_det);
        let wx = (s.two_a_level * (d + b * b) / d).sqrt() / a;
        let col = (next() * 40.0).floor() * 16.0 + 0.5;
        let ulps = (next() * 64.0) as i32 - 32;
        let x = col - wx;
        s.xy[0] = f32::from_bits((x.to_bits() as i32 + ulps) as u32);
        if (next() * 2.0) as u32 == 0 {
            // the same on the contour's top: its lowest row on a pixel centre
            let yc = (next() * 30.0).floor() * 16.0 + 0.5 + (next() * 16.0).floor();
            let hy = (s.two_a_level / d).sqrt();
            s.xy[1] = f32::from_bits(((yc + hy).to_bits() as i32 + ulps) as u32);
        }
        if s.xy.iter().all(|v| v.is_finite()) {
            splats.push(s);
        }
    }
    let (boxes, rows) = footprints(&splats, tiles, Isa::detect());
    let mut k = 0;
    for (s, b) in splats.iter().zip(&boxes) {
        let [x0, x1, y0, y1] = b.map(u32::from);
        for ty in y0..y1 {
            let [a, e] = rows[k].map(u32::from);
            k += 1;
            for tx in x0..x1 {
                assert!(
                    (a..e).contains(&tx) || !kernel_reaches(s, tx, ty),
                    "tile ({tx}, {ty}) reached but dropped: {s:?}"
                );
            }
        }
    }
}

/// Every build gives the same tiles: the AVX-512, AVX2 and plain compilations agree.
#[test]
fn every_instruction_set_gives_the_same_footprints() {
    let mut next = rng(3);
    let splats: Vec<Splat> = (0..5000)
        .map(|_| random_splat(&mut next, 500.0, 300.0))
        .collect();
    let tiles = (32, 19);
    let want = footprints(&splats, tiles, Isa::Plain);
    for isa in [Isa::Avx2, Isa::Avx512] {
        if isa == Isa::detect() || (isa == Isa::Avx2 && Isa::detect() == Isa::Avx512) {
            assert!(footprints(&splats, tiles, isa) == want, "{isa:?}");
        }
    }
}

/// Splats the test does not apply to keep their whole box rows: a non-positive determinant,
/// a zero conic, an enormous contour.
#[test]
fn degenerate_splats_keep_their_box() {
    let mut next = rng(9);
    let tiles = (20, 20);
    let mut splats = Vec::new();
    for f in [
        |s: &mut Splat| s.conic_det = 0.0,
        |s: &mut Splat| s.conic_det = -1e-3,
        |s: &mut Splat| s.two_a_level = 0.0,
        |s: &mut Splat| s.inv_a = -s.inv_a,
        |s: &mut Splat| s.conic_det = 1e-30,
    ] {
        let mut s = random_splat(&mut next, 320.0, 320.0);
        s.xy = [160.0, 150.0];
        s.radius = [60.0, 45.0];
        f(&mut s);
        splats.push(s);
    }
    let (boxes, rows) = footprints(&splats, tiles, Isa::detect());
    let mut k = 0;
    for b in &boxes {
        for _ in b[2]..b[3] {
            assert_eq!(rows[k], [b[0], b[1]]);
            k += 1;
        }
    }
    assert_eq!(k, rows.len());
    assert!(k > 0);
}

/// The point of it all: exact lists blend to the bytes of gsplat's box lists, on every kernel,
/// for random splats of every kind (opaque ones included, so pixels stop), while the lists are
/// shorter. (tests/test_raster_pinned_bytes.py pins renders and gradients of real scenes.)
#[test]
fn exact_lists_blend_to_the_bytes_of_the_box_lists() {
    use crate::raster::blend::{blend_frame, BlendParams};
    use crate::raster::sort::{sort_by_depth, TileBins};
    use crate::raster::Simd;
    let mut next = rng(21);
    let (w, h) = (300u32, 190u32);
    let tiles = (w.div_ceil(16), h.div_ceil(16));
    let splats: Vec<Splat> = (0..6000)
        .map(|i| {
            let mut s = random_splat(&mut next, w as f32, h as f32);
            // mostly small and medium splats, a few huge
            while i % 50 != 0 && s.radius[0].max(s.radius[1]) > 60.0 {
                s = random_splat(&mut next, w as f32, h as f32);
            }
            s.rgb = [next(), next(), next()];
            s.depth = 0.5 + next() * 10.0;
            if i % 9 == 0 {
                s.ln_opacity = 0.0;
            }
            s
        })
        .collect();
    let sorted = sort_by_depth(&[splats]);
    let mut exact = TileBins::default();
    let mut boxed = TileBins::default();
    exact
        .rebuild_mode(&sorted, tiles.0, tiles.1, Mode::Exact)
        .expect("bins");
    boxed
        .rebuild_mode(&sorted, tiles.0, tiles.1, Mode::Box)
        .expect("bins");
    assert!(exact.intersections() * 10 < boxed.intersections() * 9);
    for simd in [Simd::Avx512, Simd::Avx2, Simd::Scalar] {
        let p = BlendParams {
            width: w,
            height: h,
            max_alpha: 0.99,
            background: [0.1, 0.2, 0.3],
            simd: simd.resolve(),
            count_useful: true,
        };
        let npix = (w * h) as usize;
        let render = |bins: &TileBins| {
            let (mut rgb, mut depth, mut alpha) = (
                vec![0.0f32; npix * 3],
                vec![0.0f32; npix],
                vec![0.0f32; npix],
            );
            let c = blend_frame(&sorted, bins, &p, &mut rgb, &mut depth, &mut alpha);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<u32>>();
            (bits(&rgb), bits(&depth), bits(&alpha), c.useful)
        };
        assert!(render(&exact) == render(&boxed), "{simd:?}");
    }
}
