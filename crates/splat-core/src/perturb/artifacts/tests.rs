use super::*;
use crate::raster::sh::basis;

/// A scene of `n` Gaussians in a 12-unit cube around the origin (the training cameras stand
/// inside it: some Gaussians are seen by one of them only), SH degree `degree`.
fn scene(n: usize, degree: u8) -> Scene {
    let k3 = sh_rest_count(degree) * 3;
    let s = |i: usize, op: u32, w: u64| {
        let st = Stream::new(op_key(99, op), i as u64);
        (st.word(w) >> 40) as f32 / 16_777_216.0
    };
    Scene {
        means: (0..n * 3)
            .map(|t| s(t / 3, 1, (t % 3) as u64) * 12.0 - 6.0)
            .collect(),
        quats: (0..n * 4)
            .map(|t| s(t / 4, 2, (t % 4) as u64) - 0.5)
            .collect(),
        log_scales: (0..n * 3)
            .map(|t| s(t / 3, 3, (t % 3) as u64) - 4.0)
            .collect(),
        opacity_logits: (0..n).map(|i| s(i, 4, 0) * 4.0 - 2.0).collect(),
        sh0: (0..n * 3)
            .map(|t| s(t / 3, 5, (t % 3) as u64) - 0.5)
            .collect(),
        sh_rest: (0..n * k3)
            .map(|t| (s(t / k3.max(1), 6, (t % k3.max(1)) as u64) - 0.5) * 0.2)
            .collect(),
        sh_degree: degree,
        extras: vec![],
    }
}

/// A camera at `eye` looking at the origin (OpenCV axes, y down roughly -z world up).
fn camera(eye: [f64; 3]) -> Camera {
    let f = {
        let n = (eye[0] * eye[0] + eye[1] * eye[1] + eye[2] * eye[2]).sqrt();
        [-eye[0] / n, -eye[1] / n, -eye[2] / n]
    };
    let up = [0.0, 0.0, 1.0];
    let cross = |a: [f64; 3], b: [f64; 3]| {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    };
    let r = cross(f, up);
    let rn = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
    let x = [r[0] / rn, r[1] / rn, r[2] / rn];
    let y = cross(f, x);
    let rows = [x, y, f];
    let t = rows.map(|row| -(row[0] * eye[0] + row[1] * eye[1] + row[2] * eye[2]));
    let mut m = [[0.0; 4]; 4];
    for i in 0..3 {
        m[i][..3].copy_from_slice(&rows[i]);
        m[i][3] = t[i];
    }
    m[3][3] = 1.0;
    Camera::new(60.0, 60.0, 32.0, 24.0, 64, 48, m)
}

fn cams() -> Vec<Camera> {
    (0..4)
        .map(|k| {
            let a = k as f64 * std::f64::consts::FRAC_PI_2;
            camera([8.0 * a.cos(), 8.0 * a.sin(), 1.0])
        })
        .collect()
}

fn all_ops() -> ArtifactParams {
    ArtifactParams {
        depth: Some(0.3),
        view_color: Some(0.2),
        needles: Some(0.3),
        holes: Some(0.3),
        hole_size: 0.1,
        dilate: Some(0.2),
        floaters: Some(0.05),
    }
}

fn images(cams: &[Camera]) -> Vec<f32> {
    (0..cams.len() * 64 * 48 * 3)
        .map(|t| (t % 251) as f32 / 250.0)
        .collect()
}

fn run(s: &Scene, p: &ArtifactParams, seed: u64, threads: usize) -> (Scene, Vec<bool>) {
    let cams = cams();
    let img = images(&cams);
    let depth = vec![0f32; cams.len() * 64 * 48]; // no surface: visibility is the frustum
    let im = TrainImages {
        rgb: &img,
        depth: &depth,
        width: 64,
        height: 48,
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("pool");
    pool.install(|| apply(&s.view(), &[], p, &cams, Some(im), seed).expect("apply"))
}

fn bits(s: &Scene) -> Vec<u32> {
    [
        &s.means,
        &s.quats,
        &s.log_scales,
        &s.opacity_logits,
        &s.sh0,
        &s.sh_rest,
    ]
    .iter()
    .flat_map(|v| v.iter().map(|x| x.to_bits()))
    .collect()
}

#[test]
fn the_same_bits_for_any_thread_count() {
    let s = scene(3 * CHUNK + 17, 3);
    let (a, ka) = run(&s, &all_ops(), 7, 1);
    for threads in [2, 8] {
        let (b, kb) = run(&s, &all_ops(), 7, threads);
        assert_eq!(bits(&a), bits(&b), "{threads} threads");
        assert_eq!(ka, kb);
    }
    assert_ne!(
        bits(&a),
        bits(&run(&s, &all_ops(), 8, 2).0),
        "another seed, other noise"
    );
}

#[test]
fn each_gaussian_gets_the_same_noise_whichever_other_ops_run() {
    let s = scene(500, 3);
    let alone = ArtifactParams {
        depth: Some(0.3),
        ..Default::default()
    };
    let (a, _) = run(&s, &alone, 3, 2);
    let (b, _) = run(
        &s,
        &ArtifactParams {
            holes: Some(0.5),
            ..alone
        },
        3,
        2,
    );
    assert_eq!(a.means, b.means);
    assert_eq!(a.log_scales, b.log_scales);
}

#[test]
fn the_depth_slide_keeps_each_gaussian_where_its_nearest_camera_sees_it() {
    let s = scene(400, 0);
    let p = ArtifactParams {
        depth: Some(0.5),
        ..Default::default()
    };
    let (out, keep) = run(&s, &p, 1, 2);
    assert!(keep.iter().all(|&k| k) && out.len() == s.len());
    let cams: Vec<Train> = cams().iter().map(Train::of).collect();
    let mut moved = 0;
    for i in 0..s.len() {
        let mu0 = [s.means[i * 3], s.means[i * 3 + 1], s.means[i * 3 + 2]];
        let mu1 = [out.means[i * 3], out.means[i * 3 + 1], out.means[i * 3 + 2]];
        let mut near = [0; VIEW_COLOR_PINS];
        nearest(&cams, mu0, 1, &mut near);
        let c = &cams[near[0]];
        let proj = |m: [f32; 3]| {
            let d = sub(m, c.centre);
            let z = dot(c.rot[2], d);
            [dot(c.rot[0], d) / z, dot(c.rot[1], d) / z]
        };
        let (a, b) = (proj(mu0), proj(mu1));
        assert!(
            (a[0] - b[0]).abs() < 1e-4 && (a[1] - b[1]).abs() < 1e-4,
            "{i}: {a:?} vs {b:?}"
        );
        let f = dot(sub(mu1, c.centre), sub(mu1, c.centre)).sqrt()
            / dot(sub(mu0, c.centre), sub(mu0, c.centre)).sqrt();
        // every other training view that sees it (before or after) sees it within the tolerance
        let radius = 3.0
            * s.log_scales[i * 3..i * 3 + 3]
                .iter()
                .fold(f32::MIN, |a, &b| a.max(b))
                .exp();
        let seen = |o: &Train, p: [f32; 3], r: f32| {
            let z = dot(o.rot[2], sub(p, o.centre));
            o.sees(p, if z > 1e-6 { r * o.fx / z } else { 0.0 })
        };
        for (k, o) in cams.iter().enumerate() {
            if k == near[0] {
                continue;
            }
            match (seen(o, mu0, radius), seen(o, mu1, radius * f)) {
                (None, None) => {}
                (Some(a), Some(b)) => {
                    let d = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt();
                    assert!(
                        d <= TOLERANCE_PX + 1e-2,
                        "{i}: moved {d} px in training view {k}"
                    );
                }
                other => panic!("{i}: training view {k} sees it on one side only: {other:?}"),
            }
        }
        // the scales grow by the depth factor: the footprint there is unchanged
        assert!((out.log_scales[i * 3] - s.log_scales[i * 3] - f.ln()).abs() < 1e-4);
        moved += usize::from((f - 1.0).abs() > 0.05);
    }
    assert!(
        moved > s.len() / 10,
        "Gaussians seen by one training view move: {moved}"
    );
}

#[test]
fn view_dependent_colour_is_unchanged_at_the_pinned_training_directions() {
    for degree in [0u8, 1, 3] {
        let s = scene(300, degree);
        let p = ArtifactParams {
            view_color: Some(0.5),
            ..Default::default()
        };
        let (out, _) = run(&s, &p, 5, 2);
        let deg = degree.max(1);
        assert_eq!(out.sh_degree, deg);
        let (k_in, k_out) = (sh_rest_count(degree), sh_rest_count(deg));
        let cams: Vec<Train> = cams().iter().map(Train::of).collect();
        let colour = |rest: &[f32], dir: [f32; 3], ch: usize, k: usize| {
            let mut b = [0f32; 16];
            basis(deg, dir, &mut b);
            (0..k)
                .map(|j| f64::from(b[j + 1]) * f64::from(rest[j * 3 + ch]))
                .sum::<f64>()
        };
        let (mut pinned, mut other) = (0f64, 0f64);
        for i in 0..s.len() {
            let mu = [out.means[i * 3], out.means[i * 3 + 1], out.means[i * 3 + 2]];
            // the pins: the training views that see it, nearest first, at most 3 (2 at degree 1)
            let mut seen: Vec<(f32, usize)> = (0..cams.len())
                .filter(|&k| cams[k].sees(mu, 0.0).is_some()) // the frustum (no depth maps here)
                .map(|k| (dot(sub(mu, cams[k].centre), sub(mu, cams[k].centre)), k))
                .collect();
            seen.sort_by(|a, b| a.partial_cmp(b).expect("finite"));
            let near: Vec<usize> = seen
                .iter()
                .take(VIEW_COLOR_PINS.min(k_out - 1))
                .map(|x| x.1)
                .collect();
            let n = near.len();
            let before = &s.sh_rest[i * k_in * 3..(i + 1) * k_in * 3];
            let after = &out.sh_rest[i * k_out * 3..(i + 1) * k_out * 3];
            for (k, c) in cams.iter().enumerate() {
                let dir = unit(sub(mu, c.centre)).expect("dir");
                for ch in 0..3 {
                    let d = (colour(after, dir, ch, k_out) - colour(before, dir, ch, k_in)).abs();
                    if near[..n].contains(&k) {
                        pinned = pinned.max(d);
                    } else {
                        other += d;
                    }
                }
            }
        }
        assert!(
            pinned < 1e-5,
            "degree {degree}: colour moved by {pinned} at a pinned direction"
        );
        assert!(
            other / (s.len() as f64) > 0.05,
            "degree {degree}: no change elsewhere"
        );
    }
}

#[test]
fn needles_holes_and_floaters_take_supersets_as_their_fraction_grows() {
    let s = scene(2000, 1);
    let at = |f: f32| ArtifactParams {
        needles: Some(f),
        holes: Some(f),
        floaters: Some(f * 10.0),
        hole_size: 0.1,
        ..Default::default()
    };
    let (lo, klo) = run(&s, &at(0.2), 4, 2);
    let (hi, khi) = run(&s, &at(0.4), 4, 2);
    let needle = |o: &Scene, i: usize| o.log_scales[i * 3] - o.log_scales[i * 3 + 1] > 2.0;
    let n = s.len();
    let (mut nl, mut nh) = (0, 0);
    for i in 0..n {
        assert!(!needle(&lo, i) || needle(&hi, i), "needle {i} lost");
        assert!(klo[i] || !khi[i], "hole {i} filled");
        nl += usize::from(needle(&lo, i));
        nh += usize::from(needle(&hi, i));
    }
    assert!(nl > 20 && nh > nl, "needles {nl} {nh}");
    // 2 and 4 per thousand of the 4 x 64 x 48 training pixels
    assert_eq!((lo.len() - n, hi.len() - n), (25, 49));
    // floater j is the same Gaussian at both densities
    assert_eq!(lo.means[n * 3..], hi.means[n * 3..(n + 25) * 3]);
    // holes are whole cells: neighbours in one cell share their fate
    let removed = klo[..n].iter().filter(|&&k| !k).count();
    assert!(removed > 200 && removed < 800, "removed {removed}");
}

#[test]
fn a_needle_points_along_its_training_ray_and_floaters_sit_in_front_of_a_camera() {
    let s = scene(500, 0);
    let p = ArtifactParams {
        needles: Some(1.0),
        floaters: Some(5.0),
        ..Default::default()
    };
    let (out, _) = run(&s, &p, 2, 2);
    let cams: Vec<Train> = cams().iter().map(Train::of).collect();
    let mut needles = 0;
    for i in 0..s.len() {
        if out.quats[i * 4..i * 4 + 4] == s.quats[i * 4..i * 4 + 4] {
            continue; // no depth ambiguity here: the training views keep it as it is
        }
        needles += 1;
        let mu = [out.means[i * 3], out.means[i * 3 + 1], out.means[i * 3 + 2]];
        let mut near = [0; VIEW_COLOR_PINS];
        nearest(&cams, mu, 1, &mut near);
        let ray = unit(sub(mu, cams[near[0]].centre)).expect("ray");
        let q = &out.quats[i * 4..i * 4 + 4];
        // the local x axis rotated by q: the first column of R(q)
        let (w, x, y, z) = (q[0], q[1], q[2], q[3]);
        let axis = [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y + w * z),
            2.0 * (x * z - w * y),
        ];
        assert!(dot(axis, ray) > 0.999, "{i}");
        let ls = &out.log_scales[i * 3..i * 3 + 3];
        assert!(
            ls[0] > ls[1] && ls[1] == ls[2] && ls[0] - ls[1] <= NEEDLE_LOG_LENGTH,
            "{i}: {ls:?}"
        );
    }
    assert!(needles > 50, "{needles} needles");
    let img = images(&self::cams());
    let extent = mean_extent(&s.view()) as f32;
    for j in 0..50 {
        let i = s.len() + j;
        let mu = [out.means[i * 3], out.means[i * 3 + 1], out.means[i * 3 + 2]];
        let rgb = [0, 1, 2].map(|c| out.sh0[i * 3 + c] * SH_C0 + 0.5);
        // the camera it was spawned from sees it, in front, on a pixel of its colour
        let from = cams.iter().enumerate().any(|(k, c)| {
            let d = sub(mu, c.centre);
            let zc = dot(c.rot[2], d);
            let (u, v) = (
                c.fx * dot(c.rot[0], d) / zc + c.cx,
                c.fy * dot(c.rot[1], d) / zc + c.cy,
            );
            let px = |x: f32, w: f32| [x - 1e-3, x + 1e-3].map(|t| t.clamp(0.0, w - 1.0) as usize);
            zc > 0.0
                && zc <= FLOATER_FAR * extent * 1.001
                && (-0.01..64.01).contains(&u)
                && (-0.01..48.01).contains(&v)
                && px(u, 64.0).iter().any(|&x| {
                    px(v, 48.0).iter().any(|&y| {
                        let o = ((k * 48 + y) * 64 + x) * 3;
                        (0..3).all(|c| (rgb[c] - img[o + c]).abs() < 1e-4)
                    })
                })
        });
        assert!(from, "floater {j}");
    }
}

#[test]
fn bad_parameters_and_missing_cameras_are_named() {
    let s = scene(10, 0);
    let err = |p: ArtifactParams, cams: &[Camera]| {
        apply(&s.view(), &[], &p, cams, None, 0)
            .expect_err("must fail")
            .to_string()
    };
    assert!(err(
        ArtifactParams {
            needles: Some(1.5),
            ..Default::default()
        },
        &cams()
    )
    .contains("needles"));
    assert!(err(
        ArtifactParams {
            floaters: Some(11.0),
            ..Default::default()
        },
        &cams()
    )
    .contains("floaters"));
    assert!(err(
        ArtifactParams {
            hole_size: 0.0,
            ..Default::default()
        },
        &cams()
    )
    .contains("hole_size"));
    assert!(err(
        ArtifactParams {
            depth: Some(f32::NAN),
            ..Default::default()
        },
        &cams()
    )
    .contains("depth"));
    assert!(err(
        ArtifactParams {
            depth: Some(0.1),
            ..Default::default()
        },
        &[]
    )
    .contains("training cameras"));
    let (out, keep) = apply(
        &s.view(),
        &[],
        &ArtifactParams {
            dilate: Some(0.5),
            ..Default::default()
        },
        &[],
        None,
        0,
    )
    .expect("dilate needs no camera");
    assert!(keep.iter().all(|&k| k));
    assert_eq!(out.log_scales[0], s.log_scales[0] + 0.5);
}
