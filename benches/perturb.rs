//! Criterion: `perturb` over 1M Gaussians of SH degree 3 for each preset, next to a plain copy of
//! the scene arrays (the floor). `cargo bench -p splat-core --bench perturb`.
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use splat_core::perturb::{perturb, PerturbParams};
use splat_core::Scene;

const N: usize = 1_000_000;

/// A deterministic pseudo-random scene (SplitMix64 values; no extra dependencies).
fn scene(n: usize) -> Scene {
    let mut state = 1u64;
    let mut next = move || {
        state = state.wrapping_add(splat_core::rng::GAMMA);
        (splat_core::rng::mix64(state) >> 40) as f32 / 16_777_216.0 - 0.5
    };
    let mut v = |len: usize, scale: f32, offset: f32| -> Vec<f32> {
        (0..len).map(|_| next() * scale + offset).collect()
    };
    let mut s = Scene {
        means: v(n * 3, 10.0, 0.0),
        quats: v(n * 4, 2.0, 0.0),
        log_scales: v(n * 3, 2.0, -4.0),
        opacity_logits: v(n, 4.0, 0.0),
        sh0: v(n * 3, 2.0, 0.0),
        sh_rest: v(n * 45, 0.2, 0.0),
        sh_degree: 3,
        extras: Vec::new(),
    };
    s.normalize_quats();
    s
}

fn bench(c: &mut Criterion) {
    let s = scene(N);
    let view = s.view();
    let mut g = c.benchmark_group("perturb_1M_sh3");
    g.sample_size(10);
    g.throughput(Throughput::Elements(N as u64));
    g.bench_function("copy", |b| b.iter(|| s.clone()));
    for name in PerturbParams::PRESETS {
        let params = PerturbParams::preset(name).expect("known preset");
        g.bench_function(name, |b| {
            b.iter(|| perturb(&view, &[], &params, 7).expect("valid scene"))
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
