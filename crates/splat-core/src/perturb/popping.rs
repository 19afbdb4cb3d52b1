//! Popping (issue 36): visibility that flips along a clip, as in 3DGS fits from a few views.
//!
//! In a sparse fit, large, nearly opaque Gaussians overlap where few views constrain them. The
//! rasterizer sorts by centre depth, so as the camera moves two overlapping splats swap order
//! abruptly; with opaque splats the one that goes behind vanishes from the frame. And the
//! view-dependent opacity and colour such a fit learns are pinned at its training views only,
//! so between them a Gaussian may switch off. Both are a Gaussian that disappears for a range
//! of viewing directions between training views and comes back at the next one.
//!
//! Here each selected Gaussian gets a cap ([`crate::raster::caps`]): hidden iff the direction
//! from the camera to it lies within a cone around a seeded axis `a`. The axis points at the
//! Gaussian from an anchor between two consecutive training cameras (the cameras are in path
//! order: a regime's every K-th view), so the path between them crosses the cone: the Gaussian
//! pops out and back in. The cone's chord radius is `rho` (uniform in [`CAP_RATIO`]) times the
//! chord distance from `a` to the nearest training direction, so **no training view hides
//! anything**: a sparse fit reproduces its training views. Visibility is a function of the
//! camera centre, so a revisited view renders the same frame.
//!
//! Which Gaussians pop: Gaussian `i` with opacity `alpha_i` and largest scale `r_i` has weight
//! `w_i = alpha_i * 2 r_i / (r_i + r_med)` (`r_med` the scene's median largest scale; `w` in
//! [0, 2): a median-sized opaque Gaussian has weight 1) and is selected iff
//! `u_i < 1 - (1 - p)^w_i` for the op's fraction `p`: large, opaque Gaussians pop, faint and
//! small ones (whose popping would not show) rarely do, and a larger `p` selects a superset.
//!
//! Every draw is keyed by `(seed, OP_POPPING, row)`; the median is a selection on exact values;
//! only exactly rounded operations are used: the same bits for any thread count and CPU.
use rayon::prelude::*;

use super::CHUNK;
use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::fastmath;
use crate::raster::caps::{centre, direction};
use crate::rng::{normal_pair, op_key, Stream};
use crate::scene::SceneView;

/// Op id of the popping caps.
pub const OP_POPPING: u32 = 15;
/// The range of a cap's chord radius over the chord distance from its axis to the nearest
/// training direction (below 1: every training direction stays outside the cap).
pub const CAP_RATIO: (f32, f32) = (0.4, 0.95);
/// Where between its two training cameras a cap's anchor lies (a fraction of the way).
pub const ANCHOR: (f32, f32) = (0.2, 0.8);
/// No cap when every training direction is within this of the axis in `1 - cos` (a Gaussian
/// seen from one direction only: far away, or a static path).
pub const MIN_SPREAD: f32 = 1e-4;

/// The popping caps of every row of `view`: `(axis x, y, z, h)`, each one value per Gaussian
/// (`h = 0`: never hidden), for the scene extras [`crate::raster::caps::EXTRAS`].
///
/// `fraction` is `p` (in [0, 1]); `cameras` the training cameras in path order.
///
/// Errors: [`Error::InvalidArgument`] for a fraction outside [0, 1] or no cameras.
pub fn caps(
    view: &SceneView<'_>,
    cameras: &[Camera],
    fraction: f32,
    seed: u64,
) -> Result<[Vec<f32>; 4]> {
    view.validate()?;
    if !(0.0..=1.0).contains(&fraction) {
        return Err(Error::InvalidArgument(format!(
            "popping must be a fraction in [0, 1], got {fraction}"
        )));
    }
    if cameras.is_empty() {
        return Err(Error::InvalidArgument(
            "popping needs training cameras (none given)".into(),
        ));
    }
    let n = view.len();
    let centres: Vec<[f32; 3]> = cameras.iter().map(centre).collect();
    let plan = Plan {
        key: op_key(seed, OP_POPPING),
        centres,
        log_keep: if fraction < 1.0 {
            fastmath::ln(1.0 - fraction)
        } else {
            f32::NEG_INFINITY
        },
        on: fraction > 0.0,
        median: median_log_radius(view),
    };
    let mut out = [vec![0f32; n], vec![0f32; n], vec![0f32; n], vec![0f32; n]];
    let [x, y, z, h] = &mut out;
    (
        x.par_chunks_mut(CHUNK),
        y.par_chunks_mut(CHUNK),
        z.par_chunks_mut(CHUNK),
        h.par_chunks_mut(CHUNK),
    )
        .into_par_iter()
        .enumerate()
        .for_each(|(c, (x, y, z, h))| {
            for l in 0..h.len() {
                if let Some((a, hi)) = plan.cap(view, c * CHUNK + l) {
                    (x[l], y[l], z[l], h[l]) = (a[0], a[1], a[2], hi);
                }
            }
        });
    Ok(out)
}

/// The largest log scale of a Gaussian.
fn log_radius(view: &SceneView<'_>, i: usize) -> f32 {
    let s = &view.log_scales[i * 3..i * 3 + 3];
    s[0].max(s[1]).max(s[2])
}

/// The median of the finite largest log scales (the upper one of an even count; 0 for none).
fn median_log_radius(view: &SceneView<'_>) -> f32 {
    let mut r: Vec<f32> = (0..view.len())
        .map(|i| log_radius(view, i))
        .filter(|v| v.is_finite())
        .collect();
    if r.is_empty() {
        return 0.0;
    }
    let k = r.len() / 2;
    *r.select_nth_unstable_by(k, f32::total_cmp).1
}

struct Plan {
    key: u64,
    centres: Vec<[f32; 3]>,
    log_keep: f32,
    on: bool,
    median: f32,
}

impl Plan {
    /// Gaussian `i`'s cap (axis, height), or None when it does not pop.
    fn cap(&self, view: &SceneView<'_>, i: usize) -> Option<([f32; 3], f32)> {
        if !self.on {
            return None;
        }
        let s = Stream::new(self.key, i as u64);
        let u = |w: u64| (s.word(w) >> 40) as f32 * (1.0 / 16_777_216.0);
        let logit = view.opacity_logits[i];
        let alpha = 1.0 / (1.0 + fastmath::exp(-logit));
        let size = 2.0 / (1.0 + fastmath::exp(self.median - log_radius(view, i)));
        let w = alpha * size;
        if !(w.is_finite() && w > 0.0) {
            return None;
        }
        // selected with probability 1 - (1 - p)^w (1 at p = 1)
        let p = 1.0 - fastmath::exp(w * self.log_keep);
        if u(0) >= p {
            return None;
        }
        let mu = [
            view.means[i * 3],
            view.means[i * 3 + 1],
            view.means[i * 3 + 2],
        ];
        if !mu.iter().all(|v| v.is_finite()) {
            return None;
        }
        let cams = &self.centres;
        let k = cams.len();
        let axis = if k >= 2 {
            // an anchor on segment j of the path of training cameras (the last one continues
            // past the last camera, where a clip goes on after its last training view)
            let j = ((u(1) * k as f32) as usize).min(k - 1);
            let t = ANCHOR.0 + u(2) * (ANCHOR.1 - ANCHOR.0);
            let (a, b) = if j + 1 < k {
                (cams[j], cams[j + 1])
            } else {
                (
                    cams[k - 1],
                    [0, 1, 2].map(|d| 2.0 * cams[k - 1][d] - cams[k - 2][d]),
                )
            };
            let anchor = [0, 1, 2].map(|d| a[d] + t * (b[d] - a[d]));
            direction(anchor, mu)?
        } else {
            let (a, b) = normal_pair(s.word(3));
            let c = normal_pair(s.word(4)).0;
            direction([0.0; 3], [a, b, c])?
        };
        // the nearest training direction, as 1 - cos (half the squared chord)
        let spread = cams
            .iter()
            .filter_map(|&c| direction(c, mu))
            .map(|d| 1.0 - (d[0] * axis[0] + d[1] * axis[1] + d[2] * axis[2]))
            .fold(f32::INFINITY, f32::min);
        if !spread.is_finite() || spread < MIN_SPREAD {
            return None; // also a Gaussian at every training camera (no direction)
        }
        let rho = CAP_RATIO.0 + u(5) * (CAP_RATIO.1 - CAP_RATIO.0);
        Some((axis, (rho * rho * spread).min(2.0)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raster::caps::Caps;
    use crate::scene::Scene;

    /// `n` Gaussians in a 4-unit cube around the origin, log scales in [-4, -1], logits in
    /// [-3, 3] (from the counter-based generator, seed 99).
    fn scene(n: usize) -> Scene {
        let s = |i: usize, op: u32, w: u64| {
            let st = Stream::new(op_key(99, op), i as u64);
            (st.word(w) >> 40) as f32 / 16_777_216.0
        };
        Scene {
            means: (0..n * 3)
                .map(|t| s(t / 3, 1, (t % 3) as u64) * 4.0 - 2.0)
                .collect(),
            quats: (0..n).flat_map(|_| [1.0, 0.0, 0.0, 0.0]).collect(),
            log_scales: (0..n * 3)
                .map(|t| s(t / 3, 3, (t % 3) as u64) * 3.0 - 4.0)
                .collect(),
            opacity_logits: (0..n).map(|i| s(i, 4, 0) * 6.0 - 3.0).collect(),
            sh0: vec![0.0; n * 3],
            sh_rest: vec![],
            sh_degree: 0,
            extras: vec![],
        }
    }

    /// A camera at `eye` looking at the origin (the world z up).
    fn camera(eye: [f64; 3]) -> Camera {
        let n = (eye[0] * eye[0] + eye[1] * eye[1] + eye[2] * eye[2]).sqrt();
        let f = eye.map(|v| -v / n);
        let cross = |a: [f64; 3], b: [f64; 3]| {
            [
                a[1] * b[2] - a[2] * b[1],
                a[2] * b[0] - a[0] * b[2],
                a[0] * b[1] - a[1] * b[0],
            ]
        };
        let r = cross(f, [0.0, 0.0, 1.0]);
        let rn = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
        let x = r.map(|v| v / rn);
        let y = cross(f, x);
        let rows = [x, y, f];
        let mut m = [[0.0; 4]; 4];
        for i in 0..3 {
            m[i][..3].copy_from_slice(&rows[i]);
            m[i][3] = -(rows[i][0] * eye[0] + rows[i][1] * eye[1] + rows[i][2] * eye[2]);
        }
        m[3][3] = 1.0;
        Camera::new(60.0, 60.0, 32.0, 24.0, 64, 48, m)
    }

    /// A 32-view orbit of radius 8 at height 1; the training cameras are every 8th.
    fn path() -> Vec<Camera> {
        (0..32)
            .map(|k| {
                let a = k as f64 * 300f64.to_radians() / 31.0;
                camera([8.0 * a.cos(), 8.0 * a.sin(), 1.0])
            })
            .collect()
    }

    fn run(s: &Scene, p: f32, seed: u64, threads: usize) -> [Vec<f32>; 4] {
        let train: Vec<Camera> = path().into_iter().step_by(8).collect();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool");
        pool.install(|| caps(&s.view(), &train, p, seed).expect("caps"))
    }

    fn bits(c: &[Vec<f32>; 4]) -> Vec<u32> {
        c.iter().flatten().map(|v| v.to_bits()).collect()
    }

    #[test]
    fn the_same_bits_for_any_thread_count_and_supersets_as_the_fraction_grows() {
        let s = scene(3 * CHUNK + 17);
        let a = run(&s, 0.3, 7, 1);
        for threads in [2, 8] {
            assert_eq!(
                bits(&a),
                bits(&run(&s, 0.3, 7, threads)),
                "{threads} threads"
            );
        }
        assert_ne!(bits(&a), bits(&run(&s, 0.3, 8, 2)), "another seed");
        let hi = run(&s, 0.6, 7, 2);
        let on = |c: &[Vec<f32>; 4], i: usize| c[3][i] > 0.0;
        let (mut lo_n, mut hi_n) = (0, 0);
        for i in 0..s.len() {
            assert!(!on(&a, i) || on(&hi, i), "{i} lost its cap");
            if on(&a, i) {
                // the same cap: the axis and height do not depend on the fraction
                assert_eq!((a[0][i], a[3][i]), (hi[0][i], hi[3][i]));
            }
            lo_n += usize::from(on(&a, i));
            hi_n += usize::from(on(&hi, i));
        }
        assert!(lo_n > s.len() / 20 && hi_n > lo_n, "{lo_n} {hi_n}");
        assert!(run(&s, 0.0, 7, 2)[3].iter().all(|&h| h == 0.0));
    }

    #[test]
    fn large_opaque_gaussians_pop_more_often() {
        let s = scene(20000);
        let c = run(&s, 0.3, 3, 2);
        let w: Vec<(f32, bool)> = (0..s.len())
            .map(|i| {
                let alpha = 1.0 / (1.0 + (-s.opacity_logits[i]).exp());
                (alpha * log_radius(&s.view(), i).exp(), c[3][i] > 0.0)
            })
            .collect();
        let mut sorted: Vec<f32> = w.iter().map(|x| x.0).collect();
        sorted.sort_by(f32::total_cmp);
        let (q1, q3) = (sorted[s.len() / 4], sorted[3 * s.len() / 4]);
        let share = |f: &dyn Fn(f32) -> bool| {
            let sel: Vec<bool> = w.iter().filter(|x| f(x.0)).map(|x| x.1).collect();
            sel.iter().filter(|&&b| b).count() as f64 / sel.len() as f64
        };
        let (small, large) = (share(&|v| v < q1), share(&|v| v > q3));
        assert!(
            large > 2.0 * small,
            "small faint {small}, large opaque {large}"
        );
    }

    #[test]
    fn no_training_view_hides_anything_and_the_path_between_them_does() {
        let s = scene(5000);
        let c = run(&s, 0.5, 11, 2);
        let caps = Caps::of(&c[0], &c[1], &c[2], &c[3]);
        caps.validate(s.len()).expect("valid caps");
        let view = s.view();
        let hidden: Vec<usize> = path()
            .iter()
            .map(|cam| caps.hidden_count(&view, centre(cam)))
            .collect();
        for (k, &n) in hidden.iter().enumerate() {
            if k % 8 == 0 {
                assert_eq!(n, 0, "training view {k} hides {n}");
            }
        }
        let between: usize = hidden.iter().sum();
        let selected = c[3].iter().filter(|&&h| h > 0.0).count();
        assert!(
            between > selected,
            "{between} hidden Gaussian-frames for {selected} caps: {hidden:?}"
        );
    }

    #[test]
    fn bad_fractions_and_missing_cameras_are_named() {
        let s = scene(10);
        let e = caps(&s.view(), &path(), 1.5, 0).expect_err("fraction");
        assert!(e.to_string().contains("popping"), "{e}");
        let e = caps(&s.view(), &[], 0.5, 0).expect_err("cameras");
        assert!(e.to_string().contains("training cameras"), "{e}");
    }
}
