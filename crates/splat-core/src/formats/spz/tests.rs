use super::*;

#[test]
fn smallest_three_round_trips_within_quantisation() {
    for q in [
        [0.1f32, -0.7, 0.2, 0.67],
        [-0.9, 0.1, 0.3, -0.2],
        [0.0, 0.0, 0.0, 1.0],
        [0.5, 0.5, -0.5, 0.5],
    ] {
        let n = (q.iter().map(|v| v * v).sum::<f32>()).sqrt();
        let q = q.map(|v| v / n);
        let back = unpack_smallest_three(pack_smallest_three(q));
        let dot: f32 = (0..4).map(|i| q[i] * back[i]).sum();
        assert!(dot.abs() > 0.99999, "{q:?} -> {back:?}");
    }
}

#[test]
fn sh_flip_matches_the_basis_parity() {
    // band-2 basis xy, yz, 3z^2-1, xz, x^2-y^2 under (y,z) -> (-y,-z)
    assert_eq!(&SH_FLIP_RUB_RDF[3..8], &[-1.0, 1.0, 1.0, -1.0, 1.0]);
}

/// A v4 file built from v3 bytes (same sections, one zstd frame each) decodes to the same
/// scene, SH stream included (the fixtures only have SH degree 0 in v4).
#[test]
fn v4_streams_decode_like_the_v3_payload() {
    let n = 300;
    let k = sh_rest_count(2);
    let f = |m: usize, s: f32| (0..m).map(move |i| ((i * 37 % 101) as f32 / 50.0 - 1.0) * s);
    let mut quats: Vec<f32> = f(n * 4, 1.0).collect();
    crate::scene::normalize_quats(&mut quats);
    let scene = Scene {
        means: f(n * 3, 7.0).collect(),
        quats,
        log_scales: f(n * 3, 3.0).map(|v| v - 4.0).collect(),
        opacity_logits: f(n, 4.0).collect(),
        sh0: f(n * 3, 1.0).collect(),
        sh_rest: f(n * k * 3, 0.5).collect(),
        sh_degree: 2,
        extras: Vec::new(),
    };
    let v3 = encode_v3(&scene.view(), SpzAxes::Rdf).expect("encode");
    let h = parse_header(&v3, Path::new("v3")).expect("header");
    let mut streams = Vec::new();
    let mut off = 16;
    for (_, size) in h.sections() {
        let part = &v3[off..off + size as usize];
        streams.push((zstd::bulk::compress(part, 3).expect("zstd"), part.len()));
        off += size as usize;
    }
    let mut v4 = Vec::new();
    v4.extend_from_slice(&MAGIC.to_le_bytes());
    v4.extend_from_slice(&4u32.to_le_bytes());
    v4.extend_from_slice(&(n as u32).to_le_bytes());
    v4.extend_from_slice(&[2, v3[13], FLAG_EXTENSIONS, 6]);
    v4.extend_from_slice(&40u32.to_le_bytes());
    v4.extend_from_slice(&[0u8; 12]);
    // an unknown, empty extension record before the table of contents
    v4.extend_from_slice(&0x1234_0001u32.to_le_bytes());
    v4.extend_from_slice(&0u32.to_le_bytes());
    for (c, plain) in &streams {
        v4.extend_from_slice(&(c.len() as u64).to_le_bytes());
        v4.extend_from_slice(&(*plain as u64).to_le_bytes());
    }
    for (c, _) in &streams {
        v4.extend_from_slice(c);
    }
    let p = Path::new("mem.spz");
    let a = decode_bytes(&v3, p, SpzAxes::Rdf).expect("v3");
    let b = decode_bytes(&v4, p, SpzAxes::Rdf).expect("v4");
    assert_eq!(a, b);
    assert_eq!(b.sh_rest.len(), n * k * 3);
    let ours = encode_v4(&scene.view(), SpzAxes::Rdf).expect("v4");
    let c = decode_bytes(&ours, p, SpzAxes::Rdf).expect("our v4");
    assert_eq!(a, c);
}

#[test]
fn lying_counts_fail_before_allocating() {
    let p = Path::new("lie.spz");
    let mut raw = Vec::new();
    raw.extend_from_slice(&MAGIC.to_le_bytes());
    raw.extend_from_slice(&3u32.to_le_bytes());
    raw.extend_from_slice(&u32::MAX.to_le_bytes());
    raw.extend_from_slice(&[3, 12, 0, 0]);
    let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    std::io::Write::write_all(&mut gz, &raw).expect("gzip");
    let bytes = gz.finish().expect("gzip");
    let err = decode_bytes(&bytes, p, SpzAxes::Rdf)
        .expect_err("must fail")
        .to_string();
    assert!(err.contains("can hold at most"), "{err}");
}
