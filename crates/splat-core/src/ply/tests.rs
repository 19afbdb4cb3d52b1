use super::*;
use crate::scene::{normalize_quats, sh_rest_count, Scene};

fn scene(n: usize, degree: u8) -> Scene {
    let k = sh_rest_count(degree);
    let f = |m: usize, s: f32| (0..n * m).map(|i| i as f32 * s - 1.0).collect::<Vec<_>>();
    let mut quats = f(4, 0.37);
    normalize_quats(&mut quats);
    Scene {
        means: f(3, 0.1),
        quats,
        log_scales: f(3, -0.01),
        opacity_logits: f(1, 0.3),
        sh0: f(3, 0.02),
        sh_rest: f(3 * k, 0.003),
        sh_degree: degree,
        extras: vec![("filter_3D".into(), f(1, 0.5))],
    }
}

fn extras_of(s: &Scene) -> Vec<(&str, &[f32])> {
    s.extras
        .iter()
        .map(|(n, v)| (n.as_str(), v.as_slice()))
        .collect()
}

#[test]
fn round_trip_is_bit_exact() {
    let dir = tempfile::tempdir().expect("tempdir");
    for degree in 0..=4 {
        for n in [0, 1, 4096 * 3 + 17] {
            let s = scene(n, degree);
            let p = dir.path().join(format!("s{degree}-{n}.ply"));
            write_ply(&p, &s.view(), &extras_of(&s)).expect("write");
            let (back, report) = read_ply(&p, OnInvalid::Error).expect("read");
            assert_eq!(report.dropped, 0);
            assert_eq!(back, s, "degree {degree}, n {n}");
        }
    }
}

#[test]
fn thread_count_does_not_change_the_result() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut s = scene(10_000, 3);
    // Unnormalised quaternions exercise the normalisation inside the parallel decode.
    for (i, q) in s.quats.iter_mut().enumerate() {
        *q *= 1.0 + (i % 5) as f32 * 0.3;
    }
    let p = dir.path().join("t.ply");
    write_ply(&p, &s.view(), &extras_of(&s)).expect("write");
    let read_with = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool");
        pool.install(|| read_ply(&p, OnInvalid::Error).expect("read").0)
    };
    let one = read_with(1);
    assert_eq!(one, read_with(3));
    assert_eq!(one, read_with(8));
}

#[test]
fn lying_vertex_count_is_rejected_before_allocation() {
    let dir = tempfile::tempdir().expect("tempdir");
    let p = dir.path().join("lie.ply");
    let mut bytes =
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\n".to_vec();
    for name in [
        "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
        "rot_0", "rot_1", "rot_2", "rot_3",
    ] {
        bytes.extend_from_slice(format!("property float {name}\n").as_bytes());
    }
    bytes.extend_from_slice(b"end_header\n");
    bytes.extend_from_slice(&[0u8; 56 * 3]);
    std::fs::write(&p, bytes).expect("write");
    let err = read_ply(&p, OnInvalid::Error).expect_err("must fail");
    let msg = err.to_string();
    assert!(msg.contains("cannot hold"), "{msg}");
}

#[test]
fn failed_write_keeps_the_destination_and_leaves_no_temporary() {
    let dir = tempfile::tempdir().expect("tempdir");
    let p = dir.path().join("keep.ply");
    std::fs::write(&p, b"original").expect("write");
    let err = atomic_write(&p, |w| {
        w.write_all(b"partial")?;
        Err(std::io::Error::other("disk full"))
    });
    assert!(err.is_err());
    assert_eq!(std::fs::read(&p).expect("read"), b"original");
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .expect("dir")
        .map(|e| e.expect("entry").file_name())
        .collect();
    assert_eq!(names, [std::ffi::OsString::from("keep.ply")]);
}

#[test]
fn extra_names_that_would_corrupt_the_header_are_refused() {
    for bad in ["", "a b", "x", "f_rest_3", "line\nbreak"] {
        assert!(check_extra_names([bad]).is_err(), "{bad:?}");
    }
    assert!(check_extra_names(["filter_3D", "filter_3D"]).is_err());
    assert!(check_extra_names(["filter_3D", "f_rest_x"]).is_ok());
}
