//! Scene formats beyond the INRIA PLY: antimatter15 `.splat`, Niantic `.spz` (v2, v3 gzip and v4
//! zstd) and the PlayCanvas/SuperSplat `compressed.ply`.
//!
//! Every reader checks the counts a header declares against the bytes the file actually holds
//! before it allocates, and decompression is bounded by what those counts justify, so a lying or
//! truncated file fails with [`Error::Format`] naming the file and the problem.
use std::io::Read;
use std::path::Path;

use crate::error::{Error, Result};
use crate::ply::{LoadReport, OnInvalid};
use crate::scene::{Scene, SceneView};

pub mod compressed_ply;
pub mod gltf;
pub mod npy;
pub mod scenesplat;
pub mod sog;
pub mod splat;
pub mod spz;
pub mod spz_ext;
pub mod zip;

/// Gaussians decoded per parallel task (fixed, so results never depend on the thread count).
pub(crate) const ROWS_PER_TASK: usize = 4096;

/// Opacities are clamped to [EPS, 1-EPS] before the logit, as splat-transform does, so a stored
/// alpha of 0 or 255 gives a finite logit (about -13.8 / +13.8) instead of an infinity.
pub(crate) const ALPHA_EPS: f32 = 1e-6;

/// How `.spz` axes are returned. SPZ stores RUB (right, up, back: three.js); PLY and the OpenCV
/// convention used by morphgs are RDF (right, down, front).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SpzAxes {
    /// Convert to RDF on load (and from RDF on save), as nianticlabs/spz's PLY converters do.
    #[default]
    Rdf,
    /// Keep the axes exactly as stored in the file.
    Stored,
}

/// The logit of an 8-bit alpha, clamped away from 0 and 1.
#[inline]
pub(crate) fn logit_u8(a: u8) -> f32 {
    logit_unit(a as f32 / 255.0)
}

#[inline]
pub(crate) fn logit_unit(a: f32) -> f32 {
    let a = a.clamp(ALPHA_EPS, 1.0 - ALPHA_EPS);
    (a / (1.0 - a)).ln()
}

#[inline]
pub(crate) fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// Round and clamp to a byte, as the reference encoders' `toUint8`.
#[inline]
pub(crate) fn to_u8(x: f32) -> u8 {
    x.round().clamp(0.0, 255.0) as u8
}

/// Read a whole file into memory (the formats here are compact: a few bytes per Gaussian).
pub(crate) fn read_file(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| Error::io(path, e))
}

/// Read at most `limit` bytes from a decompressor. Returns the bytes and whether the stream had
/// more (the caller reports that as a lying header). `what` names the stream in messages.
/// `expect` (at most `limit`) is reserved up front; callers have checked it against the
/// compressed size, so a lying header cannot make this reservation large.
pub(crate) fn read_bounded(
    r: impl Read,
    expect: u64,
    limit: u64,
    path: &Path,
    what: &str,
) -> Result<(Vec<u8>, bool)> {
    let mut out = Vec::with_capacity(expect.min(limit) as usize + 1);
    r.take(limit.saturating_add(1))
        .read_to_end(&mut out)
        .map_err(|e| {
            Error::format(
                path,
                format!("{what}: corrupt or truncated compressed data ({e})"),
            )
        })?;
    let more = out.len() as u64 > limit;
    if more {
        out.truncate(limit as usize);
    }
    Ok((out, more))
}

/// Normalise quaternions and apply `on_invalid` to Gaussians holding NaN or Inf values.
pub(crate) fn finish(
    mut scene: Scene,
    format: &str,
    element: &str,
    path: &Path,
    on_invalid: OnInvalid,
) -> Result<(Scene, LoadReport)> {
    scene.normalize_quats();
    let bad = scene.invalid_rows();
    let mut report = LoadReport {
        format: format.to_owned(),
        dropped: 0,
        notes: Vec::new(),
    };
    if !bad.is_empty() {
        match on_invalid {
            OnInvalid::Error => {
                return Err(Error::format_at(
                    path,
                    element,
                    None,
                    format!(
                        "Gaussian {} holds NaN or Inf values ({} of {} do; pass \
                         on_invalid=\"drop\" to skip them)",
                        bad[0],
                        bad.len(),
                        scene.len()
                    ),
                ));
            }
            OnInvalid::Drop => {
                scene.drop_rows(&bad);
                report.dropped = bad.len();
            }
        }
    }
    Ok((scene, report))
}

/// Writers refuse non-finite values: quantised formats cannot hold them.
pub(crate) fn check_finite(scene: &SceneView<'_>, format: &str) -> Result<()> {
    scene.validate()?;
    let k = scene.sh_rest_k() * 3;
    for i in 0..scene.len() {
        let rows: [(&str, &[f32]); 6] = [
            ("means", &scene.means[i * 3..i * 3 + 3]),
            ("quats", &scene.quats[i * 4..i * 4 + 4]),
            ("log_scales", &scene.log_scales[i * 3..i * 3 + 3]),
            ("opacity_logits", &scene.opacity_logits[i..i + 1]),
            ("sh0", &scene.sh0[i * 3..i * 3 + 3]),
            ("sh_rest", &scene.sh_rest[i * k..i * k + k]),
        ];
        for (name, r) in rows {
            if let Some(v) = r.iter().find(|v| !v.is_finite()) {
                return Err(Error::InvalidArgument(format!(
                    "cannot write {format}: Gaussian {i} has {name} = {v} (only finite values \
                     can be quantised)"
                )));
            }
        }
    }
    Ok(())
}

/// A normalised (w,x,y,z) quaternion; zero or non-finite norms give the identity.
#[inline]
pub(crate) fn unit_quat(q: &[f32]) -> [f32; 4] {
    let n2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
    if n2 > 0.0 && n2.is_finite() {
        let inv = 1.0 / n2.sqrt();
        [q[0] * inv, q[1] * inv, q[2] * inv, q[3] * inv]
    } else {
        [1.0, 0.0, 0.0, 0.0]
    }
}

/// Per-coefficient SH signs when the axes are mirrored by `f` = (sx, sy, sz) (each +-1): the
/// parity of each basis function, from nianticlabs/spz `coordinateConverter` (bands 1-4).
pub fn sh_flips(f: [f32; 3]) -> [f32; 24] {
    let [x, y, z] = f;
    [
        y,
        z,
        x, // band 1
        x * y,
        y * z,
        1.0,
        x * z,
        1.0, // band 2
        y,
        x * y * z,
        y,
        z,
        x,
        z,
        x, // band 3
        x * y,
        y * z,
        x * y,
        y * z,
        1.0,
        x * z,
        1.0,
        x * z,
        y, // band 4
    ]
}

/// Mirror a scene's axes in place: positions by `f`, quaternions (w,x,y,z) by
/// (1, fy*fz, fx*fz, fx*fy) and SH coefficients by [`sh_flips`]. With two flips this is a
/// rotation by 180 degrees about the third axis (RUB <-> RDF, RDF <-> glTF's LUF).
pub fn flip_axes(scene: &mut Scene, f: [f32; 3]) {
    use rayon::prelude::*;
    let k = scene.sh_rest_k();
    let t = ROWS_PER_TASK;
    let q = [1.0, f[1] * f[2], f[0] * f[2], f[0] * f[1]];
    let sh = sh_flips(f);
    scene.means.par_chunks_mut(3 * t).for_each(|m| {
        for p in m.chunks_exact_mut(3) {
            for d in 0..3 {
                p[d] *= f[d];
            }
        }
    });
    scene.quats.par_chunks_mut(4 * t).for_each(|m| {
        for r in m.chunks_exact_mut(4) {
            for d in 1..4 {
                r[d] *= q[d];
            }
        }
    });
    if k > 0 {
        scene.sh_rest.par_chunks_mut(3 * k * t).for_each(|m| {
            for row in m.chunks_exact_mut(3 * k) {
                for (j, s) in sh.iter().take(k).enumerate() {
                    for c in 0..3 {
                        row[j * 3 + c] *= s;
                    }
                }
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rub_rdf_flips_match_the_spz_table() {
        let f = sh_flips([1.0, -1.0, -1.0]);
        assert_eq!(f, spz::SH_FLIP_RUB_RDF);
    }

    #[test]
    fn alpha_extremes_give_finite_logits() {
        assert!(logit_u8(0).is_finite() && logit_u8(0) < -13.0);
        assert!(logit_u8(255).is_finite() && logit_u8(255) > 13.0);
        assert!((logit_u8(128) - (128.0f32 / 127.0).ln()).abs() < 1e-6);
        for a in 0..=255u8 {
            assert_eq!(to_u8(sigmoid(logit_u8(a)) * 255.0), a);
        }
    }
}
