//! Criterion benchmarks of the CPU rasterizer on gsplat's profiling scene (the Mip-NeRF 360
//! garden points of tests/fixtures/gsplat_test_garden.npz, Gaussians built as gsplat's
//! `load_test_data` does: crop to [-2,2]^3, scales uniform in [1e-4, 0.02], random unit
//! quaternions, opacities uniform in (0,1); `grid` 5 tiles 5x5 copies offset by 4 in x and y).
//!
//! Throughput is reported in Gaussian-pixel evaluations per second of the whole frame; each
//! configuration also prints its stage times and the blend-only rate once.
//!
//!     cargo bench -p splat-core --bench raster
//!     MORPHGS_FIXTURES=/path/to/fixtures cargo bench -p splat-core --bench raster
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use splat_core::camera::Camera;
use splat_core::raster::blend::FrozenFrame;
use splat_core::raster::project::project_frame;
use splat_core::raster::{render_into, RenderOptions, RenderStats, Simd};
use splat_core::Scene;

mod garden;
use garden::{garden, resized};

fn render(scene: &Scene, cam: &Camera, opts: &RenderOptions) -> RenderStats {
    let n = cam.width as usize * cam.height as usize;
    let (mut rgb, mut depth, mut alpha) = (vec![0.0; n * 3], vec![0.0; n], vec![0.0; n]);
    render_into(&scene.view(), cam, opts, &mut rgb, &mut depth, &mut alpha).expect("render")
}

fn report(label: &str, s: &RenderStats) {
    println!(
        "{label}: visible {} evals {:.1}M | project {:.2} ms, sort {:.2} ms, bin {:.2} ms, \
         blend {:.2} ms ({:.2} G evals/s)",
        s.visible,
        s.evaluations as f64 / 1e6,
        s.project_s * 1e3,
        s.sort_s * 1e3,
        s.bin_s * 1e3,
        s.blend_s * 1e3,
        s.evaluations as f64 / s.blend_s / 1e9
    );
}

fn bench_garden(c: &mut Criterion) {
    let (scene, cams) = garden(1);
    let cam = cams[0];
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut g = c.benchmark_group("garden_648x420");
    g.sample_size(20);
    for simd in [Simd::Avx512, Simd::Avx2, Simd::Scalar] {
        if simd.resolve() != simd {
            continue;
        }
        let opts = RenderOptions {
            simd,
            ..Default::default()
        };
        let s = render(&scene, &cam, &opts);
        report(&format!("garden {} {threads} threads", simd.name()), &s);
        g.throughput(Throughput::Elements(s.evaluations));
        g.bench_function(format!("{}_{threads}threads", simd.name()), |b| {
            b.iter(|| render(&scene, &cam, &opts))
        });
    }
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool");
    let opts = RenderOptions::default();
    let s = one.install(|| render(&scene, &cam, &opts));
    report("garden auto 1 thread", &s);
    g.throughput(Throughput::Elements(s.evaluations));
    g.bench_function("auto_1thread", |b| {
        b.iter(|| one.install(|| render(&scene, &cam, &opts)))
    });
    g.finish();
}

fn bench_grid5(c: &mut Criterion) {
    let (scene, cams) = garden(5);
    let cam = resized(&cams[0], 1920, 1080);
    let opts = RenderOptions::default();
    let s = render(&scene, &cam, &opts);
    report(&format!("grid-5 ({} Gaussians) 1920x1080", scene.len()), &s);
    let mut g = c.benchmark_group("garden_grid5_1920x1080");
    g.sample_size(10);
    g.throughput(Throughput::Elements(s.evaluations));
    g.bench_function("auto", |b| b.iter(|| render(&scene, &cam, &opts)));
    g.finish();
}

/// The projection stage alone, one thread: garden camera 0 (SH degree 0, and with SH degree 3
/// coefficients added, as the fit's scene has) and grid-5 at 1920x1080.
fn bench_project(c: &mut Criterion) {
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool");
    let (scene, cams) = garden(1);
    let mut sh3 = scene.clone();
    sh3.sh_degree = 3;
    let k = sh3.sh_rest_k() * 3;
    sh3.sh_rest = (0..scene.len() * k)
        .map(|i| {
            ((i as u32).wrapping_mul(2_654_435_761) >> 8) as f32 / (1u32 << 24) as f32 * 0.2 - 0.1
        })
        .collect();
    let (grid, gcams) = garden(5);
    let cases = [
        ("garden_sh0", &scene, cams[0]),
        ("garden_sh3", &sh3, cams[0]),
        ("grid5_1920x1080", &grid, resized(&gcams[0], 1920, 1080)),
    ];
    let opts = RenderOptions::default();
    let mut g = c.benchmark_group("project_1thread");
    g.sample_size(20);
    for (name, s, cam) in cases {
        let mut parts = Vec::new();
        let view = s.view();
        let visible = project_frame(&view, &cam, &opts, &mut parts).expect("project");
        println!("project {name}: {} Gaussians, {visible} visible", s.len());
        g.throughput(Throughput::Elements(s.len() as u64));
        g.bench_function(name, |b| {
            b.iter(|| one.install(|| project_frame(&view, &cam, &opts, &mut parts)))
        });
    }
    g.finish();
}

/// The blend stage alone, one thread, on frames projected, sorted and binned once
/// ([`FrozenFrame`]): garden camera 0 with the render's expected depth and without depth (as the
/// fit's forward blends), and grid-5 at 1920x1080. Timed in the thread's CPU time where the OS
/// gives it (Linux), so other jobs on the machine disturb it less than wall time.
fn bench_blend(c: &mut Criterion) {
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("pool");
    let (scene, cams) = garden(1);
    let (grid, gcams) = garden(5);
    let cases = [
        ("garden", &scene, cams[0], true),
        ("garden_nodepth", &scene, cams[0], false),
        (
            "grid5_1920x1080",
            &grid,
            resized(&gcams[0], 1920, 1080),
            true,
        ),
    ];
    let mut g = c.benchmark_group("blend_1thread");
    g.sample_size(20);
    for (name, s, cam, depth) in cases {
        let opts = RenderOptions::default();
        let frame = FrozenFrame::new(&s.view(), &cam, &opts).expect("frame");
        let n = cam.width as usize * cam.height as usize;
        let (mut rgb, mut d, mut alpha) = (vec![0.0; n * 3], vec![0.0; n], vec![0.0; n]);
        let (evals, _) = frame.blend(&mut rgb, &mut d, &mut alpha, depth);
        println!("blend {name}: {:.2}M evaluations", evals as f64 / 1e6);
        g.throughput(Throughput::Elements(evals));
        g.bench_function(name, |b| {
            b.iter_custom(|iters| {
                one.install(|| {
                    let (t0, c0) = (std::time::Instant::now(), thread_cpu());
                    for _ in 0..iters {
                        frame.blend(&mut rgb, &mut d, &mut alpha, depth);
                    }
                    c0.map_or(t0.elapsed(), |c0| thread_cpu().expect("clock") - c0)
                })
            })
        });
    }
    g.finish();
}

/// The calling thread's CPU time (None where not available).
fn thread_cpu() -> Option<std::time::Duration> {
    #[cfg(target_os = "linux")]
    {
        let mut ts = libc::timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        // SAFETY: `ts` is a valid timespec to write.
        let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
        (rc == 0).then(|| std::time::Duration::new(ts.tv_sec as u64, ts.tv_nsec as u32))
    }
    #[cfg(not(target_os = "linux"))]
    None
}

criterion_group!(
    benches,
    bench_garden,
    bench_grid5,
    bench_project,
    bench_blend
);
criterion_main!(benches);
