//! Writing the INRIA layout (binary little-endian float32, zero normals, extras after rot_3),
//! atomically: everything goes to a temporary file beside the destination, which is synced and
//! renamed over it only when every byte was written.
//!
//! Rows are encoded in fixed-size parallel tasks, each written at its own offset with a
//! positioned write, so encoding overlaps the kernel's copy into the page cache.
use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::scene::SceneView;

use super::pio;
use super::plan::is_standard_name;

/// Rows encoded per parallel task (fixed: the bytes never depend on the thread count).
const ROWS_PER_TASK: usize = 4096;

/// Check that extra property names can be written into a PLY header and read back as extras.
pub fn check_extra_names<'a>(names: impl IntoIterator<Item = &'a str>) -> Result<()> {
    let mut seen: Vec<&str> = Vec::new();
    for name in names {
        if name.is_empty() || !name.bytes().all(|b| b.is_ascii_graphic()) {
            return Err(Error::InvalidArgument(format!(
                "extra property name {name:?} cannot be written to a PLY header (use non-empty \
                 ASCII without spaces)"
            )));
        }
        if is_standard_name(name) {
            return Err(Error::InvalidArgument(format!(
                "extra property name '{name}' is a standard INRIA property name"
            )));
        }
        if seen.contains(&name) {
            return Err(Error::InvalidArgument(format!(
                "extra property '{name}' is given twice"
            )));
        }
        seen.push(name);
    }
    Ok(())
}

/// The INRIA header for `n` Gaussians of SH rest count `k` and the given extras; also returns the
/// number of float32 values per row.
fn inria_header(n: usize, k: usize, extras: &[(&str, &[f32])]) -> (String, usize) {
    let mut names: Vec<String> = [
        "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    names.extend((0..3 * k).map(|i| format!("f_rest_{i}")));
    names.extend(
        [
            "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
        ]
        .iter()
        .map(|s| s.to_string()),
    );
    names.extend(extras.iter().map(|(n, _)| n.to_string()));
    let mut head = format!(
        "ply\nformat binary_little_endian 1.0\ncomment written by morphgs {}\nelement vertex {n}\n",
        env!("CARGO_PKG_VERSION")
    );
    for name in &names {
        head.push_str("property float ");
        head.push_str(name);
        head.push('\n');
    }
    head.push_str("end_header\n");
    (head, names.len())
}

/// Write `scene` in the INRIA layout (binary little-endian float32, zero normals), followed by
/// `extras`, atomically (see [`atomic_write_file`]).
pub fn write_ply(path: &Path, scene: &SceneView<'_>, extras: &[(&str, &[f32])]) -> Result<()> {
    scene.validate()?;
    let n = scene.len();
    for (name, v) in extras {
        if v.len() != n {
            return Err(Error::InvalidArgument(format!(
                "extra property '{name}' holds {} values, expected {n}",
                v.len()
            )));
        }
    }
    check_extra_names(extras.iter().map(|(n, _)| *n))?;
    let k = scene.sh_rest_k();
    let (head, stride) = inria_header(n, k, extras);
    let data_start = head.len() as u64;
    atomic_write_file(path, |file| {
        pio::write_all_at(file, head.as_bytes(), 0)?;
        (0..n.div_ceil(ROWS_PER_TASK))
            .into_par_iter()
            .try_for_each_init(Vec::<f32>::new, |buf, t| {
                let r0 = t * ROWS_PER_TASK;
                let rows = ROWS_PER_TASK.min(n - r0);
                if buf.len() < rows * stride {
                    buf.resize(rows * stride, 0.0);
                }
                let buf = &mut buf[..rows * stride];
                encode_rows(scene, extras, k, r0, stride, buf);
                if cfg!(target_endian = "big") {
                    for v in buf.iter_mut() {
                        *v = f32::from_bits(v.to_bits().swap_bytes());
                    }
                }
                let offset = data_start + (r0 * stride * 4) as u64;
                pio::write_all_at(file, bytemuck::cast_slice(buf), offset)
            })
    })
}

/// Fill `out` (rows of `stride` values) with Gaussians `r0..` in the INRIA column order.
fn encode_rows(
    s: &SceneView<'_>,
    extras: &[(&str, &[f32])],
    k: usize,
    r0: usize,
    stride: usize,
    out: &mut [f32],
) {
    match k {
        0 => encode_rows_k::<0>(s, extras, r0, stride, out),
        3 => encode_rows_k::<3>(s, extras, r0, stride, out),
        8 => encode_rows_k::<8>(s, extras, r0, stride, out),
        15 => encode_rows_k::<15>(s, extras, r0, stride, out),
        _ => encode_rows_k::<24>(s, extras, r0, stride, out),
    }
}

/// [`encode_rows`] for a compile-time SH rest count, so the f_rest transpose unrolls and the
/// fixed part of each row needs no bounds checks.
fn encode_rows_k<const K: usize>(
    s: &SceneView<'_>,
    extras: &[(&str, &[f32])],
    r0: usize,
    stride: usize,
    out: &mut [f32],
) {
    let rows = out.len() / stride;
    let r1 = r0 + rows;
    let means = s.means[3 * r0..3 * r1].chunks_exact(3);
    let sh0 = s.sh0[3 * r0..3 * r1].chunks_exact(3);
    let scales = s.log_scales[3 * r0..3 * r1].chunks_exact(3);
    let quats = s.quats[4 * r0..4 * r1].chunks_exact(4);
    let opacity = &s.opacity_logits[r0..r1];
    let rest = &s.sh_rest[3 * K * r0..3 * K * r1];
    let rows_iter = out
        .chunks_exact_mut(stride)
        .zip(means)
        .zip(sh0)
        .zip(scales)
        .zip(quats)
        .enumerate();
    for (j, ((((o, m), d), sc), q)) in rows_iter {
        let (head, tail) = o.split_at_mut(9 + 3 * K);
        head[0..3].copy_from_slice(m);
        head[3..6].fill(0.0);
        head[6..9].copy_from_slice(d);
        if K > 0 {
            let r = &rest[3 * K * j..3 * K * (j + 1)];
            for c in 0..3 {
                for b in 0..K {
                    head[9 + c * K + b] = r[b * 3 + c];
                }
            }
        }
        tail[0] = opacity[j];
        tail[1..4].copy_from_slice(sc);
        tail[4..8].copy_from_slice(q);
        for (e, (_, v)) in tail[8..].iter_mut().zip(extras) {
            *e = v[r0 + j];
        }
    }
}

static TEMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// Write a file atomically: `fill` writes into a new temporary file beside `path` (it may use
/// positioned writes from several threads), which is synced and renamed over `path` only when
/// everything succeeded. On failure the temporary is removed and `path` is untouched.
pub fn atomic_write_file(
    path: &Path,
    fill: impl FnOnce(&File) -> std::io::Result<()>,
) -> Result<()> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let file_name = path
        .file_name()
        .ok_or_else(|| Error::InvalidArgument(format!("{}: not a file path", path.display())))?;
    let tmp = dir.join(format!(
        ".{}.tmp-{}-{}",
        file_name.to_string_lossy(),
        std::process::id(),
        TEMP_COUNTER.fetch_add(1, Ordering::Relaxed)
    ));
    let file = OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&tmp)
        .map_err(|e| Error::io(path, e))?;
    let result = (|| -> std::io::Result<()> {
        fill(&file)?;
        file.sync_all()?;
        drop(file);
        std::fs::rename(&tmp, path)
    })();
    result.map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        Error::io(path, e)
    })
}

/// [`atomic_write_file`] for sequential writers: `fill` gets a buffered writer.
pub fn atomic_write(
    path: &Path,
    fill: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> Result<()> {
    atomic_write_file(path, |file| {
        let mut w = std::io::BufWriter::with_capacity(1 << 20, file);
        fill(&mut w)?;
        w.flush()
    })
}
