//! The garden scene of gsplat's profiling (tests/fixtures/gsplat_test_garden.npz), built as
//! gsplat's `load_test_data` does: the points inside [-2,2]^3, scales uniform in [1e-4, 0.02],
//! random unit quaternions, opacities uniform in (0,1), colours from the file; `grid` > 1 tiles
//! grid x grid copies offset by 4 in x and y. Shared by the raster benchmarks.
use std::path::PathBuf;

use splat_core::camera::Camera;
use splat_core::Scene;

/// One array of an uncompressed .npz: (dtype descr, shape, raw little-endian bytes).
fn npz_array(bytes: &[u8], name: &str) -> (String, Vec<usize>, Vec<u8>) {
    let want = format!("{name}.npy");
    let mut pos = 0;
    while pos + 30 <= bytes.len() && bytes[pos..pos + 4] == [0x50, 0x4b, 0x03, 0x04] {
        let u16_at = |p: usize| u16::from_le_bytes([bytes[p], bytes[p + 1]]) as usize;
        let (name_len, extra_len) = (u16_at(pos + 26), u16_at(pos + 28));
        let fname = std::str::from_utf8(&bytes[pos + 30..pos + 30 + name_len]).expect("name");
        let data = pos + 30 + name_len + extra_len;
        // .npy: magic, version, header length, header dict, data
        let major = bytes[data + 6];
        let (hlen, hstart) = if major == 1 {
            (u16_at(data + 8), data + 10)
        } else {
            let b = &bytes[data + 8..data + 12];
            (
                u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize,
                data + 12,
            )
        };
        let header = std::str::from_utf8(&bytes[hstart..hstart + hlen]).expect("header");
        let descr = header.split("'descr': '").nth(1).expect("descr")[..3].to_owned();
        let shape_txt = header.split("'shape': (").nth(1).expect("shape");
        let shape: Vec<usize> = shape_txt[..shape_txt.find(')').expect(")")]
            .split(',')
            .filter_map(|s| s.trim().parse().ok())
            .collect();
        let item: usize = descr[2..].parse().expect("itemsize");
        let len = shape.iter().product::<usize>() * item;
        let start = hstart + hlen;
        if fname == want {
            return (descr, shape, bytes[start..start + len].to_vec());
        }
        pos = start + len;
    }
    panic!("{name} not found in the npz");
}

fn f32s(raw: &[u8]) -> Vec<f32> {
    raw.chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// SplitMix64 uniform in [0, 1).
struct Rng(u64);
impl Rng {
    fn uniform(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
    fn normal(&mut self) -> f64 {
        let (u, v) = (self.uniform().max(1e-300), self.uniform());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

pub fn garden(grid: i32) -> (Scene, Vec<Camera>) {
    let dir = std::env::var_os("MORPHGS_FIXTURES")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures"));
    let bytes = std::fs::read(dir.join("gsplat_test_garden.npz")).expect("garden npz");
    let means = f32s(&npz_array(&bytes, "means3d").2);
    let colors = npz_array(&bytes, "colors").2;
    let viewmats = f32s(&npz_array(&bytes, "viewmats").2);
    let ks = f32s(&npz_array(&bytes, "Ks").2);
    let int = |n: &str| {
        let raw = npz_array(&bytes, n).2;
        i64::from_le_bytes(raw[..8].try_into().expect("i8")) as u32
    };
    let (width, height) = (int("width"), int("height"));
    let mut scene = Scene::empty(0);
    let mut rng = Rng(0);
    let h = grid / 2;
    for gx in -h..=h {
        for gy in -h..=h {
            for (p, c) in means.chunks_exact(3).zip(colors.chunks_exact(3)) {
                if p.iter().any(|v| !(-2.0..=2.0).contains(v)) {
                    continue;
                }
                scene
                    .means
                    .extend([p[0] + 4.0 * gx as f32, p[1] + 4.0 * gy as f32, p[2]]);
                for _ in 0..3 {
                    let s = 1e-4 + rng.uniform() * (0.02 - 1e-4);
                    scene.log_scales.push(s.ln() as f32);
                }
                let q: Vec<f64> = (0..4).map(|_| rng.normal()).collect();
                let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
                scene.quats.extend(q.iter().map(|v| (v / n) as f32));
                let o = 1e-3 + rng.uniform() * (1.0 - 2e-3);
                scene.opacity_logits.push((o / (1.0 - o)).ln() as f32);
                scene
                    .sh0
                    .extend(c.iter().map(|&v| ((v as f32 / 255.0) - 0.5) / 0.282_094_8));
            }
        }
    }
    let cams = (0..3)
        .map(|i| {
            let w: Vec<f64> = viewmats[i * 16..i * 16 + 16]
                .iter()
                .map(|&v| v as f64)
                .collect();
            let k: Vec<f64> = ks[i * 9..i * 9 + 9].iter().map(|&v| v as f64).collect();
            Camera::from_matrices(&w, &k, width, height, 0.01, 1e10).expect("camera")
        })
        .collect();
    (scene, cams)
}

pub fn resized(c: &Camera, width: u32, height: u32) -> Camera {
    let (sx, sy) = (
        width as f64 / c.width as f64,
        height as f64 / c.height as f64,
    );
    Camera {
        fx: c.fx * sx,
        cx: c.cx * sx,
        fy: c.fy * sy,
        cy: c.cy * sy,
        width,
        height,
        ..*c
    }
}
