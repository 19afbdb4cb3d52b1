//! SceneSplat-7K / SceneSplat-49K "preprocessed" scene folders: one `.npy` per attribute, written
//! by `scripts/preprocess_gs.py` of unique1i/SceneSplat from an INRIA PLY:
//!
//! | file | shape, dtype | meaning (as the script writes it) |
//! |---|---|---|
//! | `coord.npy` | (N,3) float32 | x y z, the PLY's own axes |
//! | `color.npy` | (N,3) uint8 | `(clip(0.5 + C0*f_dc, 0, 1) * 255).astype(uint8)`: truncated, DC only |
//! | `opacity.npy` | (N,) float32 | `sigmoid(opacity)` |
//! | `scale.npy` | (N,3) float32 | `exp(scale_i)`: linear scales |
//! | `quat.npy` | (N,4) float32 | rot_0..3 = (w,x,y,z), normalised, w >= 0 |
//! | `normal.npy` | (N,3) float32, optional | nx ny nz (checked for shape, not kept) |
//!
//! Everything is activated and the colour is the 8-bit DC term only, so loading is lossy: the
//! scene comes back as SH degree 0 and the report says so. Float colour arrays (what the
//! SceneSplat data loaders cast to) are read on the same 0-255 scale.
use std::path::{Path, PathBuf};

use rayon::prelude::*;

use super::{finish, logit_unit, npy};
use crate::error::{Error, Result};
use crate::ply::{LoadReport, OnInvalid};
use crate::scene::{Scene, SH_C0};

/// The attribute files a folder must hold.
pub const REQUIRED: [&str; 5] = ["coord", "color", "opacity", "scale", "quat"];

/// True when `dir` holds the required `.npy` files.
pub fn is_scenesplat_dir(dir: &Path) -> bool {
    dir.join("coord.npy").is_file()
}

/// The lossy-load note reported with every SceneSplat scene.
pub fn lossy_note(dir: &Path) -> String {
    format!(
        "{}: SceneSplat .npy folder: colours are 8-bit DC terms only (the converter dropped \
         every higher SH band) and opacity/scale were stored activated; loaded as SH degree 0, \
         which is lossy",
        dir.display()
    )
}

fn file(dir: &Path, name: &str) -> PathBuf {
    dir.join(format!("{name}.npy"))
}

/// Read one attribute and check it is `n` rows of `width` values (`width` 1 also accepts a
/// 1-D array). `n = None` takes the count from this array.
fn attribute(dir: &Path, name: &str, n: Option<usize>, width: usize) -> Result<npy::Npy> {
    let path = file(dir, name);
    if !path.is_file() {
        return Err(Error::format_at(
            dir,
            name,
            None,
            format!(
                "{} is missing; a SceneSplat folder needs {}.npy",
                path.display(),
                REQUIRED.join(".npy, ")
            ),
        ));
    }
    let a = npy::read(&path, name)?;
    let ok_shape = match a.shape.as_slice() {
        [rows] => width == 1 && n.is_none_or(|n| *rows == n),
        [rows, w] => *w == width && n.is_none_or(|n| *rows == n),
        _ => false,
    };
    if !ok_shape {
        let want = match n {
            Some(n) => format!("({n}, {width})"),
            None => format!("(N, {width})"),
        };
        return Err(Error::format_at(
            &path,
            name,
            None,
            format!(
                "shape {:?}, expected {want}{}",
                a.shape,
                if width == 1 { " or (N,)" } else { "" }
            ),
        ));
    }
    Ok(a)
}

/// Read a SceneSplat folder.
pub fn read(dir: &Path, on_invalid: OnInvalid) -> Result<(Scene, LoadReport)> {
    let coord = attribute(dir, "coord", None, 3)?;
    let n = coord.rows();
    let color = attribute(dir, "color", Some(n), 3)?;
    let opacity = attribute(dir, "opacity", Some(n), 1)?;
    let scale = attribute(dir, "scale", Some(n), 3)?;
    let quat = attribute(dir, "quat", Some(n), 4)?;
    if file(dir, "normal").is_file() {
        attribute(dir, "normal", Some(n), 3)?;
    }
    if let Some(bad) = color.values.iter().find(|v| !(0.0..=255.0).contains(*v)) {
        return Err(Error::format_at(
            file(dir, "color"),
            "color",
            None,
            format!("value {bad} outside the 0-255 colour range"),
        ));
    }
    let mut s = Scene::zeroed(n, 0);
    s.means = coord.values;
    s.quats = quat.values;
    s.sh0 = color.values.par_iter().map(|&c| color_to_dc(c)).collect();
    s.opacity_logits = opacity.values.par_iter().map(|&a| logit_unit(a)).collect();
    s.log_scales = scale
        .values
        .par_iter()
        .map(|&v| {
            if v == 0.0 {
                f32::MIN_POSITIVE.ln()
            } else {
                v.ln()
            }
        })
        .collect();
    let (scene, mut report) = finish(s, "scenesplat", "attributes", dir, on_invalid)?;
    report.notes.push(lossy_note(dir));
    Ok((scene, report))
}

/// A colour byte back to the DC coefficient: the script truncates, so the best estimate of the
/// original colour is the middle of the byte's bucket, (k + 0.5) / 255 (capped at 1).
#[inline]
pub fn color_to_dc(c: f32) -> f32 {
    let v = ((c.floor() + 0.5) / 255.0).min(1.0);
    (v - 0.5) / SH_C0
}
