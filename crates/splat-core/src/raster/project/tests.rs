use super::block::Lanes;
#[cfg(target_arch = "x86_64")]
use super::block::{deinterleave, transpose, Rows, BLOCK};
#[cfg(target_arch = "x86_64")]
use super::block_avx512 as avx512;
use super::{Projector, Splat};
use crate::camera::Camera;
use crate::fastmath;
use crate::raster::share::{self, ChunkColours};
use crate::raster::{sh, RenderOptions, Simd};
use crate::scene::SceneView;
use crate::Scene;

/// A cloud around and behind a camera at the origin looking down +z, with the hard cases
/// mixed in: non-finite values in every field, zero quaternions, tiny and huge scales,
/// opacities around the cull, Gaussians behind the camera and far off-screen.
fn scene(n: usize, degree: u8) -> Scene {
    let mut s = Scene::empty(degree);
    let k = s.sh_rest_k() * 3;
    let mut h = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = || {
        h ^= h << 13;
        h ^= h >> 7;
        h ^= h << 17;
        (h >> 40) as f32 / (1u64 << 24) as f32
    };
    for i in 0..n {
        s.means
            .extend([next() * 8.0 - 4.0, next() * 6.0 - 3.0, next() * 12.0 - 2.0]);
        s.quats
            .extend([next() - 0.5, next() - 0.5, next() - 0.5, next() - 0.5]);
        let big = if i % 97 == 0 { 4.0 } else { 0.0 };
        s.log_scales.extend([
            -6.0 + 5.0 * next() + big,
            -6.0 + 5.0 * next(),
            -6.0 + 5.0 * next(),
        ]);
        s.opacity_logits.push(next() * 16.0 - 8.0);
        s.sh0.extend([next() - 0.5, next() - 0.5, next() - 0.5]);
        s.sh_rest.extend((0..k).map(|_| next() - 0.5));
    }
    for (j, field) in (0..n).step_by(53).zip(0..) {
        match field % 6 {
            0 => s.means[j * 3 + 1] = f32::NAN,
            1 => s.quats[j * 4..j * 4 + 4].fill(0.0),
            2 => s.log_scales[j * 3 + 2] = f32::INFINITY,
            3 => s.opacity_logits[j] = f32::NAN,
            4 => s.sh0[j * 3] = f32::NEG_INFINITY,
            _ if k > 0 => s.sh_rest[j * k + k - 1] = f32::NAN,
            _ => s.quats[j * 4] = f32::NAN,
        }
    }
    s
}

fn bits(v: &[Splat]) -> Vec<u32> {
    v.iter()
        .flat_map(|s| {
            let mut f = vec![s.xy[0], s.xy[1], s.ln_opacity, s.depth];
            f.extend(s.conic.iter().chain(&s.rgb).chain(&s.radius));
            f.extend([s.two_a_level, s.conic_det, s.inv_a, s.half_height]);
            f.into_iter().map(f32::to_bits)
        })
        .collect()
}

/// The projection of one Gaussian as the code before the vectorised stage 3 computed it
/// (stages 1 and 2 in a one-lane block, then the colour and the splat per Gaussian, in
/// scalar code): the reference the block code must match bit for bit.
fn reference(proj: &Projector, scene: &SceneView<'_>, i: usize) -> Option<Splat> {
    let mut g = Lanes::default();
    g.set(0, scene, i);
    let sc = proj.screen(&g);
    let fp = proj.footprint(&g, &sc);
    if !(sc.ok[0] && fp.ok[0]) {
        return None;
    }
    let (l, q) = (0, &scene.quats[i * 4..i * 4 + 4]);
    let mean = &scene.means[i * 3..i * 3 + 3];
    let (dir, _) = proj.view_dir([mean[0], mean[1], mean[2]]);
    let k = scene.sh_rest_k() * 3;
    let rest = &scene.sh_rest[i * k..i * k + k];
    if !rest.iter().chain(q).all(|v| v.is_finite()) {
        return None;
    }
    let rgb = sh::color(proj.sh_degree, dir, &scene.sh0[i * 3..i * 3 + 3], rest);
    let conic = [fp.conic[0][l], fp.conic[1][l], fp.conic[2][l]];
    let level = fp.ln_over[l] * 1.0001 + 1e-4;
    let s = Splat {
        xy: [sc.xy[0][l], sc.xy[1][l]],
        conic,
        ln_opacity: fastmath::ln(fp.opacity[l]),
        rgb,
        depth: sc.z[l],
        radius: [fp.radius[0][l], fp.radius[1][l]],
        two_a_level: 2.0 * conic[0] * level,
        conic_det: conic[0] * conic[2] - conic[1] * conic[1],
        inv_a: 1.0 / conic[0],
        half_height: (2.0 * level * fp.c11[l]).sqrt(),
    };
    bits(&[s])
        .iter()
        .all(|b| b & 0x7FFF_FFFF < 0x7F80_0000)
        .then_some(s)
}

/// Blocks of 16 with survivor compaction and the vectorised stage 3, in every build
/// (AVX-512, AVX2, plain: `RenderOptions::simd` picks it), give the reference's splats bit
/// for bit, whatever the neighbours in a block: SH degrees 0-3 (and degree 0 rendered from
/// a degree-3 scene), antialiasing on and off, Gaussians behind the camera, beyond a far
/// plane, clamped to the frustum, culled by opacity and with non-finite values in every
/// field; the one-Gaussian path and the recorded shared colours agree too.
#[test]
fn vectorised_range_gives_the_reference_splats_bit_for_bit() {
    let mut m = [[0.0; 4]; 4];
    for (i, row) in m.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    let near = Camera::new(300.0, 280.0, 160.0, 110.0, 333, 217, m);
    let far = Camera { far: 6.5, ..near };
    for (scene_degree, degree) in [(0, 0), (1, 1), (2, 2), (3, 3), (3, 0)] {
        let s = scene(5000, scene_degree);
        let view = s.view();
        for (cam, antialiased) in [(near, false), (near, true), (far, false)] {
            let want_proj = Projector::new(
                &cam,
                &RenderOptions {
                    antialiased,
                    ..Default::default()
                },
                degree,
            );
            let want: Vec<Splat> = (0..s.len())
                .filter_map(|i| reference(&want_proj, &view, i))
                .collect();
            assert!(want.len() > 500 && want.len() < 4500, "{}", want.len());
            let one: Vec<Splat> = (0..s.len())
                .filter_map(|i| want_proj.project_with_opacity(&view, i).map(|p| p.0))
                .collect();
            assert_eq!(bits(&one), bits(&want), "degree {degree}, one by one");
            for simd in [Simd::Avx512, Simd::Avx2, Simd::Scalar] {
                if simd.resolve() != simd {
                    continue;
                }
                let opts = RenderOptions {
                    antialiased,
                    simd,
                    ..Default::default()
                };
                let proj = Projector::new(&cam, &opts, degree);
                // ranges that start and end inside 16-Gaussian blocks
                let ranges = [(0, 7), (7, 1000), (1000, 4093), (4093, 5000)];
                let mut got = Vec::new();
                let mut ids = Vec::new();
                let mut slots = share::slots(s.len());
                for (lo, hi) in ranges {
                    let mut cc = ChunkColours::Record(&mut slots[lo..hi], lo, 7);
                    proj.project_range(&view, lo, hi, &mut got, Some(&mut ids), &mut cc);
                }
                let what = format!("degree {degree}/{scene_degree}, {}", simd.name());
                assert_eq!(bits(&got), bits(&want), "{what}");
                // the indices, and every visible Gaussian's colour recorded
                let want_ids: Vec<u32> = (0..s.len() as u32)
                    .filter(|&i| reference(&want_proj, &view, i as usize).is_some())
                    .collect();
                assert_eq!(ids, want_ids, "{what}");
                for (sp, &i) in got.iter().zip(&ids) {
                    let slot = slots[i as usize];
                    assert_eq!(slot[3], 7, "{what}");
                    assert_eq!(&slot[..3], &sp.rgb.map(f32::to_bits), "{what}");
                }
            }
        }
    }
}

/// The AVX-512 transposition of splat lanes into rows is the plain one.
#[cfg(target_arch = "x86_64")]
#[test]
fn avx512_transpose_is_the_plain_one() {
    if Simd::Avx512.resolve() != Simd::Avx512 {
        return;
    }
    let f: [[f32; BLOCK]; 16] =
        std::array::from_fn(|c| std::array::from_fn(|l| (c * 100 + l) as f32));
    let (mut want, mut got) = (Rows([[0.0; 16]; BLOCK]), Rows([[0.0; 16]; BLOCK]));
    transpose(&f, &mut want);
    // SAFETY: the CPU has AVX-512 (checked above).
    unsafe { avx512::transpose(&f, &mut got) };
    assert_eq!(got.0, want.0);
}

/// The AVX-512 loads of a full block into lanes are the plain ones (1, 3 and 4 values per
/// Gaussian, at an offset).
#[cfg(target_arch = "x86_64")]
#[test]
fn avx512_deinterleave_is_the_plain_one() {
    if Simd::Avx512.resolve() != Simd::Avx512 {
        return;
    }
    let src: Vec<f32> = (0..200).map(|v| v as f32 * 0.5 - 7.0).collect();
    fn both<const C: usize>(src: &[f32]) {
        let (mut want, mut got) = ([[0.0; BLOCK]; C], [[0.0; BLOCK]; C]);
        deinterleave::<false, C>(src, 3, BLOCK, &mut want);
        deinterleave::<true, C>(src, 3, BLOCK, &mut got);
        assert_eq!(got, want, "{C} values");
        assert_eq!(want[C - 1][BLOCK - 1], src[(3 + BLOCK) * C - 1]);
    }
    both::<1>(&src);
    both::<3>(&src);
    both::<4>(&src);
}
