//! Criterion: `perturb` over 1M Gaussians of SH degree 3 for each preset, next to a plain copy of
//! the scene arrays (the floor), and the `shatter` op's fragments for 12 training views of a
//! textured plane at 128x96 (its colour fit over the other views is the cost).
//! `cargo bench -p splat-core --bench perturb`.
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use splat_core::camera::Camera;
use splat_core::perturb::haze::haze;
use splat_core::perturb::shatter::{fragments, ShatterParams, Views};
use splat_core::perturb::{perturb, PerturbParams};
use splat_core::Scene;

const N: usize = 1_000_000;

/// A deterministic pseudo-random scene (SplitMix64 values; no extra dependencies).
fn scene(n: usize) -> Scene {
    let mut state = 1u64;
    let mut next = move || {
        state = state.wrapping_add(splat_core::rng::GAMMA);
        (splat_core::rng::mix64(state) >> 40) as f32 / 16_777_216.0 - 0.5
    };
    let mut v = |len: usize, scale: f32, offset: f32| -> Vec<f32> {
        (0..len).map(|_| next() * scale + offset).collect()
    };
    let mut s = Scene {
        means: v(n * 3, 10.0, 0.0),
        quats: v(n * 4, 2.0, 0.0),
        log_scales: v(n * 3, 2.0, -4.0),
        opacity_logits: v(n, 4.0, 0.0),
        sh0: v(n * 3, 2.0, 0.0),
        sh_rest: v(n * 45, 0.2, 0.0),
        sh_degree: 3,
        extras: Vec::new(),
    };
    s.normalize_quats();
    s
}

fn bench(c: &mut Criterion) {
    let s = scene(N);
    let view = s.view();
    let mut g = c.benchmark_group("perturb_1M_sh3");
    g.sample_size(10);
    g.throughput(Throughput::Elements(N as u64));
    g.bench_function("copy", |b| b.iter(|| s.clone()));
    for name in PerturbParams::PRESETS {
        let params = PerturbParams::preset(name).expect("known preset");
        g.bench_function(name, |b| {
            b.iter(|| perturb(&view, &[], &params, 7).expect("valid scene"))
        });
    }
    g.finish();
}

/// 12 cameras along x looking down +z at a plane z = 5, 128x96, and their clean renders.
fn plane_views() -> (Vec<Camera>, Vec<f32>, Vec<f32>, Vec<f32>) {
    let (w, h, f) = (128u32, 96u32, 110.0);
    let (mut cams, mut rgb) = (Vec::new(), Vec::new());
    for k in 0..12 {
        let ox = 0.25 * f64::from(k);
        let m = [
            [1.0, 0.0, 0.0, -ox],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        cams.push(Camera::new(f, f, 64.0, 48.0, w, h, m));
        for y in 0..h {
            for x in 0..w {
                let wx = (f64::from(x) + 0.5 - 64.0) / f * 5.0 + ox;
                let wy = (f64::from(y) + 0.5 - 48.0) / f * 5.0;
                rgb.extend([
                    (0.5 + 0.4 * (3.0 * wx).sin()) as f32,
                    (0.5 + 0.4 * (2.0 * wy).cos()) as f32,
                    0.3,
                ]);
            }
        }
    }
    let n = (w * h) as usize * cams.len();
    (cams, rgb, vec![5.0; n], vec![1.0; n])
}

fn bench_shatter(c: &mut Criterion) {
    let (cams, rgb, depth, alpha) = plane_views();
    let views = Views {
        rgb: &rgb,
        depth: &depth,
        alpha: &alpha,
    };
    let mut g = c.benchmark_group("shatter_12x128x96");
    g.sample_size(10);
    for value in [1.0f32, 3.0] {
        let params = ShatterParams {
            value,
            ..Default::default()
        };
        g.bench_function(format!("v{value}"), |b| {
            b.iter(|| fragments(&params, &cams, views, 30_000, 7).expect("valid views"))
        });
    }
    g.finish();
}

/// 12 cameras on a ring of radius 3 at height 1.6 looking at the origin (OpenCV axes), 128x96:
/// a room's capture path, as the haze op meets it.
fn ring_cameras() -> Vec<Camera> {
    (0..12)
        .map(|k| {
            let a = f64::from(k) / 12.0 * std::f64::consts::TAU * 0.9;
            let c = [3.0 * a.cos(), 3.0 * a.sin(), 1.6];
            let norm = |v: [f64; 3]| {
                let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                v.map(|x| x / l)
            };
            let cross = |a: [f64; 3], b: [f64; 3]| {
                [
                    a[1] * b[2] - a[2] * b[1],
                    a[2] * b[0] - a[0] * b[2],
                    a[0] * b[1] - a[1] * b[0],
                ]
            };
            let fwd = norm([-c[0], -c[1], -c[2]]);
            let right = norm(cross(fwd, [0.0, 0.0, 1.0]));
            let down = cross(fwd, right);
            let mut m = [[0.0; 4]; 4];
            for (r, row) in [right, down, fwd].into_iter().enumerate() {
                m[r] = [
                    row[0],
                    row[1],
                    row[2],
                    -(row[0] * c[0] + row[1] * c[1] + row[2] * c[2]),
                ];
            }
            m[3][3] = 1.0;
            Camera::new(110.0, 110.0, 64.0, 48.0, 128, 96, m)
        })
        .collect()
}

fn bench_haze(c: &mut Criterion) {
    let cams = ring_cameras();
    let mut g = c.benchmark_group("haze_12x128x96");
    g.sample_size(20);
    for value in [1.0f32, 4.0] {
        g.bench_function(format!("v{value}"), |b| {
            b.iter(|| haze(&cams, value, 7).expect("valid cameras"))
        });
    }
    g.finish();
}

criterion_group!(benches, bench, bench_shatter, bench_haze);
criterion_main!(benches);
