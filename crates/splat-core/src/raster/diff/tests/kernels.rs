//! The tile backward's kernels slot for slot: the explicit AVX2 and AVX-512 kernels and the
//! kernels without the depth channel against the generic kernel, and the per-tile inputs in
//! lanes against their per-pixel reference.
use super::*;

/// Collects every slot a kernel emits, in order (`None` for `SlotSink::zero`).
#[derive(Default, PartialEq, Debug)]
struct VecSink(Vec<(u32, Option<[u32; slot::LEN]>)>);

impl blend_bwd::SlotSink for VecSink {
    fn put(&mut self, pos: u32, vals: &[f32; slot::LEN]) {
        self.0.push((pos, Some(vals.map(f32::to_bits))));
    }

    fn zero(&mut self, pos: u32) {
        self.0.push((pos, None));
    }
}

/// Every tile of several frames through each x86 kernel: the explicit AVX2 and AVX-512 kernels
/// must emit the generic kernel's slots bit for bit (the same per-lane summation order of the
/// 4x4-pixel blocks), and count the evaluations of their unit, 4x4 blocks (the forward's
/// per-pixel model of it); the generic kernel counts 16-pixel rows.
#[cfg(target_arch = "x86_64")]
#[test]
fn explicit_kernels_give_the_generic_kernels_slots_tile_by_tile() {
    if Simd::Avx2.resolve() != Simd::Avx2 && Simd::Avx512.resolve() != Simd::Avx512 {
        return;
    }
    let mut checked = 0;
    let mut nonzero = 0;
    let mut zeros = 0;
    for (n, max_alpha, w, h, aa, abs) in [
        (3000, 0.99, 100, 70, false, true),
        (20000, 0.999, 100, 70, false, false),
        (8000, 0.99, 61, 45, true, true),
    ] {
        let s = scene(n, 3, n as u64);
        let cam = camera(w, h);
        let opts = DiffOptions {
            render: RenderOptions {
                max_alpha,
                antialiased: aa,
                background: [0.3, 0.1, 0.7],
                ..Default::default()
            },
            ..Default::default()
        };
        let mut ws = Workspace::default();
        forward(&mut ws, &s, &cam, &opts);
        let sv = ws.saved.expect("saved");
        let (r, d, a) = image_grads(&cam, 99);
        let grads = ImageGrads {
            rgb: Some(&r),
            depth: Some(&d),
            alpha: Some(&a),
            skip_background: false,
        };
        let tiles_x = ws.bins.tiles_x as usize;
        for t in 0..ws.tiles.len() {
            let (x0, y0) = ((t % tiles_x) * LANES, (t / tiles_x) * LANES);
            let mut pix = blend_bwd::PixIn::default();
            blend_bwd::tile_inputs(
                x0,
                y0,
                w as usize,
                h as usize,
                &ws.tiles[t],
                &grads,
                sv.blend.background,
                true,
                true,
                sv.blend.simd,
                &mut pix,
            );
            let lists = || ws.bins.lists(t);
            // the kernel instance for this absgrad setting
            macro_rules! call {
                ($($f:ident)::+, $out:expr) => {
                    if abs {
                        $($f)::+::<true, true, _>(x0 as u32, y0 as u32, &sv.blend, &ws.sorted, lists(), &pix, $out)
                    } else {
                        $($f)::+::<false, true, _>(x0 as u32, y0 as u32, &sv.blend, &ws.sorted, lists(), &pix, $out)
                    }
                };
            }
            let mut want = VecSink::default();
            // SAFETY: AVX2 and FMA are present (checked above; AVX-512 implies both).
            let we = unsafe { call!(blend_bwd::bwd_tile_generic_fma, &mut want) };
            nonzero += want
                .0
                .iter()
                .filter(|(_, v)| v.is_some_and(|v| v.iter().any(|&b| b != 0)))
                .count();
            zeros += want.0.iter().filter(|(_, v)| v.is_none()).count();
            assert_eq!(
                we,
                blend::unit_model::<16, 1>(x0 as u32, y0 as u32, &sv.blend, &ws.sorted, lists())
                    .evals,
                "generic evaluations, tile {t}"
            );
            let blocks =
                blend::unit_model::<4, 4>(x0 as u32, y0 as u32, &sv.blend, &ws.sorted, lists())
                    .evals;
            let mut got = Vec::new();
            if Simd::Avx2.resolve() == Simd::Avx2 {
                let mut o = VecSink::default();
                // SAFETY: AVX2 and FMA are present.
                let e = unsafe { call!(blend_bwd_avx2::bwd_tile_avx2, &mut o) };
                got.push(("avx2", o, e));
            }
            if Simd::Avx512.resolve() == Simd::Avx512 {
                let mut o = VecSink::default();
                // SAFETY: the AVX-512 features are present.
                let e = unsafe { call!(blend_bwd_avx512::bwd_tile_avx512, &mut o) };
                got.push(("avx512", o, e));
            }
            for (name, o, e) in got {
                assert_eq!(e, blocks, "{name} evaluations, tile {t}");
                assert_eq!(o.0.len(), want.0.len(), "{name} slots, tile {t}");
                for (i, (a, b)) in o.0.iter().zip(&want.0).enumerate() {
                    assert_eq!(a, b, "{name} tile {t} entry {i}");
                }
                checked += 1;
            }
        }
    }
    assert!(
        checked > 50 && nonzero > 1000 && zeros > 100,
        "{checked} tiles, {nonzero} slots, {zeros} without sums"
    );
}

/// `tile_inputs` as it was written one pixel at a time (row-major, the background sum in
/// float64 in pixel order): the lane version must give the same bits.
fn tile_inputs_reference(
    (x0, y0, width, height): (usize, usize, usize, usize),
    saved: &crate::raster::blend::TileOut,
    grads: &ImageGrads<'_>,
    background: [f32; 3],
    expected_depth: bool,
) -> (blend_bwd::PixIn, [f64; 3]) {
    let mut pix = blend_bwd::PixIn::default();
    let mut v_bg = [0.0f64; 3];
    for r in 0..LANES.min(height - y0) {
        for l in 0..LANES.min(width - x0) {
            let i = (y0 + r) * width + x0 + l;
            let t = saved.t[r][l].abs();
            let a = 1.0 - t;
            let mut g = [0.0f32; 4];
            if let Some(v) = grads.rgb {
                g[..3].copy_from_slice(&v[i * 3..i * 3 + 3]);
            }
            let mut ga = grads.alpha.map_or(0.0, |v| v[i]);
            let gd = grads.depth.map_or(0.0, |v| v[i]);
            if expected_depth {
                let am = a.max(1e-10);
                g[3] = gd / am;
                if a > 1e-10 {
                    ga -= gd * (saved.d[r][l] / am) / am;
                }
            } else {
                g[3] = gd;
            }
            let cf = [
                saved.c[0][r][l],
                saved.c[1][r][l],
                saved.c[2][r][l],
                saved.d[r][l],
            ];
            let gbg = g[0] * background[0] + g[1] * background[1] + g[2] * background[2];
            let mut q = t * (gbg - ga);
            let (b, j) = blend_bwd::block_lane(r, l);
            for c in 0..4 {
                q += g[c] * cf[c];
                pix.g[c][b][j] = g[c];
            }
            pix.q[b][j] = q;
            for c in 0..3 {
                v_bg[c] += g[c] as f64 * t as f64;
            }
        }
    }
    (pix, v_bg)
}

fn pix_bits(p: &blend_bwd::PixIn) -> Vec<u32> {
    let mut v: Vec<u32> =
        p.g.iter()
            .flatten()
            .flatten()
            .map(|x| x.to_bits())
            .collect();
    v.extend(p.q.iter().flatten().map(|x| x.to_bits()));
    v
}

#[test]
fn tile_inputs_lanes_give_the_per_pixel_bits_on_every_build() {
    // edge tiles (61x45), each image gradient present or absent, expected or accumulated depth
    let s = scene(3000, 1, 21);
    let cam = camera(61, 45);
    let opts = DiffOptions {
        render: RenderOptions {
            background: [0.3, 0.1, 0.7],
            ..Default::default()
        },
        ..Default::default()
    };
    let mut ws = Workspace::default();
    forward(&mut ws, &s, &cam, &opts);
    let sv = ws.saved.expect("saved");
    let (r, d, a) = image_grads(&cam, 5);
    let tiles_x = ws.bins.tiles_x as usize;
    let (w, h) = (61usize, 45usize);
    let mut checked = 0;
    for (rgb, depth, alpha) in [
        (true, true, true),
        (true, false, false),
        (false, true, true),
    ] {
        let grads = ImageGrads {
            rgb: rgb.then_some(&r[..]),
            depth: depth.then_some(&d[..]),
            alpha: alpha.then_some(&a[..]),
            skip_background: false,
        };
        for expected in [false, true] {
            for t in 0..ws.tiles.len() {
                let (x0, y0) = ((t % tiles_x) * LANES, (t / tiles_x) * LANES);
                let (want, want_bg) = tile_inputs_reference(
                    (x0, y0, w, h),
                    &ws.tiles[t],
                    &grads,
                    sv.blend.background,
                    expected,
                );
                for simd in [Simd::Avx512, Simd::Avx2, Simd::Scalar] {
                    let mut pix = blend_bwd::PixIn::default();
                    // a reused PixIn holding other values must be overwritten everywhere
                    pix.q[3][3] = 7.0;
                    let bg = blend_bwd::tile_inputs(
                        x0,
                        y0,
                        w,
                        h,
                        &ws.tiles[t],
                        &grads,
                        sv.blend.background,
                        expected,
                        true,
                        simd.resolve(),
                        &mut pix,
                    );
                    assert_eq!(pix_bits(&pix), pix_bits(&want), "tile {t} {simd:?}");
                    assert_eq!(bg.map(f64::to_bits), want_bg.map(f64::to_bits));
                    checked += 1;
                }
            }
        }
    }
    assert!(checked > 100);
}

/// Without a depth-image gradient the band loop runs the kernels without the depth channel
/// (`bwd_tile`'s `depth` false): every kernel (AVX-512, AVX2, plain) must emit the slots of its
/// full version bit for bit, tile by tile, for expected and accumulated depth, absgrad on and
/// off. Pixels whose rgb and alpha gradients are -0.0 give g . c = -0.0 without the depth term
/// and +0.0 with it (then -0.0 or +0.0 in dL/dalpha), which the sums must absorb. With a depth
/// gradient the two versions differ (the channel is really left out).
#[test]
fn kernels_without_the_depth_channel_give_the_same_slots() {
    let s = scene(6000, 1, 77);
    let cam = camera(90, 60);
    let (mut r, d, mut a) = image_grads(&cam, 5);
    for p in (0..a.len()).step_by(5) {
        r[3 * p..3 * p + 3].fill(-0.0);
        a[p] = -0.0;
    }
    let mut checked = 0;
    for simd in [Simd::Avx512, Simd::Avx2, Simd::Scalar] {
        if simd.resolve() != simd {
            continue;
        }
        for (depth, absgrad) in [
            (DepthKind::Expected, false),
            (DepthKind::Accumulated, true),
            (DepthKind::Expected, true),
        ] {
            let opts = DiffOptions {
                render: RenderOptions {
                    simd,
                    background: [0.2, 0.5, 0.9],
                    ..Default::default()
                },
                depth,
                absgrad,
                ..Default::default()
            };
            let mut ws = Workspace::default();
            forward(&mut ws, &s, &cam, &opts);
            let sv = ws.saved.expect("saved");
            let tiles_x = ws.bins.tiles_x as usize;
            let (mut nonzero, mut differ) = (0, 0);
            for with_depth_grad in [false, true] {
                let grads = ImageGrads {
                    rgb: Some(&r),
                    depth: with_depth_grad.then_some(&d[..]),
                    alpha: Some(&a),
                    skip_background: false,
                };
                for t in 0..ws.tiles.len() {
                    let (x0, y0) = ((t % tiles_x) * LANES, (t / tiles_x) * LANES);
                    let mut pix = blend_bwd::PixIn::default();
                    blend_bwd::tile_inputs(
                        x0,
                        y0,
                        cam.width as usize,
                        cam.height as usize,
                        &ws.tiles[t],
                        &grads,
                        sv.blend.background,
                        depth == DepthKind::Expected,
                        true,
                        sv.blend.simd,
                        &mut pix,
                    );
                    let run = |channel: bool| {
                        let mut o = VecSink::default();
                        let (x, y) = (x0 as u32, y0 as u32);
                        let lists = ws.bins.lists(t);
                        let e = blend_bwd::bwd_tile(
                            x, y, &sv.blend, &ws.sorted, lists, &pix, &mut o, absgrad, channel,
                        );
                        (o.0, e)
                    };
                    let (full, e_full) = run(true);
                    let (without, e_without) = run(false);
                    assert_eq!(e_full, e_without, "{} tile {t}", simd.name());
                    if with_depth_grad {
                        differ += (full != without) as usize;
                        continue;
                    }
                    assert_eq!(full, without, "{} {depth:?} tile {t}", simd.name());
                    nonzero += full
                        .iter()
                        .filter(|(_, v)| v.is_some_and(|v| v.iter().any(|&b| b != 0)))
                        .count();
                    checked += 1;
                }
            }
            assert!(
                nonzero > 1000 && differ > 5,
                "{nonzero} slots, {differ} tiles differ"
            );
        }
    }
    assert!(checked >= 24 * 3, "{checked} tiles");
}
