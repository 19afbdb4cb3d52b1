use super::*;

/// `n` cameras at x = 0, 0.3, 0.6, ... looking down +z at a textured plane z = 5 (OpenCV
/// convention), 32x24 pixels, and their exact clean renders: depth 5, alpha 1, a colour that
/// depends on the world x of the plane point (so every view agrees on it).
fn plane(n: usize) -> (Vec<Camera>, Vec<f32>, Vec<f32>, Vec<f32>) {
    let (w, h) = (32u32, 24u32);
    let (f, cx, cy) = (30.0, 16.0, 12.0);
    let mut cams = Vec::new();
    let (mut rgb, mut depth, mut alpha) = (Vec::new(), Vec::new(), Vec::new());
    for k in 0..n {
        let ox = 0.3 * k as f64;
        let m = [
            [1.0, 0.0, 0.0, -ox],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        cams.push(Camera::new(f, f, cx, cy, w, h, m));
        for y in 0..h {
            for x in 0..w {
                let wx = (f64::from(x) + 0.5 - cx) / f * 5.0 + ox;
                let wy = (f64::from(y) + 0.5 - cy) / f * 5.0;
                rgb.extend([
                    (0.5 + 0.4 * (3.0 * wx).sin()) as f32,
                    (0.5 + 0.4 * (2.0 * wy).cos()) as f32,
                    0.3,
                ]);
                depth.push(5.0);
                alpha.push(1.0);
            }
        }
    }
    (cams, rgb, depth, alpha)
}

fn run(value: f32, threads: usize) -> Fragments {
    let (cams, rgb, depth, alpha) = plane(4);
    let views = Views {
        rgb: &rgb,
        depth: &depth,
        alpha: &alpha,
    };
    let params = ShatterParams {
        value,
        ..Default::default()
    };
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("pool")
        .install(|| fragments(&params, &cams, views, 1000, 7))
        .expect("fragments")
}

#[test]
fn the_same_fragments_for_any_thread_count() {
    let one = run(1.5, 1);
    assert!(one.len() > 100, "{}", one.len());
    assert_eq!(one, run(1.5, 2));
    assert_eq!(one, run(1.5, 5));
    let rm = |t: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(t)
            .build()
            .expect("pool")
            .install(|| removal(10_000, 1.5, 7))
    };
    assert_eq!(rm(1), rm(3));
}

#[test]
fn a_larger_value_removes_a_superset_and_spreads_the_fragments_further() {
    let lo = removal(20_000, 0.5, 3);
    let hi = removal(20_000, 2.0, 3);
    assert!(lo.iter().zip(&hi).all(|(&l, &h)| !l || h));
    let share = |m: &[bool]| m.iter().filter(|&&r| r).count() as f64 / m.len() as f64;
    assert!((share(&lo) - (1.0 - (-0.5f64).exp())).abs() < 0.02);
    assert!((share(&hi) - (1.0 - (-2.0f64).exp())).abs() < 0.02);
    // log depth ratio spread about the plane (z = 5 in every view here)
    let iqr = |f: &Fragments| {
        let mut r: Vec<f64> = f
            .means
            .iter()
            .map(|m| (f64::from(m[2]) / 5.0).ln())
            .collect();
        r.sort_by(f64::total_cmp);
        r[3 * r.len() / 4] - r[r.len() / 4]
    };
    let (a, b) = (run(0.3, 2), run(2.0, 2));
    assert!(
        0.0 < iqr(&a) && iqr(&a) < iqr(&b),
        "{} {}",
        iqr(&a),
        iqr(&b)
    );
    // within the clip: a factor 4 up to v = 4.6, one sigma (e^(0.3 v)) beyond
    let c = run(8.0, 2);
    let out = |f: &Fragments, clip: f64| {
        f.means
            .iter()
            .filter(|m| (f64::from(m[2]) / 5.0).ln().abs() > clip.ln() + 1e-4)
            .count()
    };
    assert_eq!(out(&c, 2.4f64.exp()), 0);
    assert!(out(&c, DEPTH_CLIP) > 0);
    assert!(iqr(&b) < iqr(&c));
    for f in [&a, &b] {
        for m in &f.means {
            let z = f64::from(m[2]);
            assert!(
                (5.0 / DEPTH_CLIP - 1e-4..=5.0 * DEPTH_CLIP + 1e-4).contains(&z),
                "{z}"
            );
        }
    }
}

#[test]
fn each_fragment_lies_on_a_ray_through_its_own_pixel_and_keeps_its_colour_there() {
    let (cams, rgb, ..) = plane(4);
    let f = run(1.0, 2);
    let (w, h) = (32, 24);
    for j in 0..f.len() {
        let cam = &cams[f.view[j] as usize];
        let m = f.means[j].map(f64::from);
        let c = [m[0] + cam.translation()[0], m[1], m[2]];
        let (u, v) = (cam.fx * c[0] / c[2] + cam.cx, cam.fy * c[1] / c[2] + cam.cy);
        assert!(
            (0.0..w as f64).contains(&u) && (0.0..h as f64).contains(&v),
            "{u} {v}"
        );
        // its colour seen from its own camera: within max_error RMS of the pixel it came from
        let view = View::of(cam);
        let b = view.basis(m);
        let i = (v as usize) * w + u as usize;
        let o = (f.view[j] as usize * w * h + i) * 3;
        let mut s = 0.0;
        for ch in 0..3 {
            let mut col = b[0] * f64::from(f.sh0[j][ch]);
            for k in 0..3 {
                col += b[k + 1] * f64::from(f.sh1[j][k][ch]);
            }
            s += (col + 0.5 - f64::from(rgb[o + ch])).powi(2);
        }
        assert!(
            (s / 3.0).sqrt() <= MAX_ERROR + 1e-4,
            "fragment {j}: {}",
            (s / 3.0).sqrt()
        );
        let a = 1.0 / (1.0 + (-f.opacity_logits[j]).exp());
        assert!((1e-3..=0.991).contains(&a));
    }
}

#[test]
fn fragments_the_views_cannot_agree_on_are_dropped_or_put_back_on_the_surface() {
    let (cams, mut rgb, depth, alpha) = plane(4);
    // view 1 sees a different colour everywhere: many fragments of view 0 disagree with it
    let px = 32 * 24 * 3;
    for c in &mut rgb[px..2 * px] {
        *c = 1.0 - *c;
    }
    let views = Views {
        rgb: &rgb,
        depth: &depth,
        alpha: &alpha,
    };
    let dropped = fragments(
        &ShatterParams {
            value: 1.0,
            ..Default::default()
        },
        &cams,
        views,
        1000,
        7,
    )
    .expect("fragments");
    let kept = fragments(
        &ShatterParams {
            value: 1.0,
            drop: false,
            ..Default::default()
        },
        &cams,
        views,
        1000,
        7,
    )
    .expect("fragments");
    assert!(
        kept.len() > dropped.len(),
        "{} {}",
        kept.len(),
        dropped.len()
    );
    // the put-back ones sit on the surface (z = 5)
    let on_surface = kept
        .means
        .iter()
        .filter(|m| (m[2] - 5.0).abs() < 1e-4)
        .count();
    assert!(on_surface >= kept.len() - dropped.len());
}

#[test]
fn no_kept_fragment_is_wider_than_the_limit_in_a_view_its_footprint_reaches() {
    // view 0 five units from a plane z = 5; view 1 one unit from it and to the side, so the
    // fragments of view 0 pass close to view 1, some with their centre just outside its image
    let (w, h, f) = (32u32, 24u32, 30.0);
    let at = |x: f64, z: f64| {
        let m = [
            [1.0, 0.0, 0.0, -x],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, -z],
            [0.0, 0.0, 0.0, 1.0],
        ];
        Camera::new(f, f, 16.0, 12.0, w, h, m)
    };
    let cams = vec![at(0.0, 0.0), at(0.9, 4.0)];
    let (mut rgb, mut depth) = (Vec::new(), Vec::new());
    for (cx, cz) in [(0.0, 0.0), (0.9, 4.0)] {
        for _ in 0..h {
            for x in 0..w {
                let d = 5.0 - cz;
                let wx = (f64::from(x) + 0.5 - 16.0) / f * d + cx;
                rgb.extend([(0.5 + 0.1 * wx.sin()) as f32, 0.5, 0.4]);
                depth.push(d as f32);
            }
        }
    }
    let alpha = vec![1.0f32; depth.len()];
    let views = Views {
        rgb: &rgb,
        depth: &depth,
        alpha: &alpha,
    };
    let params = ShatterParams {
        value: 6.0,
        max_error: 1.0, // colours never disagree here: only the footprint decides
        ..Default::default()
    };
    let frags = fragments(&params, &cams, views, 100_000, 11).expect("fragments");
    let mut near_the_border = 0;
    for (i, m) in frags.means.iter().enumerate() {
        let r = f64::from(frags.log_scales[i]).exp();
        for (t, cam) in cams.iter().enumerate() {
            if frags.view[i] as usize == t {
                continue;
            }
            let (x, z) = (
                f64::from(m[0]) - [0.0, 0.9][t],
                f64::from(m[2]) - [0.0, 4.0][t],
            );
            let y = f64::from(m[1]);
            if z <= 1e-6 {
                continue;
            }
            let (u, v, sigma) = (f * x / z + 16.0, f * y / z + 12.0, r * cam.fx / z);
            let reach = 3.0 * sigma;
            let reaches = u >= -reach && u < 32.0 + reach && v >= -reach && v < 24.0 + reach;
            assert!(
                !reaches || sigma <= MAX_FOOTPRINT_PX + 1e-6,
                "fragment {i}: {sigma} px in view {t}"
            );
            near_the_border += usize::from(reaches && !(0.0..32.0).contains(&u));
        }
    }
    assert!(
        near_the_border > 0,
        "no fragment reached view 1 from outside its image"
    );
}

#[test]
fn bad_parameters_and_maps_are_named() {
    let (cams, rgb, depth, alpha) = plane(2);
    let views = Views {
        rgb: &rgb,
        depth: &depth,
        alpha: &alpha,
    };
    let err = |p: ShatterParams, v: Views<'_>, c: &[Camera]| {
        fragments(&p, c, v, 10, 0)
            .expect_err("an error")
            .to_string()
    };
    let d = ShatterParams::default();
    assert!(err(
        ShatterParams {
            value: f32::NAN,
            ..d
        },
        views,
        &cams
    )
    .contains("value"));
    assert!(err(ShatterParams { ridge: -1.0, ..d }, views, &cams).contains("ridge"));
    assert!(err(
        ShatterParams {
            max_error: 0.0,
            ..d
        },
        views,
        &cams
    )
    .contains("max_error"));
    assert!(err(d, views, &[]).contains("training cameras"));
    let short = Views {
        depth: &depth[1..],
        ..views
    };
    assert!(err(d, short, &cams).contains("depth maps"));
    // value 0 and empty views make no fragment
    assert!(
        fragments(&ShatterParams { value: 0.0, ..d }, &cams, views, 10, 0)
            .expect("fragments")
            .is_empty()
    );
    let none = vec![0.0f32; alpha.len()];
    let empty = Views {
        alpha: &none,
        ..views
    };
    assert!(fragments(&d, &cams, empty, 10, 0)
        .expect("fragments")
        .is_empty());
}

#[test]
fn the_cholesky_solve_inverts_a_known_system() {
    let a = [
        [4.0, 1.0, 0.5, 0.2],
        [1.0, 3.0, 0.3, 0.1],
        [0.5, 0.3, 2.0, 0.4],
        [0.2, 0.1, 0.4, 1.5],
    ];
    let x_true = [
        [1.0, -2.0, 0.5],
        [0.3, 0.0, 1.0],
        [-1.0, 2.0, 0.25],
        [0.7, 0.1, -0.4],
    ];
    let mut b = [[0.0; 3]; 4];
    for i in 0..4 {
        for c in 0..3 {
            b[i][c] = (0..4).map(|k| a[i][k] * x_true[k][c]).sum();
        }
    }
    let x = solve_spd4(a, b);
    for i in 0..4 {
        for c in 0..3 {
            assert!((x[i][c] - x_true[i][c]).abs() < 1e-12);
        }
    }
}
