use super::*;
use crate::raster::sort::TileBins;

/// A frozen frame (what `blend_1thread` times) blends to the bits and evaluation count of
/// a render of the same frame, with every kernel this CPU has, with and without depth
/// (40,000 Gaussians: several binning chunks, so several lists per tile, as grid-5 has).
/// The explicit kernels' stream across the lists' ends is held to the generic kernel by
/// `explicit_kernels_give_the_generic_kernels_bits_tile_by_tile` (two chunks there).
#[test]
fn frozen_frame_blends_as_a_render() {
    use crate::camera::Camera;
    use crate::raster::{render_into, RenderOptions, Simd};
    let s = crate::raster::tests::cloud(40_000, 0x9e37_79b9, -4.0);
    let mut m = [[0.0; 4]; 4];
    for (i, row) in m.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    m[2][3] = 4.0;
    let cam = Camera::new(300.0, 300.0, 100.0, 70.0, 200, 140, m);
    let n = 200 * 140;
    let mut levels = vec![Simd::Scalar];
    for simd in [Simd::Avx2, Simd::Avx512] {
        if simd.resolve() == simd {
            levels.push(simd);
        }
    }
    for simd in levels {
        let opts = RenderOptions {
            simd,
            ..Default::default()
        };
        let (mut rgb, mut depth, mut alpha) = (vec![0.0; n * 3], vec![0.0; n], vec![0.0; n]);
        let st =
            render_into(&s.view(), &cam, &opts, &mut rgb, &mut depth, &mut alpha).expect("render");
        assert!(st.visible > 2 * TileBins::CHUNK as u64, "{}", st.visible);
        let frame = FrozenFrame::new(&s.view(), &cam, &opts).expect("frame");
        let (mut rgb2, mut depth2, mut alpha2) = (vec![1.0; n * 3], vec![1.0; n], vec![1.0; n]);
        let (evals, _) = frame.blend(&mut rgb2, &mut depth2, &mut alpha2, true);
        assert_eq!(evals, st.evaluations, "{simd:?}");
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&rgb2), bits(&rgb), "{simd:?}");
        assert_eq!(bits(&depth2), bits(&depth), "{simd:?}");
        assert_eq!(bits(&alpha2), bits(&alpha), "{simd:?}");
        // without depth: the same colour and alpha, the depth image untouched
        let (mut rgb3, mut alpha3) = (vec![1.0; n * 3], vec![1.0; n]);
        let mut none = vec![7.0f32; n];
        frame.blend(&mut rgb3, &mut none, &mut alpha3, false);
        assert_eq!(bits(&rgb3), bits(&rgb), "{simd:?}");
        assert_eq!(bits(&alpha3), bits(&alpha), "{simd:?}");
        assert!(none.iter().all(|&v| v == 7.0));
    }
}

#[test]
fn opacity_exp_matches_float64() {
    let mut worst = 0.0f64;
    for ln_op in [0.0f32, -0.1, -1.0, -5.54] {
        for i in 0..200_000 {
            let sigma = i as f32 * 4e-4;
            // the exponential of the float32 argument u = sigma - ln_op (rounding u costs
            // up to |u| 6e-8 more, as rounding sigma itself does)
            let want = (-((sigma - ln_op) as f64)).exp();
            for got in [
                opacity_exp::<true>(sigma, ln_op),
                opacity_exp::<false>(sigma, ln_op),
            ] {
                let rel = (got as f64 - want).abs() / want;
                worst = worst.max(rel);
                assert!(rel < 3e-7, "exp({ln_op} - {sigma}): {got} vs {want}");
            }
        }
    }
    eprintln!("worst relative error {worst:.2e}");
    assert_eq!(opacity_exp::<true>(0.0, 0.0), 1.0);
    // negative, NaN and huge sigma give an alpha far below the threshold
    for sigma in [-1e-9, -1.0, f32::NAN, 1e9, f32::INFINITY] {
        assert!(opacity_exp::<true>(sigma, 0.0) < 1e-30, "{sigma}");
    }
    for j in 0..16 {
        let v = f32::from_bits(EXP2_16THS[j]);
        let exact = 2f64.powf(j as f64 / 16.0);
        assert!((v as f64 - exact).abs() <= f32::EPSILON as f64 * 0.5 * exact);
    }
}
