//! Criterion benchmarks of the differentiable rasterizer: forward with saved state plus backward
//! (all parameter gradients and the densification statistics) of the garden frame (648x420,
//! gsplat's profiling scene, see `garden`) on the AVX-512, AVX2 and plain kernels, and of the
//! grid-5 copy (2.8M Gaussians) at 1920x1080. Each configuration prints its stage times, the
//! blend-backward rate in Gaussian-pixel evaluations per second, the backward / forward ratio
//! and the memory it holds once.
//!
//!     cargo bench -p splat-core --bench raster_backward
use std::time::Instant;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use splat_core::camera::Camera;
use splat_core::raster::diff::{
    BackwardStats, DensifyStats, DiffOptions, Gradients, ImageGrads, Workspace,
};
use splat_core::raster::{RenderOptions, RenderStats, Simd};
use splat_core::Scene;

mod garden;
use garden::{garden, resized};

/// Everything an optimiser step keeps between steps.
struct Step {
    ws: Workspace,
    grads: Gradients,
    densify: DensifyStats,
    rgb: Vec<f32>,
    depth: Vec<f32>,
    alpha: Vec<f32>,
    v_rgb: Vec<f32>,
}

impl Step {
    fn new(scene: &Scene, cam: &Camera) -> Self {
        let n = cam.width as usize * cam.height as usize;
        // an L1 loss's image gradient: +-1 / (3 n), fixed pseudo-random signs
        let mut h = 0x9e37_79b9_7f4a_7c15u64;
        let v_rgb = (0..n * 3)
            .map(|_| {
                h ^= h << 13;
                h ^= h >> 7;
                h ^= h << 17;
                (if h & 1 == 0 { 1.0 } else { -1.0 }) / (3 * n) as f32
            })
            .collect();
        let mut densify = DensifyStats::default();
        densify.reset(scene.len());
        Step {
            ws: Workspace::default(),
            grads: Gradients::default(),
            densify,
            rgb: vec![0.0; n * 3],
            depth: vec![0.0; n],
            alpha: vec![0.0; n],
            v_rgb,
        }
    }

    /// Forward and backward; returns their stats and wall times in seconds.
    fn run(
        &mut self,
        scene: &Scene,
        cam: &Camera,
        opts: &DiffOptions,
    ) -> (RenderStats, BackwardStats, f64, f64) {
        let view = scene.view();
        let t0 = Instant::now();
        let f = self
            .ws
            .forward(
                &view,
                cam,
                opts,
                None,
                &mut self.rgb,
                &mut self.depth,
                &mut self.alpha,
            )
            .expect("forward");
        let t1 = Instant::now();
        self.grads.reset(scene.len(), scene.sh_rest_k(), false);
        let grads = ImageGrads {
            rgb: Some(&self.v_rgb),
            ..Default::default()
        };
        let b = self
            .ws
            .backward(
                &view,
                None,
                &grads,
                &mut self.grads,
                None,
                Some(&mut self.densify),
            )
            .expect("backward");
        let t2 = Instant::now();
        (f, b, (t1 - t0).as_secs_f64(), (t2 - t1).as_secs_f64())
    }
}

fn report(label: &str, step: &mut Step, scene: &Scene, cam: &Camera, opts: &DiffOptions) {
    // best of a few runs (the first pays page faults)
    let mut best: Option<(RenderStats, BackwardStats, f64, f64)> = None;
    for _ in 0..5 {
        let r = step.run(scene, cam, opts);
        if best.is_none_or(|b| r.2 + r.3 < b.2 + b.3) {
            best = Some(r);
        }
    }
    let Some((f, b, wf, wb)) = best else { return };
    println!(
        "{label}: forward {:.1} ms (project {:.1}, sort {:.1}, bin {:.1}, blend {:.1}) | backward \
         {:.1} ms (blend {:.1}, reduce {:.1}, project+SH {:.1}, zeroing {:.1}) | ratio {:.2} | \
         {:.1}M evals, blend backward {:.2} G evals/s | visible {}, {} intersections, {} band(s), \
         slots {:.1} MB, workspace {:.1} MB",
        wf * 1e3,
        f.project_s * 1e3,
        f.sort_s * 1e3,
        f.bin_s * 1e3,
        f.blend_s * 1e3,
        wb * 1e3,
        b.blend_s * 1e3,
        b.reduce_s * 1e3,
        b.project_s * 1e3,
        (wb - b.blend_s - b.reduce_s - b.project_s) * 1e3,
        wb / wf,
        b.evaluations as f64 / 1e6,
        b.evaluations as f64 / b.blend_s / 1e9,
        f.visible,
        b.intersections,
        b.bands,
        b.slot_bytes as f64 / 1e6,
        step.ws.bytes() as f64 / 1e6,
    );
}

fn bench_garden(c: &mut Criterion) {
    let (scene, cams) = garden(1);
    let cam = cams[0];
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut g = c.benchmark_group("backward_garden_648x420");
    g.sample_size(20);
    let mut step = Step::new(&scene, &cam);
    for simd in [Simd::Avx512, Simd::Avx2, Simd::Scalar] {
        if simd.resolve() != simd {
            continue;
        }
        let opts = DiffOptions {
            render: RenderOptions {
                simd,
                ..Default::default()
            },
            ..Default::default()
        };
        report(
            &format!("garden {} {threads} threads", simd.name()),
            &mut step,
            &scene,
            &cam,
            &opts,
        );
        let evals = step.run(&scene, &cam, &opts).1.evaluations;
        g.throughput(Throughput::Elements(evals));
        g.bench_function(format!("fwd_bwd_{}_{threads}threads", simd.name()), |b| {
            b.iter(|| step.run(&scene, &cam, &opts))
        });
    }
    let opts = DiffOptions {
        absgrad: true,
        ..Default::default()
    };
    report(
        &format!("garden auto + absgrad {threads} threads"),
        &mut step,
        &scene,
        &cam,
        &opts,
    );
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool");
    let opts = DiffOptions::default();
    one.install(|| report("garden auto 1 thread", &mut step, &scene, &cam, &opts));
    g.bench_function("fwd_bwd_auto_1thread", |b| {
        b.iter(|| one.install(|| step.run(&scene, &cam, &opts)))
    });
    g.finish();
}

/// Peak resident memory of this process so far (VmHWM), in MB.
fn peak_rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
        })
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

fn bench_grid5(c: &mut Criterion) {
    let (scene, cams) = garden(5);
    let cam = resized(&cams[0], 1920, 1080);
    let opts = DiffOptions::default();
    let before = peak_rss_mb();
    let mut step = Step::new(&scene, &cam);
    report(
        &format!("grid-5 ({} Gaussians) 1920x1080", scene.len()),
        &mut step,
        &scene,
        &cam,
        &opts,
    );
    println!(
        "grid-5 peak RSS {:.0} MB (scene, images and gradients included; {:.0} MB before the \
         first step)",
        peak_rss_mb(),
        before
    );
    let mut g = c.benchmark_group("backward_grid5_1920x1080");
    g.sample_size(10);
    g.bench_function("fwd_bwd_auto", |b| b.iter(|| step.run(&scene, &cam, &opts)));
    g.finish();
}

criterion_group!(benches, bench_garden, bench_grid5);
criterion_main!(benches);
