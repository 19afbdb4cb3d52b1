//! Tests of the differentiable rasterizer's mechanics: same forward bits as `render_into`, the
//! SIMD backward kernels against the generic one bit for bit, and gradients that do not depend
//! on the thread count or the banding. (The gradients' values are checked against torch
//! autograd and finite differences in tests/test_backward_*.py.)
use super::gauss_bwd::viewmat_grad;
use super::*;
use crate::raster::{render_into, RenderOptions, Simd};
use crate::Scene;

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

/// The kernel of each SIMD level gives finite gradients close to the others (the plain kernel
/// rounds without FMA, so only closeness is expected from it). Their evaluation counts differ
/// by work unit (16-pixel rows, 4x4 blocks; held to a model tile by tile above); the two
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

/// The same bits, or NaN in both (a NaN's payload is not part of the contract).
fn same(a: f32, b: f32) -> bool {
    a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())
}

/// Gaussians for the per-Gaussian backward, ordinary ones and degenerate ones: means outside
/// the frustum clamp on either side, behind the camera and at its centre, needle-thin (the
/// antialiasing clamp), huge, unnormalised quaternions, saturated and faint opacities.
fn odd_scene(n: usize, degree: u8, seed: u64) -> Scene {
    let mut s = scene(n, degree, seed);
    let mut next = rng(seed ^ 0x9e37);
    for i in 0..n {
        let m = &mut s.means[i * 3..i * 3 + 3];
        match i % 9 {
            1 => m[0] = 6.0 + 4.0 * next(),  // right of the clamp (z about 4)
            2 => m[1] = -7.0 - 4.0 * next(), // above it
            3 => m[2] = -4.5 - next(),       // behind the camera
            4 => m.copy_from_slice(&[0.0, 0.0, -4.0]), // the camera centre
            _ => {}
        }
        let ls = &mut s.log_scales[i * 3..i * 3 + 3];
        match i % 5 {
            1 => ls[0] = -12.0, // needle: det ratio below the clamp
            2 => ls.copy_from_slice(&[-11.0, -11.5, -12.0]),
            3 => ls[2] = 1.0,
            _ => {}
        }
        if i % 4 == 1 {
            for q in &mut s.quats[i * 4..i * 4 + 4] {
                *q *= 2.5;
            }
        }
        if i % 6 == 5 {
            s.opacity_logits[i] = -9.0;
        }
    }
    s
}

/// A splat conic (positive definite mostly, sometimes not) and summed slots of any sign.
fn odd_inputs(next: &mut impl FnMut() -> f32, i: usize) -> (Splat, [f32; slot::LEN]) {
    let (a, c) = (0.01 + 3.0 * next(), 0.01 + 3.0 * next());
    let b = (next() - 0.5) * if i.is_multiple_of(11) { 8.0 } else { 0.5 };
    let s = Splat {
        conic: [a, b, c],
        ..Default::default()
    };
    let mut acc = [0.0f32; slot::LEN];
    for v in acc.iter_mut() {
        *v = (next() - 0.5) * 4.0;
    }
    if i.is_multiple_of(13) {
        acc = [0.0; slot::LEN]; // a Gaussian no pixel sent a gradient
    }
    (s, acc)
}

/// Every output of the block backward is the scalar reference's, bit for bit, lane by lane:
/// SH degrees 0 to 3, given colours, antialiasing on and off, full and partial blocks (whose
/// unused lanes hold another block's values).
#[test]
fn block_backward_gives_the_scalar_reference_bits() {
    use gauss_block::{block_backward, GradLanes, InLanes, BLOCK};
    use gauss_bwd::{gauss_backward, scales_into, GaussCtx};
    let cam = camera(120, 90);
    let n = 5 * BLOCK + 7;
    let mut checked = 0;
    for degree in 0..=3u8 {
        let s = odd_scene(n, 3, 40 + degree as u64);
        let view = s.view();
        let mut scales = Vec::new();
        scales_into(&s.log_scales, &mut scales);
        let mut next = rng(77 + degree as u64);
        let inputs: Vec<_> = (0..n).map(|i| odd_inputs(&mut next, i)).collect();
        let colors: Vec<f32> = (0..n * 3).map(|_| next()).collect();
        for antialiased in [false, true] {
            let ropts = RenderOptions {
                antialiased,
                ..Default::default()
            };
            let proj = Projector::new(&cam, &ropts, degree);
            for given in [false, true] {
                let ctx = GaussCtx {
                    proj: &proj,
                    scene: &view,
                    degree,
                    colors: given.then_some(&colors[..]),
                    pose: true,
                    scales: &scales,
                };
                let (mut g, mut o) = (InLanes::default(), GradLanes::default());
                // blocks of 16, then a partial block, then lanes in a shuffled order
                let order: Vec<usize> = (0..n).map(|k| (k * 37) % n).collect();
                for (b, idx) in order.chunks(BLOCK).enumerate() {
                    let idx: Vec<usize> = if b == 1 {
                        idx[..5].to_vec()
                    } else {
                        idx.to_vec()
                    };
                    for (l, &i) in idx.iter().enumerate() {
                        g.set(&ctx, l, i, &inputs[i].0, &inputs[i].1);
                    }
                    block_backward(&ctx, &g, &mut o);
                    for (l, &i) in idx.iter().enumerate() {
                        let r = gauss_backward(&ctx, i, &inputs[i].0, &inputs[i].1);
                        let lane = |v: &[[f32; BLOCK]]| v.iter().map(|x| x[l]).collect::<Vec<_>>();
                        let nb = (degree as usize + 1).pow(2);
                        let mut pairs: Vec<(&str, Vec<f32>, Vec<f32>)> = vec![
                            ("means", lane(&o.means), r.means.to_vec()),
                            ("quats", lane(&o.quats), r.quats.to_vec()),
                            ("log_scales", lane(&o.log_scales), r.log_scales.to_vec()),
                            ("logit", lane(&[o.opacity_logit]), vec![r.opacity_logit]),
                            ("scales", lane(&o.scales), r.scales.to_vec()),
                            ("opacity", lane(&[o.opacity]), vec![r.opacity]),
                            ("means2d", lane(&o.means2d), r.means2d.to_vec()),
                            ("means2d_abs", lane(&o.means2d_abs), r.means2d_abs.to_vec()),
                            ("conic", lane(&o.conic), r.conic.to_vec()),
                            ("rgb", lane(&o.rgb), r.rgb.to_vec()),
                            ("o_eff", lane(&[o.opacity_eff]), vec![r.opacity_eff]),
                            ("depth", lane(&[o.depth]), vec![r.depth]),
                            ("pose", lane(&o.pose), r.pose.to_vec()),
                        ];
                        if given {
                            pairs.push(("color", lane(&o.rgb), r.color.to_vec()));
                        } else {
                            for k in 0..nb {
                                pairs.push(("sh", lane(&o.sh[k]), r.sh[k].to_vec()));
                            }
                        }
                        for (name, got, want) in pairs {
                            assert!(
                                got.iter().zip(&want).all(|(a, b)| same(*a, *b)),
                                "{name} of Gaussian {i} (degree {degree}, aa {antialiased}, \
                                 colours {given}): {got:?} vs {want:?}"
                            );
                        }
                        checked += 1;
                    }
                }
            }
        }
    }
    assert_eq!(checked, 4 * 2 * 2 * (n - (BLOCK - 5)));
}

/// The whole backward's per-Gaussian outputs (parameter gradients, view gradients, the
/// camera gradient summed per part in index order) against the scalar reference applied to
/// the workspace's own summed slots, on a frame with thousands of visible Gaussians (so
/// several parts, partial last blocks), SH degree 2 and given colours, pose on, with each
/// build of the block code (AVX-512, AVX2, baseline: `simd`).
#[test]
fn backward_gives_the_scalar_reference_gradients() {
    for simd in [Simd::Avx512, Simd::Avx2, Simd::Scalar] {
        backward_matches_the_scalar_reference(simd);
    }
}

fn backward_matches_the_scalar_reference(simd: Simd) {
    use gauss_bwd::{gauss_backward, scales_into, GaussCtx, POSE_LEN};
    let cam = camera(112, 80);
    let s = scene(9000, 3, 21);
    let view = s.view();
    let colors: Vec<f32> = {
        let mut next = rng(5);
        (0..s.len() * 3).map(|_| next()).collect()
    };
    // SH degrees 0-3 (1 to 3 rows of 16 coefficients in the AVX-512 pass) and given colours
    for (given, degree) in [(false, 0u8), (false, 1), (false, 2), (false, 3), (true, 2)] {
        let opts = DiffOptions {
            render: RenderOptions {
                sh_degree: Some(degree),
                antialiased: given,
                simd,
                ..Default::default()
            },
            ..Default::default()
        };
        let cols = given.then_some(&colors[..]);
        let mut ws = Workspace::default();
        let npx = (cam.width * cam.height) as usize;
        let (mut rgb, mut depth, mut alpha) = (vec![0.0; npx * 3], vec![0.0; npx], vec![0.0; npx]);
        ws.forward(&view, &cam, &opts, cols, &mut rgb, &mut depth, &mut alpha)
            .expect("forward");
        let (r, d, a) = image_grads(&cam, 9);
        // gradients already holding values: the backward adds to them
        let prior = |g: &mut Gradients| {
            let mut next = rng(17);
            for v in [
                &mut g.means,
                &mut g.quats,
                &mut g.log_scales,
                &mut g.opacity_logits,
                &mut g.sh0,
                &mut g.sh_rest,
                &mut g.scales,
                &mut g.opacities,
                &mut g.colors,
            ] {
                v.iter_mut().for_each(|x| *x = next());
            }
        };
        let mut g = Gradients::default();
        g.reset(s.len(), s.sh_rest_k(), given);
        prior(&mut g);
        let mut vg = ViewGrads {
            viewmat: Some([0.0; 16]),
            ..Default::default()
        };
        let ig = ImageGrads {
            rgb: Some(&r),
            depth: Some(&d),
            alpha: Some(&a),
            skip_background: false,
        };
        ws.backward(&view, cols, &ig, &mut g, Some(&mut vg), None)
            .expect("backward");
        assert!(ws.parts.iter().filter(|p| !p.is_empty()).count() > 1);

        // the reference: the scalar function per visible Gaussian, in each part's order
        let proj = Projector::new(&cam, &opts.render, degree);
        let mut scales = Vec::new();
        scales_into(&s.log_scales, &mut scales);
        let ctx = GaussCtx {
            proj: &proj,
            scene: &view,
            degree,
            colors: cols,
            pose: true,
            scales: &scales,
        };
        let mut want = Gradients::default();
        want.reset(s.len(), s.sh_rest_k(), given);
        prior(&mut want);
        let mut sum = [0.0f64; POSE_LEN];
        let mut visible = 0;
        for (c, (ss, ids)) in ws.parts.iter().zip(&ws.part_ids).enumerate() {
            let mut part = [0.0f64; POSE_LEN];
            for (j, (sp, &i)) in ss.iter().zip(ids).enumerate() {
                let i = i as usize;
                let p = ws.pos[ws.part_off[c] + j] as usize;
                let q = gauss_backward(&ctx, i, sp, ws.sums().get(p));
                for (a, v) in part.iter_mut().zip(&q.pose) {
                    *a += *v as f64;
                }
                let add = |dst: &mut [f32], at: usize, v: &[f32]| {
                    for (k, x) in v.iter().enumerate() {
                        dst[at + k] += x;
                    }
                };
                add(&mut want.means, i * 3, &q.means);
                add(&mut want.quats, i * 4, &q.quats);
                add(&mut want.log_scales, i * 3, &q.log_scales);
                add(&mut want.opacity_logits, i, &[q.opacity_logit]);
                add(&mut want.scales, i * 3, &q.scales);
                add(&mut want.opacities, i, &[q.opacity]);
                if given {
                    add(&mut want.colors, i * 3, &q.color);
                } else {
                    add(&mut want.sh0, i * 3, &q.sh[0]);
                    for b in 1..(degree as usize + 1).pow(2) {
                        add(&mut want.sh_rest, (i * s.sh_rest_k() + b - 1) * 3, &q.sh[b]);
                    }
                }
                let v = |dst: &[f32], at: usize, x: &[f32]| {
                    assert!(dst[at..at + x.len()]
                        .iter()
                        .zip(x)
                        .all(|(a, b)| same(*a, *b)));
                };
                v(&vg.means2d, i * 2, &q.means2d);
                v(&vg.means2d_abs, i * 2, &q.means2d_abs);
                v(&vg.conics, i * 3, &q.conic);
                v(&vg.colors, i * 3, &q.rgb);
                v(&vg.opacities, i, &[q.opacity_eff]);
                v(&vg.depths, i, &[q.depth]);
                visible += 1;
            }
            for (a, v) in sum.iter_mut().zip(&part) {
                *a += v;
            }
        }
        assert!(visible > 1000, "{visible} visible");
        want.background = g.background;
        let bits = |g: &Gradients| {
            [
                &g.means,
                &g.quats,
                &g.log_scales,
                &g.opacity_logits,
                &g.sh0,
                &g.sh_rest,
                &g.scales,
                &g.opacities,
                &g.colors,
            ]
            .iter()
            .flat_map(|v| v.iter().map(|x| x.to_bits()))
            .collect::<Vec<_>>()
        };
        assert_eq!(
            bits(&g),
            bits(&want),
            "colours {given}, degree {degree}, {simd:?}"
        );
        let vm = viewmat_grad(&sum, &proj.rot, &proj.center);
        assert_eq!(
            vg.viewmat.map(|m| m.map(f64::to_bits)),
            Some(vm.map(f64::to_bits))
        );
    }
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
