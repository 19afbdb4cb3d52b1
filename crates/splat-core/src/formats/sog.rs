//! PlayCanvas SOG ("spatially ordered Gaussians"): a `meta.json` plus lossless WebP textures,
//! one texel per Gaussian in row-major texel order (playcanvas/splat-transform `read-sog.ts`,
//! `read-sog-v1.ts`, `write-sog.ts`). Delivered as a `.sog` ZIP of those files, or unbundled as a
//! folder holding `meta.json` and the textures. The axes are the PLY's own (RDF).
//!
//! Version 2 (`"version": 2`):
//! - `means`: `means_l.webp` / `means_u.webp` hold the low / high byte of a 16-bit value per axis
//!   (RGB); x = inv_log(mins + (maxs - mins) * v / 65535), inv_log(v) = sign(v) (e^|v| - 1);
//! - `quats`: RGB are the three smallest components of (w,x,y,z), byte/255*2-1 scaled by
//!   1/sqrt(2), A = 252 + index of the largest (which is rebuilt positive);
//! - `scales`: RGB index a 256-entry `codebook` of log-scales;
//! - `sh0`: RGB index a `codebook` of DC coefficients, A is the opacity, sigmoid * 255;
//! - `shN` (optional): `shN_labels.webp` holds a 16-bit palette index (R + 256 G) per Gaussian,
//!   `shN_centroids.webp` holds 64 palette entries per row, each `coeffs` texels wide, whose RGB
//!   bytes index `codebook`; `bands` gives the degree and `count` the palette size.
//!
//! Version 1 (no `version` key; still read by the PlayCanvas engine): the same textures, but
//! `means.shape[0]` is the count and scales, DC colour, opacity (a logit in `sh0`'s alpha) and
//! SH are linear between per-channel `mins`/`maxs` instead of codebooks; the SH degree follows
//! from the centroid texture width (192, 512, 960).
use std::io::Cursor;
use std::path::{Component, Path, PathBuf};

use image::ImageDecoder;
use rayon::prelude::*;
use serde_json::Value;

use super::zip::Zip;
use super::{finish, logit_unit, ROWS_PER_TASK};
use crate::error::{Error, Result};
use crate::ply::{LoadReport, OnInvalid};
use crate::scene::{sh_rest_count, Scene};

/// WebP's largest side.
const MAX_SIDE: u64 = 16_383;
const SQRT2: f32 = std::f32::consts::SQRT_2;
/// Positions of the three stored components for each largest-component index (w,x,y,z order).
const QUAT_IDX: [[usize; 3]; 4] = [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]];

/// Where the files of one SOG scene come from.
enum Source<'a> {
    Zip { zip: Zip<'a>, prefix: String },
    Dir(PathBuf),
}

impl Source<'_> {
    fn load(&self, name: &str, report_path: &Path) -> Result<Vec<u8>> {
        match self {
            Source::Zip { zip, prefix } => zip.read(&format!("{prefix}{name}")),
            Source::Dir(dir) => {
                let rel = Path::new(name);
                if rel.is_absolute() || rel.components().any(|c| !matches!(c, Component::Normal(_)))
                {
                    return Err(Error::format_at(
                        report_path,
                        "meta.json",
                        None,
                        format!("texture name '{name}' must be a plain relative file name"),
                    ));
                }
                let p = dir.join(rel);
                std::fs::read(&p).map_err(|e| Error::io(&p, e))
            }
        }
    }
}

/// A decoded texture: RGBA8, row-major.
struct Texture {
    width: usize,
    height: usize,
    rgba: Vec<u8>,
}

/// Decode a WebP texture, checking its size before allocating: it must hold at least
/// `min_texels` and (for per-Gaussian textures) not vastly more.
fn decode_webp(
    bytes: &[u8],
    path: &Path,
    name: &str,
    min_texels: u64,
    max_texels: u64,
) -> Result<Texture> {
    let err = |m: String| Error::format_at(path, name, None, m);
    let dec = image::codecs::webp::WebPDecoder::new(Cursor::new(bytes))
        .map_err(|e| err(format!("not a readable WebP image ({e})")))?;
    let (w, h) = dec.dimensions();
    let texels = w as u64 * h as u64;
    if w as u64 > MAX_SIDE || h as u64 > MAX_SIDE || texels < min_texels || texels > max_texels {
        return Err(err(format!(
            "texture is {w}x{h} ({texels} texels); this SOG needs between {min_texels} and \
             {max_texels}"
        )));
    }
    let channels = dec.color_type().channel_count() as usize;
    let mut buf = vec![0u8; texels as usize * channels];
    dec.read_image(&mut buf)
        .map_err(|e| err(format!("corrupt WebP data ({e})")))?;
    let rgba = if channels == 4 {
        buf
    } else {
        let mut out = vec![255u8; texels as usize * 4];
        for (o, i) in out.chunks_exact_mut(4).zip(buf.chunks_exact(channels)) {
            o[..3].copy_from_slice(&i[..3]);
        }
        out
    };
    Ok(Texture {
        width: w as usize,
        height: h as usize,
        rgba,
    })
}

/// Typed access to meta.json with errors naming the key.
struct Meta<'a> {
    v: &'a Value,
    path: &'a Path,
}

impl<'a> Meta<'a> {
    fn err(&self, key: &str, msg: impl Into<String>) -> Error {
        Error::format_at(self.path, "meta.json", Some(key), msg)
    }

    fn get(&self, key: &str) -> Result<&'a Value> {
        let mut v = self.v;
        for part in key.split('.') {
            v = v
                .get(part)
                .ok_or_else(|| self.err(key, "missing (required by the SOG layout)"))?;
        }
        Ok(v)
    }

    fn floats(&self, key: &str, len: Option<usize>) -> Result<Vec<f32>> {
        let arr = self
            .get(key)?
            .as_array()
            .ok_or_else(|| self.err(key, "is not an array"))?;
        if let Some(n) = len {
            if arr.len() != n {
                return Err(self.err(key, format!("holds {} numbers, expected {n}", arr.len())));
            }
        }
        arr.iter()
            .map(|x| {
                x.as_f64()
                    .map(|f| f as f32)
                    .filter(|f| f.is_finite())
                    .ok_or_else(|| self.err(key, format!("holds {x}, not a finite number")))
            })
            .collect()
    }

    fn float(&self, key: &str) -> Result<f32> {
        self.get(key)?
            .as_f64()
            .map(|f| f as f32)
            .filter(|f| f.is_finite())
            .ok_or_else(|| self.err(key, "is not a finite number"))
    }

    fn uint(&self, key: &str) -> Result<u64> {
        self.get(key)?
            .as_u64()
            .ok_or_else(|| self.err(key, "is not a non-negative integer"))
    }

    fn files(&self, key: &str, n: usize) -> Result<Vec<String>> {
        let arr = self
            .get(key)?
            .as_array()
            .ok_or_else(|| self.err(key, "is not an array of file names"))?;
        if arr.len() < n {
            return Err(self.err(key, format!("lists {} files, expected {n}", arr.len())));
        }
        arr.iter()
            .take(n)
            .map(|x| {
                x.as_str()
                    .map(str::to_owned)
                    .ok_or_else(|| self.err(key, "holds a non-string file name"))
            })
            .collect()
    }
}

/// True when `bytes` are a ZIP holding a `meta.json` (at the root or in one folder).
pub fn zip_has_meta(bytes: &[u8], path: &Path) -> bool {
    Zip::open(bytes, path)
        .map(|z| meta_prefix(&z).is_some())
        .unwrap_or(false)
}

fn meta_prefix(z: &Zip<'_>) -> Option<String> {
    if z.entry("meta.json").is_some() {
        return Some(String::new());
    }
    let nested: Vec<&str> = z
        .entries
        .iter()
        .filter_map(|e| e.name.strip_suffix("meta.json"))
        .filter(|p| p.ends_with('/') && p.matches('/').count() == 1)
        .collect();
    (nested.len() == 1).then(|| nested[0].to_owned())
}

/// Read a bundled `.sog` (ZIP bytes of the file at `path`).
pub fn read_zip(bytes: &[u8], path: &Path, on_invalid: OnInvalid) -> Result<(Scene, LoadReport)> {
    let zip = Zip::open(bytes, path)?;
    let prefix = meta_prefix(&zip).ok_or_else(|| {
        Error::format_at(
            path,
            "meta.json",
            None,
            "the archive has no meta.json (not a SOG bundle)",
        )
    })?;
    let src = Source::Zip { zip, prefix };
    let meta = src.load("meta.json", path)?;
    read_source(&src, &meta, path, on_invalid)
}

/// Read an unbundled SOG: `path` is its `meta.json` or the folder holding it.
pub fn read_dir(path: &Path, on_invalid: OnInvalid) -> Result<(Scene, LoadReport)> {
    let meta_path = if path.is_dir() {
        path.join("meta.json")
    } else {
        path.to_path_buf()
    };
    let dir = meta_path
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."));
    let meta = std::fs::read(&meta_path).map_err(|e| Error::io(&meta_path, e))?;
    read_source(&Source::Dir(dir), &meta, &meta_path, on_invalid)
}

/// True when `bytes` parse as a SOG meta.json (an object with `means` and `quats`).
pub fn looks_like_meta(bytes: &[u8]) -> bool {
    serde_json::from_slice::<Value>(bytes)
        .map(|v| v.get("means").is_some() && v.get("quats").is_some())
        .unwrap_or(false)
}

fn read_source(
    src: &Source<'_>,
    meta_bytes: &[u8],
    path: &Path,
    on_invalid: OnInvalid,
) -> Result<(Scene, LoadReport)> {
    let v: Value = serde_json::from_slice(meta_bytes)
        .map_err(|e| Error::format_at(path, "meta.json", None, format!("not valid JSON ({e})")))?;
    let meta = Meta { v: &v, path };
    let version = match v.get("version") {
        None => 1,
        Some(x) => x.as_u64().filter(|&n| n == 2).ok_or_else(|| {
            meta.err(
                "version",
                format!("SOG version {x} is not supported (1 and 2 are)"),
            )
        })?,
    };
    let count = if version == 2 {
        meta.uint("count")?
    } else {
        meta.get("means.shape")?
            .get(0)
            .and_then(Value::as_u64)
            .ok_or_else(|| meta.err("means.shape", "has no leading integer count"))?
    };
    if count > MAX_SIDE * MAX_SIDE {
        return Err(meta.err(
            if version == 2 { "count" } else { "means.shape" },
            format!("{count} Gaussians exceed what 16383x16383 textures can hold"),
        ));
    }
    let n = count as usize;
    // per-Gaussian textures: at least n texels, and not more than the writer's padding allows
    let max_texels = (count + 4 * (count as f64).sqrt() as u64 + 64) * 2 + 4096;
    let texture = |key: &str, i: usize| -> Result<Texture> {
        let name = meta.files(key, i + 1)?.swap_remove(i);
        let bytes = src.load(&name, path)?;
        decode_webp(&bytes, path, &name, count, max_texels)
    };
    let jobs: Vec<(&str, usize)> = vec![
        ("means.files", 0),
        ("means.files", 1),
        ("quats.files", 0),
        ("scales.files", 0),
        ("sh0.files", 0),
    ];
    let tex: Vec<Texture> = jobs
        .par_iter()
        .map(|&(k, i)| texture(k, i))
        .collect::<Result<_>>()?;
    let Ok::<[Texture; 5], _>([lo, hi, quats, scales, sh0]) = tex.try_into() else {
        return Err(Error::format(path, "internal: texture count"));
    };

    let mins = meta.floats("means.mins", Some(3))?;
    let maxs = meta.floats("means.maxs", Some(3))?;
    let shn = read_shn(src, &meta, version, count, max_texels, path)?;
    let degree = shn.as_ref().map_or(0, |s| s.degree);
    let mut s = Scene::zeroed(n, degree);
    decode_means(&mut s.means, &lo, &hi, &mins, &maxs);
    decode_quats(&mut s.quats, &quats);
    if version == 2 {
        let scb = meta.floats("scales.codebook", None)?;
        let ccb = meta.floats("sh0.codebook", None)?;
        for (key, cb) in [("scales.codebook", &scb), ("sh0.codebook", &ccb)] {
            if cb.len() < 256 {
                check_indices(
                    &meta,
                    key,
                    cb.len(),
                    if key == "scales.codebook" {
                        &scales
                    } else {
                        &sh0
                    },
                    n,
                )?;
            }
        }
        lookup3(&mut s.log_scales, &scales, &scb);
        lookup3(&mut s.sh0, &sh0, &ccb);
        for (o, t) in s.opacity_logits.iter_mut().zip(sh0.rgba.chunks_exact(4)) {
            *o = logit_unit(t[3] as f32 / 255.0);
        }
    } else {
        let smin = meta.floats("scales.mins", Some(3))?;
        let smax = meta.floats("scales.maxs", Some(3))?;
        let cmin = meta.floats("sh0.mins", Some(4))?;
        let cmax = meta.floats("sh0.maxs", Some(4))?;
        for (i, t) in scales.rgba.chunks_exact(4).take(n).enumerate() {
            for d in 0..3 {
                s.log_scales[i * 3 + d] = lerp(smin[d], smax[d], t[d]);
            }
        }
        for (i, t) in sh0.rgba.chunks_exact(4).take(n).enumerate() {
            for d in 0..3 {
                s.sh0[i * 3 + d] = lerp(cmin[d], cmax[d], t[d]);
            }
            s.opacity_logits[i] = lerp(cmin[3], cmax[3], t[3]);
        }
    }
    if let Some(sh) = shn {
        decode_shn(&mut s.sh_rest, &sh, n);
    }
    let fmt = if version == 2 { "sog" } else { "sog-v1" };
    finish(s, fmt, "sog", path, on_invalid)
}

#[inline]
fn lerp(lo: f32, hi: f32, b: u8) -> f32 {
    lo + (hi - lo) * (b as f32 / 255.0)
}

/// Error if any of the first `n` texels' RGB index past a short codebook.
fn check_indices(meta: &Meta<'_>, key: &str, len: usize, t: &Texture, n: usize) -> Result<()> {
    for (i, px) in t.rgba.chunks_exact(4).take(n).enumerate() {
        if let Some(b) = px[..3].iter().find(|&&b| b as usize >= len) {
            return Err(meta.err(
                key,
                format!("has {len} entries but Gaussian {i} uses index {b}"),
            ));
        }
    }
    Ok(())
}

fn inv_log(v: f32) -> f32 {
    let e = v.abs().exp() - 1.0;
    if v < 0.0 {
        -e
    } else {
        e
    }
}

fn decode_means(out: &mut [f32], lo: &Texture, hi: &Texture, mins: &[f32], maxs: &[f32]) {
    let t = ROWS_PER_TASK;
    let scale: Vec<f32> = (0..3)
        .map(|d| {
            let r = maxs[d] - mins[d];
            if r == 0.0 {
                1.0
            } else {
                r
            }
        })
        .collect();
    out.par_chunks_mut(3 * t)
        .zip(lo.rgba.par_chunks(4 * t))
        .zip(hi.rgba.par_chunks(4 * t))
        .for_each(|((o, l), h)| {
            for ((p, l), h) in o
                .chunks_exact_mut(3)
                .zip(l.chunks_exact(4))
                .zip(h.chunks_exact(4))
            {
                for d in 0..3 {
                    let v = (l[d] as u32 | (h[d] as u32) << 8) as f32;
                    p[d] = inv_log(mins[d] + scale[d] * (v / 65535.0));
                }
            }
        });
}

fn decode_quats(out: &mut [f32], q: &Texture) {
    let t = ROWS_PER_TASK;
    out.par_chunks_mut(4 * t)
        .zip(q.rgba.par_chunks(4 * t))
        .for_each(|(o, src)| {
            for (q, px) in o.chunks_exact_mut(4).zip(src.chunks_exact(4)) {
                if !(252..=255).contains(&px[3]) {
                    q.copy_from_slice(&[1.0, 0.0, 0.0, 0.0]);
                    continue;
                }
                let largest = (px[3] - 252) as usize;
                let mut v = [0f32; 4];
                let mut sum = 0.0;
                for (k, &slot) in QUAT_IDX[largest].iter().enumerate() {
                    let c = (px[k] as f32 / 255.0 * 2.0 - 1.0) / SQRT2;
                    v[slot] = c;
                    sum += c * c;
                }
                v[largest] = (1.0 - sum).max(0.0).sqrt();
                q.copy_from_slice(&v);
            }
        });
}

fn lookup3(out: &mut [f32], t: &Texture, codebook: &[f32]) {
    for (o, px) in out.chunks_exact_mut(3).zip(t.rgba.chunks_exact(4)) {
        for d in 0..3 {
            o[d] = codebook.get(px[d] as usize).copied().unwrap_or(0.0);
        }
    }
}

/// The higher SH bands: labels per Gaussian and a palette of dequantised centroids.
struct ShN {
    degree: u8,
    coeffs: usize,
    labels: Texture,
    /// Palette entry e, coefficient j, channel c at `palette[(e * coeffs + j) * 3 + c]`.
    palette: Vec<f32>,
    palette_count: usize,
}

fn read_shn(
    src: &Source<'_>,
    meta: &Meta<'_>,
    version: u64,
    count: u64,
    max_texels: u64,
    path: &Path,
) -> Result<Option<ShN>> {
    if meta.v.get("shN").is_none() {
        return Ok(None);
    }
    let files = meta.files("shN.files", 2)?;
    let cbytes = src.load(&files[0], path)?;
    // the palette holds at most 65536 entries of at most 15 texels
    let centroids = decode_webp(&cbytes, path, &files[0], 1, 65_536 * 15)?;
    let lbytes = src.load(&files[1], path)?;
    let labels = decode_webp(&lbytes, path, &files[1], count, max_texels)?;
    let (degree, palette_count, dequant): (u8, usize, Box<dyn Fn(u8) -> f32>) = if version == 2 {
        let bands = meta.uint("shN.bands")?;
        if !(1..=3).contains(&bands) {
            return Err(meta.err("shN.bands", format!("{bands} bands (1-3 are valid)")));
        }
        let cb = meta.floats("shN.codebook", None)?;
        let pc = meta.uint("shN.count")? as usize;
        (
            bands as u8,
            pc,
            Box::new(move |b: u8| cb.get(b as usize).copied().unwrap_or(0.0)),
        )
    } else {
        let degree = match centroids.width {
            192 => 1,
            512 => 2,
            960 => 3,
            w => {
                return Err(Error::format_at(
                    path,
                    files[0].as_str(),
                    None,
                    format!("centroid texture width {w} is none of 192, 512, 960"),
                ))
            }
        };
        let lo = meta.float("shN.mins")?;
        let hi = meta.float("shN.maxs")?;
        let k = sh_rest_count(degree);
        (
            degree,
            centroids.width / k * centroids.height,
            Box::new(move |b: u8| lerp(lo, hi, b)),
        )
    };
    let coeffs = sh_rest_count(degree);
    if centroids.width != 64 * coeffs {
        return Err(Error::format_at(
            path,
            files[0].as_str(),
            None,
            format!(
                "centroid texture is {} wide; SH degree {degree} needs {}",
                centroids.width,
                64 * coeffs
            ),
        ));
    }
    let slots = centroids.width / coeffs * centroids.height;
    let entries = palette_count.min(slots);
    let mut palette = vec![0f32; entries * coeffs * 3];
    for e in 0..entries {
        for j in 0..coeffs {
            let x = (e % 64) * coeffs + j;
            let y = e / 64;
            let px = &centroids.rgba[(y * centroids.width + x) * 4..][..3];
            for c in 0..3 {
                palette[(e * coeffs + j) * 3 + c] = dequant(px[c]);
            }
        }
    }
    Ok(Some(ShN {
        degree,
        coeffs,
        labels,
        palette,
        palette_count: entries,
    }))
}

fn decode_shn(out: &mut [f32], sh: &ShN, n: usize) {
    let row = sh.coeffs * 3;
    let t = ROWS_PER_TASK;
    out.par_chunks_mut(row * t)
        .zip(sh.labels.rgba[..n * 4].par_chunks(4 * t))
        .for_each(|(o, l)| {
            for (dst, px) in o.chunks_exact_mut(row).zip(l.chunks_exact(4)) {
                let label = px[0] as usize | (px[1] as usize) << 8;
                if label < sh.palette_count {
                    dst.copy_from_slice(&sh.palette[label * row..(label + 1) * row]);
                }
            }
        });
}
