use super::*;
use crate::perturb::haze::tests::ring;

const BACKDROP: [f32; 3] = [0.05, 0.04, 0.06];

/// Clean views of a unit sphere at the origin (shaded by its normal) in front of a dark backdrop
/// (nothing hit: depth 0), as the renderer would give them.
fn sphere_views(cams: &[Camera]) -> (Vec<f32>, Vec<f32>) {
    let (mut rgb, mut depth) = (Vec::new(), Vec::new());
    for c in cams {
        let o = c.center();
        let r = c.rotation();
        for y in 0..c.height {
            for x in 0..c.width {
                let l = [
                    (f64::from(x) + 0.5 - c.cx) / c.fx,
                    (f64::from(y) + 0.5 - c.cy) / c.fy,
                    1.0,
                ];
                let d = [0, 1, 2].map(|k| r[0][k] * l[0] + r[1][k] * l[1] + r[2][k] * l[2]);
                // |o + t d|^2 = 1, t the camera z (d has camera z 1)
                let a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
                let b = 2.0 * (o[0] * d[0] + o[1] * d[1] + o[2] * d[2]);
                let cc = o[0] * o[0] + o[1] * o[1] + o[2] * o[2] - 1.0;
                let disc = b * b - 4.0 * a * cc;
                if disc < 0.0 {
                    rgb.extend_from_slice(&BACKDROP);
                    depth.push(0.0);
                } else {
                    let t = (-b - disc.sqrt()) / (2.0 * a);
                    let n = [0, 1, 2].map(|k| o[k] + t * d[k]);
                    let shade = (0.6 + 0.3 * n[2] + 0.1 * n[0]) as f32;
                    rgb.extend_from_slice(&[shade, 0.8 * shade, 0.6 * shade]);
                    depth.push(t as f32);
                }
            }
        }
    }
    (rgb, depth)
}

fn pixel(c: &Camera, p: [f32; 3]) -> Option<(usize, usize, f64)> {
    let m = &c.world_to_camera;
    let p = p.map(f64::from);
    let z = m[2][0] * p[0] + m[2][1] * p[1] + m[2][2] * p[2] + m[2][3];
    let u = c.fx * (m[0][0] * p[0] + m[0][1] * p[1] + m[0][2] * p[2] + m[0][3]) / z + c.cx;
    let v = c.fy * (m[1][0] * p[0] + m[1][1] * p[1] + m[1][2] * p[2] + m[1][3]) / z + c.cy;
    (z > 0.0 && u >= 0.0 && v >= 0.0 && u < f64::from(c.width) && v < f64::from(c.height))
        .then_some((u as usize, v as usize, z))
}

#[test]
fn the_same_bytes_for_1_2_and_8_threads_and_a_larger_value_keeps_a_superset() {
    let cams = ring(6, (64, 48));
    let (rgb, depth) = sphere_views(&cams);
    let views = Views {
        rgb: &rgb,
        depth: &depth,
    };
    let run = |t: usize, v: f32| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(t)
            .build()
            .expect("pool")
            .install(|| veil(&cams, views, v, 3).expect("veil"))
    };
    let one = run(1, 1.0);
    assert_eq!(one.len(), 600);
    assert_eq!(one, run(2, 1.0));
    assert_eq!(one, run(8, 1.0));
    let more = run(2, 1.5);
    assert_eq!(more.len(), 900);
    assert_eq!(&more.means[..600], &one.means[..]);
    assert_eq!(&more.sh0[..600], &one.sh0[..]);
    assert!(veil(&cams, views, 0.0, 3).expect("veil").is_empty());
    assert_ne!(one, veil(&cams, views, 1.0, 4).expect("veil"));
}

#[test]
fn the_veil_shows_its_own_colour_to_every_training_view_and_covers_the_object_between_them() {
    let all = ring(24, (64, 48));
    let train: Vec<Camera> = all.iter().step_by(4).cloned().collect();
    let (rgb, depth) = sphere_views(&train);
    let views = Views {
        rgb: &rgb,
        depth: &depth,
    };
    let v = veil(&train, views, 1.0, 11).expect("veil");
    assert_eq!(v.len(), 600);
    let (w, h) = (64usize, 48usize);
    let mut dark = 0;
    for (i, p) in v.means.iter().enumerate() {
        let c = v.sh0[i].map(|x| x * SH_C0 + 0.5);
        if (0..3).all(|k| (c[k] - BACKDROP[k]).abs() < 1e-6) {
            dark += 1;
        }
        let mut seen = 0;
        for (k, cam) in train.iter().enumerate() {
            let Some((x, y, z)) = pixel(cam, *p) else {
                continue;
            };
            let surface = depth[(k * h + y) * w + x];
            if surface > 0.0 && z as f32 > HIDDEN * surface {
                continue;
            }
            seen += 1;
            let o = ((k * h + y) * w + x) * 3;
            let e: f32 = (0..3).map(|j| (rgb[o + j] - c[j]).powi(2)).sum::<f32>() / 3.0;
            assert!(
                e <= TOLERANCE * TOLERANCE,
                "veil {i} in view {k}: rms {}",
                e.sqrt()
            );
        }
        assert!(seen >= 1, "veil {i}'s centre in no training view");
    }
    // the smooth shading leaves few uniform patches on the object: the veil is the backdrop's
    assert!(
        dark * 10 >= v.len() * 9,
        "{dark} of {} backdrop-coloured",
        v.len()
    );
    // and from the held-out cameras some of it lies over the object
    let (_, hdepth) = sphere_views(&all);
    let over = v
        .means
        .iter()
        .filter(|p| {
            all.iter().enumerate().any(|(k, cam)| {
                k % 4 != 0
                    && pixel(cam, **p)
                        .is_some_and(|(x, y, z)| hdepth[(k * h + y) * w + x] as f64 > z)
            })
        })
        .count();
    assert!(
        over * 5 >= v.len(),
        "{over} of {} over the object held out",
        v.len()
    );
}

#[test]
fn bad_values_and_maps_are_errors() {
    let cams = ring(4, (32, 24));
    let (rgb, depth) = sphere_views(&cams);
    let views = Views {
        rgb: &rgb,
        depth: &depth,
    };
    assert!(veil(&cams, views, f32::NAN, 0).is_err());
    assert!(veil(&cams, views, -1.0, 0).is_err());
    assert!(veil(&cams, views, 1e30, 0).is_err()); // no huge allocation
    assert!(veil(&[], views, 1.0, 0).is_err());
    assert!(veil(&cams[..1], views, 1.0, 0).is_err());
    let short = Views {
        rgb: &rgb[..rgb.len() - 3],
        depth: &depth,
    };
    let e = veil(&cams, short, 1.0, 0).expect_err("short maps");
    assert!(e.to_string().contains("expected 4 renders of 32x24"), "{e}");
}
