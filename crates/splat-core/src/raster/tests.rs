use super::*;
use crate::Scene;

fn scene(n: usize) -> Scene {
    cloud(n, 0x1234_5678, -3.0)
}

/// A deterministic cloud of `n` Gaussians in [-1, 1]^3 (xorshift from `seed`), log-scales
/// `log_scale` - U(0, 1) (the third axis 0.5 more), for tests in front of a camera.
pub(crate) fn cloud(n: usize, seed: u64, log_scale: f32) -> Scene {
    let mut s = Scene::empty(0);
    let mut h = seed;
    let mut next = || {
        h ^= h << 13;
        h ^= h >> 7;
        h ^= h << 17;
        (h >> 40) as f32 / (1u64 << 24) as f32
    };
    for _ in 0..n {
        s.means
            .extend([next() * 2.0 - 1.0, next() * 2.0 - 1.0, next() * 2.0 - 1.0]);
        s.quats
            .extend([1.0, next() - 0.5, next() - 0.5, next() - 0.5]);
        s.log_scales.extend([
            log_scale - next(),
            log_scale - next(),
            (log_scale + 0.5) - next(),
        ]);
        s.opacity_logits.push(next() * 4.0 - 2.0);
        s.sh0.extend([next() - 0.5, next() - 0.5, next() - 0.5]);
    }
    s.normalize_quats();
    s
}

/// A frame of `scene(n)` seen by `cam` ready for the tile kernels: the depth-sorted splats,
/// their tile lists and the blend parameters (black background).
fn tiled(
    cam: &Camera,
    n: usize,
    max_alpha: f32,
    simd: Simd,
    count_useful: bool,
) -> (Vec<project::Splat>, sort::TileBins, blend::BlendParams) {
    let s = scene(n);
    let opts = RenderOptions {
        max_alpha,
        ..Default::default()
    };
    let proj = project::Projector::new(cam, &opts, 0);
    let sorted = sort::sort_by_depth(&project::project_visible(&s.view(), &proj));
    let (tx, ty) = cam.tiles();
    let bins = sort::TileBins::build(&sorted, tx, ty).expect("bins");
    let p = blend::BlendParams {
        width: cam.width,
        height: cam.height,
        max_alpha,
        background: [0.0; 3],
        simd,
        count_useful,
    };
    (sorted, bins, p)
}

fn camera() -> Camera {
    let mut m = [[0.0; 4]; 4];
    for (i, row) in m.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    m[2][3] = 4.0;
    Camera::new(120.0, 120.0, 50.0, 37.0, 100, 70, m)
}

fn render(s: &Scene, opts: &RenderOptions) -> (Vec<f32>, Vec<f32>, Vec<f32>, RenderStats) {
    let cam = camera();
    let n = 100 * 70;
    let (mut rgb, mut depth, mut alpha) = (vec![0.0; n * 3], vec![0.0; n], vec![0.0; n]);
    let st = render_into(&s.view(), &cam, opts, &mut rgb, &mut depth, &mut alpha).expect("render");
    (rgb, depth, alpha, st)
}

#[test]
fn output_is_identical_for_any_thread_count() {
    let s = scene(5000);
    let opts = RenderOptions::default();
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool")
            .install(|| render(&s, &opts))
    };
    let (a, b, c) = (run(1), run(3), run(8));
    assert!(a.3.evaluations > 0);
    for other in [&b, &c] {
        assert_eq!(a.0, other.0);
        assert_eq!(a.1, other.1);
        assert_eq!(a.2, other.2);
    }
}

#[test]
fn simd_kernels_agree_with_the_plain_one() {
    let s = scene(3000);
    let base = render(
        &s,
        &RenderOptions {
            simd: Simd::Scalar,
            ..Default::default()
        },
    );
    for simd in [Simd::Avx2, Simd::Avx512] {
        let got = render(
            &s,
            &RenderOptions {
                simd,
                ..Default::default()
            },
        );
        let err = got
            .0
            .iter()
            .zip(&base.0)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(err < 1e-4, "{}: max error {err}", simd.resolve().name());
        // the AVX2 kernel's half rows are the halves of the plain kernel's rows that a
        // footprint reaches, so never more evaluations; both kernels' counts are held to
        // their unit models in `explicit_kernels_give_the_generic_kernels_bits_tile_by_tile`
        if simd.resolve() == Simd::Avx2 {
            assert!(got.3.evaluations <= base.3.evaluations);
        }
    }
}

/// Every tile of a frame through each x86 kernel: the explicit AVX2 and AVX-512 kernels
/// must give the generic kernel's bits (|T|, colour and depth sums) and useful evaluations;
/// their evaluation counts are those of the per-pixel model of their work units (AVX2: 8x1
/// pixels, AVX-512: 4x4).
#[cfg(target_arch = "x86_64")]
#[test]
fn explicit_kernels_give_the_generic_kernels_bits_tile_by_tile() {
    if Simd::Avx2.resolve() != Simd::Avx2 && Simd::Avx512.resolve() != Simd::Avx512 {
        return;
    }
    let cam = camera();
    let mut checked = 0;
    for (n, max_alpha) in [(3000, 0.99), (20000, 0.999), (20000, 0.99)] {
        let (sorted, bins, p) = tiled(&cam, n, max_alpha, Simd::Auto, true);
        let (tx, ty) = cam.tiles();
        for t in 0..(tx * ty) as usize {
            let (x0, y0) = ((t as u32 % tx) * 16, (t as u32 / tx) * 16);
            let mut want = blend::TileOut::default();
            // SAFETY: AVX2 and FMA are present (checked above; AVX-512 implies both).
            let we = unsafe {
                blend::blend_tile_generic_fma(x0, y0, &p, &sorted, bins.lists(t), &mut want)
            };
            let mut got = Vec::new();
            let halves = blend::unit_model::<8, 1>(x0, y0, &p, &sorted, bins.lists(t));
            let blocks = blend::unit_model::<4, 4>(x0, y0, &p, &sorted, bins.lists(t));
            // the row unit of the generic kernel, modelled: its own count
            let rows = blend::unit_model::<16, 1>(x0, y0, &p, &sorted, bins.lists(t));
            assert_eq!(rows, we, "row model, tile {t}");
            assert_eq!((halves.useful, blocks.useful), (we.useful, we.useful));
            if Simd::Avx2.resolve() == Simd::Avx2 {
                let mut o = blend::TileOut::default();
                // SAFETY: AVX2 and FMA are present.
                let e = unsafe {
                    blend_avx2::blend_tile_avx2::<true, true>(
                        x0,
                        y0,
                        &p,
                        &sorted,
                        bins.lists(t),
                        &mut o,
                    )
                };
                got.push(("avx2", o, e, halves));
            }
            if Simd::Avx512.resolve() == Simd::Avx512 {
                let mut o = blend::TileOut::default();
                // SAFETY: the AVX-512 features are present.
                let e = unsafe {
                    blend_avx512::blend_tile_avx512::<true, true>(
                        x0,
                        y0,
                        &p,
                        &sorted,
                        bins.lists(t),
                        &mut o,
                    )
                };
                got.push(("avx512", o, e, blocks));
            }
            for (name, o, e, want_e) in got {
                assert_eq!(e, want_e, "{name} evaluations, tile {t}");
                for r in 0..16 {
                    for l in 0..16 {
                        if x0 + l as u32 >= cam.width || y0 + r as u32 >= cam.height {
                            continue;
                        }
                        let bits = |v: f32| v.to_bits();
                        let ctx = format!("{name} tile {t} pixel ({l}, {r})");
                        assert_eq!(bits(o.t[r][l].abs()), bits(want.t[r][l].abs()), "{ctx}");
                        assert_eq!(bits(o.d[r][l]), bits(want.d[r][l]), "{ctx}");
                        for ch in 0..3 {
                            assert_eq!(bits(o.c[ch][r][l]), bits(want.c[ch][r][l]), "{ctx}");
                        }
                    }
                }
                checked += 1;
            }
        }
    }
    assert!(checked > 50);
}

/// Every kernel (plain, AVX2, AVX-512) without depth sums (the fit's forward) gives the
/// transmittance and colour bits of the same kernel with them, whatever the tile buffer
/// held before (each kernel sets its starting state itself), and leaves the depth sums as
/// they were.
#[test]
fn kernels_without_depth_keep_the_colour_and_transmittance_bits() {
    let cam = camera();
    let mut checked = 0;
    for simd in [Simd::Avx512, Simd::Avx2, Simd::Scalar] {
        if simd.resolve() != simd {
            continue;
        }
        let max_alpha = RenderOptions::default().max_alpha;
        let (sorted, bins, p) = tiled(&cam, 20000, max_alpha, simd, false);
        let (tx, ty) = cam.tiles();
        let mut contributed = 0;
        for t in 0..(tx * ty) as usize {
            let (x0, y0) = ((t as u32 % tx) * 16, (t as u32 / tx) * 16);
            let stale = || {
                let mut o = blend::TileOut::default();
                for v in o.t.iter_mut().chain(o.d.iter_mut()).flatten() {
                    *v = 7.5;
                }
                for v in o.c.iter_mut().flatten().flatten() {
                    *v = -3.25;
                }
                o
            };
            let (mut with, mut without) = (stale(), stale());
            let e1 = blend::blend_tile(x0, y0, &p, &sorted, bins.lists(t), &mut with, true);
            let e0 = blend::blend_tile(x0, y0, &p, &sorted, bins.lists(t), &mut without, false);
            assert_eq!(e0, e1, "{simd:?} tile {t}");
            let bits = |o: &blend::TileOut| {
                let mut v: Vec<u32> = o.t.iter().flatten().map(|x| x.abs().to_bits()).collect();
                v.extend(o.c.iter().flatten().flatten().map(|x| x.to_bits()));
                v
            };
            assert_eq!(bits(&with), bits(&without), "{simd:?} tile {t}");
            assert!(without.d.iter().flatten().all(|&v| v == 7.5));
            contributed += with.d.iter().flatten().any(|&v| v != 0.0) as usize;
            checked += 1;
        }
        assert!(contributed > 10, "{simd:?}");
    }
    assert!(checked > 50);
}

/// Counting the useful evaluations changes no output byte; the count lies between 1 and
/// the evaluations, and every x86 kernel counts the same.
#[test]
fn useful_evaluations_are_counted_on_request_without_changing_the_image() {
    let s = scene(5000);
    let mut counts = Vec::new();
    for simd in [Simd::Avx512, Simd::Avx2, Simd::Scalar] {
        if simd.resolve() != simd {
            continue;
        }
        let off = render(
            &s,
            &RenderOptions {
                simd,
                ..Default::default()
            },
        );
        let on = render(
            &s,
            &RenderOptions {
                simd,
                count_useful: true,
                ..Default::default()
            },
        );
        assert_eq!((off.0, off.1, off.2), (on.0, on.1, on.2));
        assert_eq!(off.3.useful, 0);
        assert_eq!(off.3.evaluations, on.3.evaluations);
        assert!(
            on.3.useful > 0 && on.3.useful < on.3.evaluations,
            "{:?}",
            on.3
        );
        counts.push((simd, on.3.useful));
    }
    // the FMA kernels give the same alphas, so the same count
    let fma: Vec<u64> = counts
        .iter()
        .filter(|c| c.0 != Simd::Scalar)
        .map(|c| c.1)
        .collect();
    assert!(fma.windows(2).all(|w| w[0] == w[1]), "{counts:?}");
}

#[test]
fn avx512_intrinsics_kernel_gives_the_same_bits_as_the_avx2_one() {
    if Simd::Avx512.resolve() != Simd::Avx512 {
        return;
    }
    let s = scene(3000);
    let [a, b] = [Simd::Avx2, Simd::Avx512].map(|simd| {
        render(
            &s,
            &RenderOptions {
                simd,
                max_alpha: 0.999,
                count_useful: true,
                ..Default::default()
            },
        )
    });
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&a.0), bits(&b.0));
    assert_eq!(bits(&a.1), bits(&b.1));
    assert_eq!(bits(&a.2), bits(&b.2));
    // the same useful evaluations (their work units differ, so their evaluation counts
    // do: see `explicit_kernels_give_the_generic_kernels_bits_tile_by_tile`)
    assert!(a.3.useful > 0);
    assert_eq!(a.3.useful, b.3.useful);
}

/// A degree-3 copy of `scene(n)` with view-dependent colours.
fn scene_sh3(n: usize) -> Scene {
    let base = scene(n);
    let mut s = Scene::empty(3);
    s.means = base.means;
    s.quats = base.quats;
    s.log_scales = base.log_scales;
    s.opacity_logits = base.opacity_logits;
    s.sh0 = base.sh0;
    let k = s.sh_rest_k() * 3;
    s.sh_rest = (0..n * k)
        .map(|i| ((i * 7919 % 1000) as f32 / 1000.0 - 0.5) * 0.6)
        .collect();
    s
}

/// A "pair": the clean scene, and a copy pruned with changed scales and rotations, some
/// means moved, some SH changed and some quaternions broken. Rendering both in one batch
/// (the copy taking the clean render's colours where its mean and SH match) gives each
/// scene's own render bit for bit, for every frame.
#[test]
fn shared_colours_give_the_bits_of_separate_renders() {
    let clean = scene_sh3(6000);
    let keep: Vec<bool> = (0..clean.len())
        .map(|i| i % 3 != 1 && i % 401 != 0)
        .collect();
    let mut other = clean.filter(&keep);
    let k = other.sh_rest_k() * 3;
    for j in 0..other.len() {
        for c in 0..3 {
            other.log_scales[j * 3 + c] += 0.3 * ((j + c) % 5) as f32 - 0.6;
        }
        other.quats[j * 4 + 1] += 0.1;
        match j % 37 {
            0 => other.means[j * 3] += 0.01,
            1 => other.sh_rest[j * k + k - 1] += 0.25,
            2 => other.sh0[j * 3 + 2] = -other.sh0[j * 3 + 2],
            3 => other.quats[j * 4] = f32::NAN,
            _ => {}
        }
    }
    other.normalize_quats();
    let map = share::colour_map(&clean.view(), &other.view()).expect("matches");
    let matched = map.iter().filter(|&&i| i != share::NO_MATCH).count();
    assert!(
        matched > other.len() * 9 / 10 && matched < other.len(),
        "{matched}"
    );
    for (j, &i) in map.iter().enumerate() {
        if i != share::NO_MATCH {
            assert_eq!(other.means[j * 3], clean.means[i as usize * 3]);
            assert_eq!(
                other.sh_rest[j * k + k - 1],
                clean.sh_rest[i as usize * k + k - 1]
            );
        }
    }
    let mut cams = Vec::new();
    for f in 0..3 {
        let mut c = camera();
        c.world_to_camera[0][3] = 0.3 * f as f64 - 0.3;
        c.world_to_camera[1][3] = 0.1 * f as f64;
        cams.push(c);
    }
    let views = [clean.view(), other.view()];
    for antialiased in [false, true] {
        let opts = RenderOptions {
            antialiased,
            ..Default::default()
        };
        let batch = render_batch(&views, &cams, &opts).expect("batch");
        let (w, h) = (cams[0].width as usize, cams[0].height as usize);
        let npix = w * h;
        for (s, view) in views.iter().enumerate() {
            for (f, cam) in cams.iter().enumerate() {
                let (mut rgb, mut depth, mut alpha) =
                    (vec![0.0; npix * 3], vec![0.0; npix], vec![0.0; npix]);
                render_into(view, cam, &opts, &mut rgb, &mut depth, &mut alpha).expect("render");
                let u = s * cams.len() + f;
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                let ctx = format!("scene {s} frame {f} antialiased {antialiased}");
                assert_eq!(
                    bits(&batch.rgb[u * npix * 3..(u + 1) * npix * 3]),
                    bits(&rgb),
                    "{ctx}"
                );
                assert_eq!(
                    bits(&batch.depth[u * npix..(u + 1) * npix]),
                    bits(&depth),
                    "{ctx}"
                );
                assert_eq!(
                    bits(&batch.alpha[u * npix..(u + 1) * npix]),
                    bits(&alpha),
                    "{ctx}"
                );
            }
        }
    }
}

#[test]
fn empty_scene_gives_the_background_and_bad_options_are_errors() {
    let opts = RenderOptions {
        background: [0.25, 0.5, 1.0],
        ..Default::default()
    };
    let (rgb, depth, alpha, st) = render(&Scene::empty(0), &opts);
    assert!(rgb.chunks_exact(3).all(|p| p == [0.25, 0.5, 1.0]));
    assert!(depth.iter().chain(&alpha).all(|&v| v == 0.0));
    assert_eq!(st.visible, 0);
    let s = scene(10);
    let cam = camera();
    let mut buf = vec![0.0; 3];
    let bad = RenderOptions {
        max_alpha: 1.5,
        ..Default::default()
    };
    assert!(render_into(
        &s.view(),
        &cam,
        &bad,
        &mut buf.clone(),
        &mut buf.clone(),
        &mut buf
    )
    .is_err());
    let deg = RenderOptions {
        sh_degree: Some(1),
        ..Default::default()
    };
    assert!(deg.effective_sh_degree(0).is_err());
    assert_eq!(
        RenderOptions::default().effective_sh_degree(4).ok(),
        Some(3)
    );
}

#[test]
fn render_batch_into_recycled_buffers_gives_the_bits_of_render_batch() {
    let clean = scene_sh3(3000);
    let keep: Vec<bool> = (0..clean.len()).map(|i| i % 3 != 1).collect();
    let other = clean.filter(&keep);
    let mut cams = vec![camera(), camera()];
    cams[1].world_to_camera[0][3] = 0.4;
    let mut away = camera(); // looks away from the cloud: every tile is background
    away.world_to_camera[2][3] = -4.0;
    cams.push(away);
    let opts = RenderOptions {
        background: [0.25, 0.5, 1.0],
        ..Default::default()
    };
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    let both = [clean.view(), other.view()];
    // two scenes share colours, one scene does not: both paths write every value
    for views in [&both[..], &both[..1]] {
        let want = render_batch(views, &cams, &opts).expect("batch");
        let n = want.depth.len();
        let (mut rgb, mut depth, mut alpha) =
            (vec![f32::NAN; n * 3], vec![f32::NAN; n], vec![-7.0; n]);
        for _ in 0..2 {
            let stats = render_batch_into(views, &cams, &opts, &mut rgb, &mut depth, &mut alpha)
                .expect("into");
            assert_eq!(bits(&rgb), bits(&want.rgb));
            assert_eq!(bits(&depth), bits(&want.depth));
            assert_eq!(bits(&alpha), bits(&want.alpha));
            assert_eq!(stats.evaluations, want.stats.evaluations);
        }
        let err = render_batch_into(views, &cams, &opts, &mut rgb, &mut depth[1..], &mut alpha);
        assert!(matches!(err, Err(Error::InvalidArgument(_))));
    }
    let none = render_batch_into(&both, &[], &opts, &mut [], &mut [], &mut []).expect("empty");
    assert_eq!(none.frames, 0);
}
