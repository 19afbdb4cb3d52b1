//! Criterion benches of the PLY reader and writer on a generated 200,000-Gaussian, SH-degree-3
//! scene (62 float32 properties per row, 49.6 MB) written to a temporary folder.
//!
//!     cargo bench -p splat-core --bench ply
use std::hint::black_box;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use splat_core::ply::{read_ply, write_ply, OnInvalid};
use splat_core::scene::{normalize_quats, sh_rest_count, Scene};

const N: usize = 200_000;

/// A deterministic scene with varied values (a cheap integer hash mapped to [-1, 1)).
fn scene(n: usize, degree: u8) -> Scene {
    let vals = |count: usize, salt: u32| -> Vec<f32> {
        (0..count as u32)
            .map(|i| {
                let h = (i ^ salt.wrapping_mul(0x9e37_79b9))
                    .wrapping_mul(0x85eb_ca6b)
                    .rotate_left(13)
                    .wrapping_mul(0xc2b2_ae35);
                (h >> 8) as f32 / (1u32 << 23) as f32 - 1.0
            })
            .collect()
    };
    let mut quats = vals(n * 4, 2);
    normalize_quats(&mut quats);
    Scene {
        means: vals(n * 3, 1),
        quats,
        log_scales: vals(n * 3, 3),
        opacity_logits: vals(n, 4),
        sh0: vals(n * 3, 5),
        sh_rest: vals(n * 3 * sh_rest_count(degree), 6),
        sh_degree: degree,
        extras: Vec::new(),
    }
}

fn bench_ply(c: &mut Criterion) {
    let dir = match tempfile::tempdir() {
        Ok(d) => d,
        Err(e) => panic!("no temporary folder: {e}"),
    };
    let path = dir.path().join("bench.ply");
    let s = scene(N, 3);
    if let Err(e) = write_ply(&path, &s.view(), &[]) {
        panic!("write failed: {e}");
    }
    let bytes = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);

    let mut g = c.benchmark_group("ply");
    g.throughput(Throughput::Bytes(bytes));
    g.sample_size(20);
    g.bench_function("read_200k_sh3", |b| {
        b.iter(|| black_box(read_ply(black_box(&path), OnInvalid::Error).map(|r| r.0.len())))
    });
    let out = dir.path().join("out.ply");
    g.bench_function("write_200k_sh3", |b| {
        b.iter(|| black_box(write_ply(black_box(&out), &s.view(), &[])))
    });
    g.finish();
}

criterion_group!(benches, bench_ply);
criterion_main!(benches);
