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
                let (s, l, e) = ws.ssim_l1(&x, &y, w, h, &mut g, -0.2, 0.8 / (3 * w * h) as f32);
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
