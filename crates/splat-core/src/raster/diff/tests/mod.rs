//! Tests of the differentiable rasterizer's mechanics: same forward bits as `render_into`, the
//! SIMD backward kernels against the generic one bit for bit, and gradients that do not depend
//! on the thread count or the banding. (The gradients' values are checked against torch
//! autograd and finite differences in tests/test_backward_*.py.)
//!
//! Here the forward, determinism and argument tests; `kernels`: the tile backward's kernels
//! slot for slot; `reference`: the per-Gaussian backward against its scalar reference.
use super::*;
use crate::raster::{render_into, RenderOptions, Simd};
use crate::Scene;

mod kernels;
mod reference;

fn rng(seed: u64) -> impl FnMut() -> f32 {
    let mut h = seed | 1;
    move || {
        h ^= h << 13;
        h ^= h >> 7;
        h ^= h << 17;
        (h >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// A cloud in front of the camera, SH degree `degree`, with large and opaque Gaussians mixed in
/// (alpha at max_alpha, early termination).
fn scene(n: usize, degree: u8, seed: u64) -> Scene {
    let mut s = Scene::empty(degree);
    let k = s.sh_rest_k() * 3;
    let mut next = rng(seed);
    for i in 0..n {
        s.means
            .extend([next() * 2.0 - 1.0, next() * 2.0 - 1.0, next() * 2.0 - 1.0]);
        s.quats
            .extend([1.0, next() - 0.5, next() - 0.5, next() - 0.5]);
        let big = if i % 41 == 0 { 1.5 } else { 0.0 };
        s.log_scales.extend([
            -3.5 - next() + big,
            -3.5 - next() + big,
            -3.0 - next() + big,
        ]);
        s.opacity_logits
            .push(if i % 7 == 0 { 8.0 } else { next() * 6.0 - 3.0 });
        s.sh0.extend([next() - 0.5, next() - 0.5, next() - 0.5]);
        s.sh_rest.extend((0..k).map(|_| 0.3 * (next() - 0.5)));
    }
    s.normalize_quats();
    s
}

fn camera(width: u32, height: u32) -> Camera {
    let mut m = [[0.0; 4]; 4];
    for (i, row) in m.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    m[2][3] = 4.0;
    Camera::new(
        1.2 * width as f64,
        1.2 * width as f64,
        0.47 * width as f64,
        0.55 * height as f64,
        width,
        height,
        m,
    )
}

struct Frame {
    rgb: Vec<f32>,
    depth: Vec<f32>,
    alpha: Vec<f32>,
}

fn forward(ws: &mut Workspace, s: &Scene, cam: &Camera, opts: &DiffOptions) -> Frame {
    let n = cam.width as usize * cam.height as usize;
    let mut f = Frame {
        rgb: vec![0.0; n * 3],
        depth: vec![0.0; n],
        alpha: vec![0.0; n],
    };
    ws.forward(
        &s.view(),
        cam,
        opts,
        None,
        &mut f.rgb,
        &mut f.depth,
        &mut f.alpha,
    )
    .expect("forward");
    f
}

fn image_grads(cam: &Camera, seed: u64) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let n = cam.width as usize * cam.height as usize;
    let mut next = rng(seed);
    (
        (0..n * 3).map(|_| next() - 0.5).collect(),
        (0..n).map(|_| 0.2 * (next() - 0.5)).collect(),
        (0..n).map(|_| next() - 0.5).collect(),
    )
}

/// Every gradient's bits, in a fixed order.
fn grad_bits(g: &Gradients, d: &DensifyStats) -> Vec<u32> {
    let mut v = Vec::new();
    for a in [
        &g.means,
        &g.quats,
        &g.log_scales,
        &g.opacity_logits,
        &g.sh0,
        &g.sh_rest,
        &g.scales,
        &g.opacities,
        &d.grad2d,
        &d.grad2d_abs,
        &d.count,
        &d.max_radius,
    ] {
        v.extend(a.iter().map(|x| x.to_bits()));
    }
    v.extend(g.background.iter().map(|x| x.to_bits()));
    v
}

fn backward_bits(s: &Scene, cam: &Camera, opts: &DiffOptions, seed: u64) -> (Vec<u32>, u64) {
    let mut ws = Workspace::default();
    forward(&mut ws, s, cam, opts);
    let (r, d, a) = image_grads(cam, seed);
    let mut g = Gradients::default();
    g.reset(s.len(), s.sh_rest_k(), false);
    let mut dens = DensifyStats::default();
    dens.reset(s.len());
    let st = ws
        .backward(
            &s.view(),
            None,
            &ImageGrads {
                rgb: Some(&r),
                depth: Some(&d),
                alpha: Some(&a),
                skip_background: false,
            },
            &mut g,
            None,
            Some(&mut dens),
        )
        .expect("backward");
    assert!(g.means.iter().all(|v| v.is_finite()));
    (grad_bits(&g, &dens), st.evaluations)
}

#[test]
fn forward_gives_render_into_bits() {
    let s = scene(4000, 1, 3);
    let cam = camera(100, 70);
    for antialiased in [false, true] {
        let opts = DiffOptions {
            render: RenderOptions {
                antialiased,
                background: [0.2, 0.4, 0.9],
                ..Default::default()
            },
            ..Default::default()
        };
        let mut ws = Workspace::default();
        let f = forward(&mut ws, &s, &cam, &opts);
        let n = 100 * 70;
        let (mut rgb, mut depth, mut alpha) = (vec![0.0; n * 3], vec![0.0; n], vec![0.0; n]);
        render_into(
            &s.view(),
            &cam,
            &opts.render,
            &mut rgb,
            &mut depth,
            &mut alpha,
        )
        .expect("render");
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&f.rgb), bits(&rgb));
        assert_eq!(bits(&f.depth), bits(&depth));
        assert_eq!(bits(&f.alpha), bits(&alpha));
        // a second forward on the same workspace (reused buffers) gives the same bits
        let g = forward(&mut ws, &s, &cam, &opts);
        assert_eq!(bits(&g.rgb), bits(&rgb));
    }
}

#[test]
fn gradients_are_identical_for_any_thread_count() {
    let s = scene(5000, 2, 5);
    let cam = camera(96, 80);
    let opts = DiffOptions::default();
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool")
            .install(|| backward_bits(&s, &cam, &opts, 11))
    };
    let (a, b, c) = (run(1), run(3), run(8));
    assert!(a.1 > 0);
    assert_eq!(a, b);
    assert_eq!(a, c);
}

#[test]
fn gradients_do_not_depend_on_the_banding() {
    let s = scene(3000, 0, 8);
    let cam = camera(80, 100);
    let one = DiffOptions::default();
    // a budget below one tile row's slots: one band per tile row
    let tiny = DiffOptions {
        slot_budget: 1,
        ..Default::default()
    };
    let mid = DiffOptions {
        slot_budget: 3000 * SLOT_BYTES,
        ..Default::default()
    };
    let want = backward_bits(&s, &cam, &one, 2);
    assert_eq!(backward_bits(&s, &cam, &tiny, 2), want);
    assert_eq!(backward_bits(&s, &cam, &mid, 2), want);
    let mut ws = Workspace::default();
    forward(&mut ws, &s, &cam, &tiny);
    assert_eq!(ws.bands(1).len(), 7); // 100 px = 7 tile rows
    assert!(ws.bands(3000 * SLOT_BYTES).len() > 1);
    assert_eq!(ws.bands(usize::MAX).len(), 1);
}

/// The kernel of each SIMD level gives finite gradients close to the others (the plain kernel
/// rounds without FMA, so only closeness is expected from it). Their evaluation counts differ
/// by work unit (16-pixel rows, 4x4 blocks; held to a model tile by tile in `kernels`); the two
/// explicit kernels, which share the unit, count the same.
#[test]
fn simd_levels_give_close_gradients() {
    let s = scene(3000, 1, 21);
    let cam = camera(90, 60);
    let run = |simd: Simd| {
        let opts = DiffOptions {
            render: RenderOptions {
                simd,
                ..Default::default()
            },
            ..Default::default()
        };
        let (bits, evals) = backward_bits(&s, &cam, &opts, 4);
        (
            bits.into_iter().map(f32::from_bits).collect::<Vec<_>>(),
            evals,
        )
    };
    let (base, _) = run(Simd::Scalar);
    let scale = base.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let mut counts = Vec::new();
    for simd in [Simd::Avx2, Simd::Avx512] {
        let (got, e) = run(simd);
        if simd.resolve() != Simd::Scalar {
            counts.push(e);
        }
        let err = got
            .iter()
            .zip(&base)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(
            err <= 1e-3 * scale,
            "{}: {err} of {scale}",
            simd.resolve().name()
        );
    }
    if let [a, b] = counts[..] {
        assert_eq!(a, b, "AVX2 and AVX-512 evaluations");
    }
}

#[test]
fn backward_checks_its_inputs() {
    let s = scene(100, 0, 1);
    let cam = camera(32, 32);
    let mut ws = Workspace::default();
    let mut g = Gradients::default();
    g.reset(s.len(), 0, false);
    let none = ImageGrads::default();
    assert!(ws
        .backward(&s.view(), None, &none, &mut g, None, None)
        .is_err());
    forward(&mut ws, &s, &cam, &DiffOptions::default());
    let short = vec![0.0f32; 10];
    let bad = ImageGrads {
        rgb: Some(&short),
        ..Default::default()
    };
    assert!(ws
        .backward(&s.view(), None, &bad, &mut g, None, None)
        .is_err());
    let other = scene(50, 0, 2);
    assert!(ws
        .backward(&other.view(), None, &none, &mut g, None, None)
        .is_err());
    let mut wrong = Gradients::default();
    wrong.reset(7, 0, false);
    assert!(ws
        .backward(&s.view(), None, &none, &mut wrong, None, None)
        .is_err());
    // zero image gradients give zero parameter gradients
    ws.backward(&s.view(), None, &none, &mut g, None, None)
        .expect("backward");
    assert!(g.means.iter().chain(&g.sh0).all(|&v| v == 0.0));
}

#[test]
fn reset_since_a_lower_degree_gives_the_fresh_reset_gradients() {
    // a scene storing SH degree 3, backward passes at degree 1 then 2 (as an optimiser raises
    // its degree): clearing only the bands the previous pass could write leaves the same bits
    let s = scene(300, 3, 11);
    let cam = camera(64, 48);
    let (r, _, _) = image_grads(&cam, 12);
    let grads = ImageGrads {
        rgb: Some(&r),
        ..ImageGrads::default()
    };
    let at = |degree: u8| DiffOptions {
        render: RenderOptions {
            sh_degree: Some(degree),
            ..RenderOptions::default()
        },
        ..DiffOptions::default()
    };
    let mut ws = Workspace::default();
    let mut g = Gradients::default();
    g.reset_since(s.len(), s.sh_rest_k(), false, None);
    forward(&mut ws, &s, &cam, &at(1));
    ws.backward(&s.view(), None, &grads, &mut g, None, None)
        .expect("backward");
    assert!(
        g.sh_rest.iter().any(|&v| v != 0.0),
        "degree 1 writes band 1"
    );
    g.reset_since(s.len(), s.sh_rest_k(), false, Some(1));
    assert!(g.sh_rest.iter().all(|&v| v == 0.0));
    forward(&mut ws, &s, &cam, &at(2));
    ws.backward(&s.view(), None, &grads, &mut g, None, None)
        .expect("backward");
    let mut fresh = Gradients::default();
    fresh.reset(s.len(), s.sh_rest_k(), false);
    ws.backward(&s.view(), None, &grads, &mut fresh, None, None)
        .expect("backward");
    let none = DensifyStats::default();
    assert_eq!(grad_bits(&g, &none), grad_bits(&fresh, &none));
    // another size is a full reset
    g.reset_since(10, s.sh_rest_k(), false, Some(0));
    assert_eq!(g.sh_rest.len(), 10 * s.sh_rest_k() * 3);
    assert!(g.means.iter().chain(&g.sh_rest).all(|&v| v == 0.0));
}

#[test]
fn reset_since_clears_large_buffers_in_parallel_chunks_exactly() {
    // more floats than one parallel chunk, and a Gaussian count whose SH rows do not divide it:
    // every parameter gradient and exactly the bands up to the degree end up zero
    let (n, k) = (7_001, 15);
    let mut g = Gradients::default();
    g.reset(n, k, false);
    for v in [
        &mut g.means,
        &mut g.quats,
        &mut g.log_scales,
        &mut g.opacity_logits,
        &mut g.sh0,
        &mut g.sh_rest,
        &mut g.scales,
        &mut g.opacities,
    ] {
        v.fill(1.0);
    }
    g.reset_since(n, k, false, Some(1));
    for v in [
        &g.means,
        &g.quats,
        &g.log_scales,
        &g.opacity_logits,
        &g.sh0,
        &g.scales,
        &g.opacities,
    ] {
        assert!(v.iter().all(|&x| x == 0.0));
    }
    for row in g.sh_rest.chunks_exact(k * 3) {
        assert!(row[..9].iter().all(|&x| x == 0.0));
        assert!(row[9..].iter().all(|&x| x == 1.0));
    }
    g.reset_since(n, k, false, Some(3));
    assert!(g.sh_rest.iter().all(|&x| x == 0.0));
}

#[test]
fn skipping_the_background_gradient_leaves_every_other_gradient_bit() {
    let s = scene(3000, 2, 8);
    let cam = camera(70, 50);
    let opts = DiffOptions {
        render: RenderOptions {
            background: [0.3, 0.1, 0.7],
            ..Default::default()
        },
        ..Default::default()
    };
    let (r, _, _) = image_grads(&cam, 6);
    let run = |skip: bool| {
        let mut ws = Workspace::default();
        forward(&mut ws, &s, &cam, &opts);
        let mut g = Gradients::default();
        g.reset(s.len(), s.sh_rest_k(), false);
        let mut dens = DensifyStats::default();
        dens.reset(s.len());
        let grads = ImageGrads {
            rgb: Some(&r),
            skip_background: skip,
            ..ImageGrads::default()
        };
        ws.backward(&s.view(), None, &grads, &mut g, None, Some(&mut dens))
            .expect("backward");
        let bg = std::mem::take(&mut g.background);
        (grad_bits(&g, &dens), bg)
    };
    let (with, bg) = run(false);
    let (without, none) = run(true);
    assert_eq!(with, without);
    assert!(bg.iter().any(|&v| v != 0.0));
    assert_eq!(none, [0.0; 3]);
}

/// The fit's forward without depth (`DepthKind::None`) gives the rgb and alpha bits of a
/// forward with depth, and, with no depth gradient, the same gradient bits (the per-tile
/// inputs then skip the depth sums, which that forward leaves stale), on every kernel, with
/// and without absgrad; a depth gradient is refused after it.
#[test]
fn forward_without_depth_keeps_rgb_alpha_and_gradient_bits_on_every_kernel() {
    let s = scene(4000, 1, 17);
    let cam = camera(83, 61);
    let (r, _, a) = image_grads(&cam, 9);
    let n = cam.width as usize * cam.height as usize;
    let mut checked = 0;
    for simd in [Simd::Avx512, Simd::Avx2, Simd::Scalar] {
        for absgrad in [false, true] {
            let run = |depth: DepthKind, ws: &mut Workspace| {
                let opts = DiffOptions {
                    render: RenderOptions {
                        simd,
                        background: [0.2, 0.5, 0.1],
                        ..Default::default()
                    },
                    depth,
                    absgrad,
                    ..Default::default()
                };
                let (mut rgb, mut alpha) = (vec![0.0; n * 3], vec![0.0; n]);
                // without depth the depth image may be empty
                let mut d = if depth == DepthKind::None {
                    Vec::new()
                } else {
                    vec![0.0; n]
                };
                ws.forward(&s.view(), &cam, &opts, None, &mut rgb, &mut d, &mut alpha)
                    .expect("forward");
                let mut g = Gradients::default();
                g.reset(s.len(), s.sh_rest_k(), false);
                let mut dens = DensifyStats::default();
                dens.reset(s.len());
                let grads = ImageGrads {
                    rgb: Some(&r),
                    alpha: Some(&a),
                    ..ImageGrads::default()
                };
                ws.backward(&s.view(), None, &grads, &mut g, None, Some(&mut dens))
                    .expect("backward");
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                (bits(&rgb), bits(&alpha), grad_bits(&g, &dens))
            };
            // the same workspace: the forward with depth first, so the stale depth sums the
            // one without depth leaves are real values, not zeros
            let mut ws = Workspace::default();
            let with = run(DepthKind::Expected, &mut ws);
            let without = run(DepthKind::None, &mut ws);
            assert!(with.2.iter().any(|&b| b != 0));
            assert_eq!(with.0, without.0, "rgb {simd:?}");
            assert_eq!(with.1, without.1, "alpha {simd:?}");
            assert_eq!(with.2, without.2, "gradients {simd:?} absgrad {absgrad}");
            assert_eq!(with, run(DepthKind::Accumulated, &mut Workspace::default()));
            checked += 1;
            // a depth gradient after a forward without depth is an error
            let mut g = Gradients::default();
            g.reset(s.len(), s.sh_rest_k(), false);
            let depth = vec![0.0f32; n];
            let err = ws
                .backward(
                    &s.view(),
                    None,
                    &ImageGrads {
                        depth: Some(&depth),
                        ..ImageGrads::default()
                    },
                    &mut g,
                    None,
                    None,
                )
                .expect_err("depth gradient without depth");
            assert!(err.to_string().contains("DepthKind::None"), "{err}");
        }
    }
    assert_eq!(checked, 6);
}
