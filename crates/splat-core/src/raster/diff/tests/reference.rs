//! The per-Gaussian backward against its scalar reference (`gauss_bwd::gauss_backward`): the
//! block code lane by lane, and a whole backward's per-Gaussian outputs, bit for bit.
use super::*;
use crate::raster::diff::gauss_bwd::viewmat_grad;

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
