//! End-to-end checks of the loop on a small synthetic scene fitted from its own renders.
use super::*;
use crate::camera::Camera;
use crate::raster::{render_into, RenderOptions};
use crate::scene::Scene;

/// A scene of `n` coloured Gaussians around the origin.
fn truth(n: usize) -> Scene {
    let (p, c) = init::random_points(n, [-1.0; 3], [1.0; 3], 11);
    let mut s = init::scene_from_points(&p, &c, 0.8, 1.0, 1).expect("scene");
    for v in &mut s.log_scales {
        *v = -2.8;
    }
    s
}

/// `k` cameras on a circle of radius 4 looking at the origin, w x h.
fn cameras(k: usize, w: u32, h: u32) -> Vec<Camera> {
    (0..k)
        .map(|i| {
            let a = i as f64 / k as f64 * std::f64::consts::TAU;
            let eye = [4.0 * a.cos(), 4.0 * a.sin(), 1.0];
            // look at the origin, z up (OpenCV axes: x right, y down, z forward)
            let f = {
                let n = (eye[0] * eye[0] + eye[1] * eye[1] + eye[2] * eye[2]).sqrt();
                [-eye[0] / n, -eye[1] / n, -eye[2] / n]
            };
            let up = [0.0, 0.0, 1.0];
            let mut r = [
                f[1] * up[2] - f[2] * up[1],
                f[2] * up[0] - f[0] * up[2],
                f[0] * up[1] - f[1] * up[0],
            ];
            let rn = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
            r = [r[0] / rn, r[1] / rn, r[2] / rn];
            let d = [
                f[1] * r[2] - f[2] * r[1],
                f[2] * r[0] - f[0] * r[2],
                f[0] * r[1] - f[1] * r[0],
            ];
            let rows = [r, d, f];
            let mut m = [[0.0; 4]; 4];
            for (i, row) in rows.iter().enumerate() {
                m[i][..3].copy_from_slice(row);
                m[i][3] = -(row[0] * eye[0] + row[1] * eye[1] + row[2] * eye[2]);
            }
            m[3][3] = 1.0;
            Camera::new(
                w as f64 * 0.9,
                w as f64 * 0.9,
                w as f64 / 2.0,
                h as f64 / 2.0,
                w,
                h,
                m,
            )
        })
        .collect()
}

fn views(s: &Scene, cams: &[Camera]) -> Vec<View> {
    cams.iter()
        .map(|c| {
            let npix = (c.width * c.height) as usize;
            let (mut rgb, mut d, mut a) = (vec![0.0; npix * 3], vec![0.0; npix], vec![0.0; npix]);
            render_into(
                &s.view(),
                c,
                &RenderOptions::default(),
                &mut rgb,
                &mut d,
                &mut a,
            )
            .expect("render");
            let img = rgb
                .iter()
                .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
                .collect();
            View::new(*c, img).expect("view")
        })
        .collect()
}

fn setup(strategy: Strategy) -> (FitConfig, Vec<View>, Vec<View>, Scene) {
    let gt = truth(400);
    let cams = cameras(20, 48, 36);
    let all = views(&gt, &cams);
    let (mut train, mut eval) = (Vec::new(), Vec::new());
    for (i, v) in all.into_iter().enumerate() {
        if i % 5 == 0 {
            eval.push(v);
        } else {
            train.push(v);
        }
    }
    let (p, c) = init::random_points(300, [-1.0; 3], [1.0; 3], 5);
    // gsplat's trainer: init_opa 0.1 (default), 0.5 (mcmc)
    let opacity = if matches!(strategy, Strategy::Mcmc(_)) {
        0.5
    } else {
        0.1
    };
    let init = init::scene_from_points(&p, &c, opacity, 1.0, 1).expect("init");
    let cfg = FitConfig {
        steps: 400,
        seed: 3,
        scene_scale: 4.4,
        sh_degree: 1,
        sh_degree_interval: 100,
        strategy,
        ..FitConfig::default()
    };
    (cfg, train, eval, init)
}

fn small_default() -> Strategy {
    Strategy::Default(DefaultStrategy {
        refine_start: 30,
        refine_every: 20,
        reset_every: 150,
        refine_stop: 300,
        ..DefaultStrategy::default()
    })
}

fn small_mcmc() -> Strategy {
    Strategy::Mcmc(McmcStrategy {
        cap_max: 500,
        refine_start: 30,
        refine_every: 20,
        ..McmcStrategy::default()
    })
}

struct Quiet;
impl Hooks for Quiet {
    fn event(&mut self, _e: Event<'_>) -> Flow {
        Flow::Continue
    }
}

fn mean_psnr(t: &mut Trainer) -> f64 {
    let e = t.evaluate(|_, _, _| {}).expect("eval");
    e.iter().map(|v| v.psnr).sum::<f64>() / e.len() as f64
}

#[test]
fn fitting_raises_held_out_psnr_with_both_strategies() {
    for strategy in [small_mcmc(), small_default()] {
        let (cfg, train, eval, init) = setup(strategy);
        let mut t = Trainer::new(cfg, train, eval, &init.view()).expect("trainer");
        let before = mean_psnr(&mut t);
        let opts = RunOptions {
            until: 400,
            ..RunOptions::default()
        };
        assert_eq!(
            run(&mut t, &opts, &mut Quiet).expect("run"),
            RunEnd::Finished
        );
        let after = mean_psnr(&mut t);
        assert!(
            after > before + 6.0 && after > 20.0,
            "{strategy:?}: {before} -> {after}"
        );
    }
}

#[test]
fn same_bits_for_any_thread_count_and_after_a_checkpoint() {
    for strategy in [small_default(), small_mcmc()] {
        let straight = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("pool")
                .install(|| {
                    let (cfg, train, eval, init) = setup(strategy);
                    let mut t = Trainer::new(cfg, train, eval, &init.view()).expect("trainer");
                    let opts = RunOptions {
                        until: 160,
                        ..RunOptions::default()
                    };
                    run(&mut t, &opts, &mut Quiet).expect("run");
                    t.params().clone()
                })
        };
        let one = straight(1);
        assert_eq!(one, straight(3), "{strategy:?}");
        // stop at 70 with a checkpoint, restore, finish
        let dir = tempfile::tempdir().expect("tmp");
        let path = dir.path().join("ck.bin");
        let (cfg, train, eval, init) = setup(strategy);
        let mut t = Trainer::new(cfg, train.clone(), eval.clone(), &init.view()).expect("trainer");
        let opts = RunOptions {
            until: 70,
            checkpoint: Some(path.clone()),
            fingerprint: b"x".to_vec(),
            ..RunOptions::default()
        };
        run(&mut t, &opts, &mut Quiet).expect("run");
        drop(t);
        let ck = checkpoint::load(&path, b"x").expect("load");
        assert_eq!(ck.step, 70);
        let mut t = Trainer::restore(cfg, train, eval, ck).expect("restore");
        let opts = RunOptions {
            until: 160,
            ..RunOptions::default()
        };
        run(&mut t, &opts, &mut Quiet).expect("run");
        assert_eq!(&one, t.params(), "{strategy:?} after a restore");
    }
}

#[test]
fn a_hook_stop_writes_a_checkpoint_and_returns() {
    struct StopAt(u32);
    impl Hooks for StopAt {
        fn event(&mut self, e: Event<'_>) -> Flow {
            match e {
                Event::Step(r) if r.step == self.0 => Flow::Stop,
                _ => Flow::Continue,
            }
        }
    }
    let (cfg, train, eval, init) = setup(small_default());
    let dir = tempfile::tempdir().expect("tmp");
    let path = dir.path().join("ck.bin");
    let mut t = Trainer::new(cfg, train, eval, &init.view()).expect("trainer");
    let opts = RunOptions {
        until: 100,
        checkpoint: Some(path.clone()),
        checkpoint_every: 1000,
        ..RunOptions::default()
    };
    assert_eq!(
        run(&mut t, &opts, &mut StopAt(17)).expect("run"),
        RunEnd::Stopped
    );
    assert_eq!(checkpoint::load(&path, b"").expect("load").step, 17);
}
