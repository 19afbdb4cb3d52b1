//! Decode throughput of the compressed formats: the real SuperSplat capture
//! (playcanvas_engine_guitar.compressed.ply, from MORPHGS_FIXTURES or tests/fixtures), the real
//! PlayCanvas SOG playcanvas_engine_monkey_0001.sog, and a generated 100k-splat SH-3 scene as
//! .spz (v3 gzip, v4 zstd) and .glb, decoded from memory; and encode throughput of the writers
//! (.spz v3/v4, compressed PLY, .glb) on the same scene.
use std::hint::black_box;
use std::io::Write;
use std::path::{Path, PathBuf};

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use splat_core::formats::{compressed_ply, gltf, sog, spz, SpzAxes};
use splat_core::io::{load, LoadOptions};
use splat_core::ply::OnInvalid;
use splat_core::scene::{normalize_quats, sh_rest_count, Scene};

fn fixtures() -> PathBuf {
    std::env::var_os("MORPHGS_FIXTURES").map_or_else(
        || Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures"),
        PathBuf::from,
    )
}

fn synthetic(n: usize, degree: u8) -> Scene {
    let k = sh_rest_count(degree);
    // a cheap deterministic pseudo-random sequence in [-1, 1)
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 40) as f32 / (1u64 << 23) as f32 - 1.0
    };
    let mut f = |m: usize, s: f32, o: f32| (0..m).map(|_| next() * s + o).collect::<Vec<_>>();
    let mut quats = f(n * 4, 1.0, 0.0);
    normalize_quats(&mut quats);
    Scene {
        means: f(n * 3, 5.0, 0.0),
        quats,
        log_scales: f(n * 3, 2.0, -4.0),
        opacity_logits: f(n, 3.0, 0.0),
        sh0: f(n * 3, 1.0, 0.0),
        sh_rest: f(n * k * 3, 0.3, 0.0),
        sh_degree: degree,
        extras: Vec::new(),
    }
}

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("formats");
    g.sample_size(20);
    let guitar = fixtures().join("playcanvas_engine_guitar.compressed.ply");
    if guitar.is_file() {
        g.throughput(Throughput::Elements(90_854));
        g.bench_function("load guitar.compressed.ply", |b| {
            b.iter(|| black_box(load(&guitar, LoadOptions::default()).map(|s| s.0.len())))
        });
    } else {
        eprintln!(
            "skipping the compressed PLY bench: {} not found",
            guitar.display()
        );
    }
    let n = 100_000;
    let scene = synthetic(n, 3);
    let raw = spz::encode_v3(&scene.view(), SpzAxes::Rdf).expect("encode");
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    gz.write_all(&raw).expect("gzip");
    let bytes = gz.finish().expect("gzip");
    g.throughput(Throughput::Elements(n as u64));
    g.bench_function("decode 100k-splat SH3 .spz (gzip)", |b| {
        b.iter(|| {
            black_box(spz::decode_bytes(
                &bytes,
                Path::new("mem.spz"),
                SpzAxes::Rdf,
            ))
        })
    });
    g.bench_function("decode 100k-splat SH3 .spz (uncompressed NGSP)", |b| {
        b.iter(|| black_box(spz::decode_bytes(&raw, Path::new("mem.spz"), SpzAxes::Rdf)))
    });
    let v4 = spz::encode_v4(&scene.view(), SpzAxes::Rdf).expect("v4");
    g.bench_function("decode 100k-splat SH3 .spz v4 (zstd)", |b| {
        b.iter(|| black_box(spz::decode_bytes(&v4, Path::new("mem.spz"), SpzAxes::Rdf)))
    });
    let glb = gltf::encode_glb(&scene.view(), "bench").expect("glb");
    g.bench_function("decode 100k-splat SH3 .glb", |b| {
        b.iter(|| black_box(gltf::read(&glb, Path::new("mem.glb"), OnInvalid::Error)))
    });
    g.bench_function("encode 100k-splat SH3 .spz v3 (gzip)", |b| {
        b.iter(|| {
            let raw = spz::encode_v3(&scene.view(), SpzAxes::Rdf).expect("v3");
            let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
            gz.write_all(&raw).expect("gzip");
            black_box(gz.finish().expect("gzip").len())
        })
    });
    g.bench_function("encode 100k-splat SH3 .spz v4 (zstd)", |b| {
        b.iter(|| black_box(spz::encode_v4(&scene.view(), SpzAxes::Rdf).map(|v| v.len())))
    });
    g.bench_function("encode 100k-splat SH3 compressed PLY", |b| {
        b.iter(|| black_box(compressed_ply::encode(&scene.view(), "bench").map(|v| v.len())))
    });
    g.bench_function("encode 100k-splat SH3 .glb", |b| {
        b.iter(|| black_box(gltf::encode_glb(&scene.view(), "bench").map(|v| v.len())))
    });
    let monkey = fixtures().join("playcanvas_engine_monkey_0001.sog");
    if let Ok(bytes) = std::fs::read(&monkey) {
        g.throughput(Throughput::Elements(31_658));
        g.bench_function("decode monkey_0001.sog (31,658 splats, WebP)", |b| {
            b.iter(|| {
                black_box(sog::read_zip(&bytes, &monkey, OnInvalid::Error).map(|s| s.0.len()))
            })
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
