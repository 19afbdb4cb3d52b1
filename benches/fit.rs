//! Criterion benchmarks of `morphgs fit`'s hot paths on gsplat's profiling scene (the garden,
//! 648x420, benches/garden): the loss with its gradient (L1 + SSIM), one Adam step over every
//! parameter of the garden-sized initial scene, and one whole training step (forward, loss,
//! backward, Adam) of a fit initialised from the garden points (3-NN scales, opacity 0.1,
//! SH degree 3 stored, degree 0 in use) against renders of the garden scene; and the MCMC
//! strategy's per-step passes (position noise, regularisers) over the same Gaussians.
//!
//!     cargo bench -p splat-core --bench fit
use criterion::{criterion_group, criterion_main, BatchSize, Criterion, Throughput};
use splat_core::camera::Camera;
use splat_core::fit::config::McmcStrategy;
use splat_core::fit::loss::LossWorkspace;
use splat_core::fit::mcmc;
use splat_core::fit::params::{AdamParams, Params, GROUPS};
use splat_core::fit::{init, FitConfig, Trainer, View};
use splat_core::raster::{render_into, RenderOptions};
use splat_core::scene::SH_C0;
use splat_core::Scene;

#[allow(dead_code)] // the shared module also holds helpers other benches use
mod garden;
use garden::garden;

fn render_u8(scene: &Scene, cam: &Camera) -> Vec<u8> {
    let n = cam.width as usize * cam.height as usize;
    let (mut rgb, mut d, mut a) = (vec![0.0; n * 3], vec![0.0; n], vec![0.0; n]);
    render_into(
        &scene.view(),
        cam,
        &RenderOptions::default(),
        &mut rgb,
        &mut d,
        &mut a,
    )
    .expect("render");
    rgb.iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect()
}

/// The fit's starting point: the garden points as INRIA initialises them.
fn initial(gt: &Scene) -> Scene {
    let colors: Vec<f32> = gt.sh0.iter().map(|v| 0.5 + SH_C0 * v).collect();
    init::scene_from_points(&gt.means, &colors, 0.1, 1.0, 3).expect("init")
}

fn bench_fit(c: &mut Criterion) {
    let (gt, cams) = garden(1);
    let cam = cams[0];
    let (w, h) = (cam.width as usize, cam.height as usize);
    let threads = rayon::current_num_threads();
    let mut g = c.benchmark_group("fit_garden_648x420");
    g.sample_size(20);

    // the loss of a render of the initial scene against the garden render
    let start = initial(&gt);
    let target: Vec<f32> = render_u8(&gt, &cam)
        .iter()
        .map(|&v| v as f32 / 255.0)
        .collect();
    let pred: Vec<f32> = render_u8(&start, &cam)
        .iter()
        .map(|&v| v as f32 / 255.0)
        .collect();
    let mut ws = LossWorkspace::default();
    let mut grad = vec![0.0f32; w * h * 3];
    g.throughput(Throughput::Elements((w * h) as u64));
    g.bench_function(format!("loss_l1_ssim_grad_{threads}threads"), |b| {
        b.iter(|| ws.loss_and_grad(&pred, &target, w, h, 0.2, &mut grad))
    });

    // Adam over every array of the 111,785-Gaussian SH-3 scene (59 values each)
    let mut p = Params::from_view(&start.view());
    // (the step zeroes the gradients it reads: each iteration gets fresh ones, outside the
    // timed part)
    let grads: Vec<Vec<f32>> = p.groups.iter().map(|q| vec![1e-3; q.value.len()]).collect();
    let adam = AdamParams::default();
    let mut t = 0u64;
    g.throughput(Throughput::Elements(start.len() as u64));
    g.bench_function(format!("adam_all_bands_{threads}threads"), |b| {
        b.iter_batched_ref(
            || grads.clone(),
            |gs| {
                t += 1;
                let mut it = gs.iter_mut();
                let gref: [&mut [f32]; GROUPS] =
                    std::array::from_fn(|_| &mut it.next().expect("group")[..]);
                p.adam_step(gref, [1e-3; GROUPS], t, &adam, 3)
            },
            BatchSize::LargeInput,
        )
    });

    // whole training steps: the 3 garden views as the training images
    let views: Vec<View> = cams
        .iter()
        .map(|c| View::new(*c, render_u8(&gt, c)).expect("view"))
        .collect();
    let cfg = FitConfig {
        steps: 30_000,
        scene_scale: 3.0,
        ..FitConfig::default()
    };
    let mut trainer = Trainer::new(cfg, views, Vec::new(), &start.view()).expect("trainer");
    let rec = trainer.step_once().expect("step");
    println!(
        "garden step ({threads} threads): {:.1} ms = forward {:.1} + loss {:.1} + backward {:.1} + adam {:.1} + strategy {:.1}",
        rec.seconds * 1e3,
        rec.forward_s * 1e3,
        rec.loss_s * 1e3,
        rec.backward_s * 1e3,
        rec.adam_s * 1e3,
        rec.strategy_s * 1e3
    );
    g.throughput(Throughput::Elements(1));
    g.bench_function(format!("train_step_{threads}threads"), |b| {
        b.iter(|| trainer.step_once().expect("step"))
    });

    // the MCMC strategy's work at every step over the 111,785 Gaussians: the position noise
    // (outside its refine steps) and the regularisers' gradients
    let mcmc = McmcStrategy::default();
    let mut p = Params::from_view(&start.view());
    let mut step = 1u32;
    g.throughput(Throughput::Elements(start.len() as u64));
    g.bench_function(format!("mcmc_noise_{threads}threads"), |b| {
        b.iter(|| {
            step += 2; // odd: never a refine step
            mcmc::post_step(&mcmc, &mut p, step, 1.6e-4, 0)
        })
    });
    let (mut go, mut gs) = (vec![0.0f32; start.len()], vec![0.0f32; 3 * start.len()]);
    g.bench_function(format!("mcmc_regularisers_{threads}threads"), |b| {
        b.iter(|| mcmc::add_regularisers(&mcmc, &p, &mut go, &mut gs))
    });
    g.finish();
}

criterion_group!(benches, bench_fit);
criterion_main!(benches);
