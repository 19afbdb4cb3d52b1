//! Niantic `.spz` (nianticlabs/spz `load-spz.cc`; playcanvas/splat-transform `read-spz.ts`).
//!
//! v2/v3: a gzip stream (or, as splat-transform's "raw" variant, the same bytes uncompressed)
//! holding a 16-byte header — magic 0x5053474e "NGSP", version u32, numPoints u32, shDegree u8,
//! fractionalBits u8, flags u8 (0x1 antialiased, 0x2 extensions follow), reserved u8 — then the
//! attributes one after the other: positions (24-bit signed fixed point, 9 B), alphas (1 B),
//! colours (3 B, dc*0.15*255+127.5), log-scales (3 B, (log+10)*16), rotations (v2: 3 B x,y,z with
//! w >= 0; v3: 4 B smallest-three, 2-bit index + 3 x (sign + 9 bits)) and SH (K*3 B, colour the
//! fastest axis, (v-128)/128).
//!
//! v4: a plain 32-byte header (the same fields, then numStreams u8 at 15, tocByteOffset u32 at 16,
//! 12 reserved bytes), optional extension records up to tocByteOffset, a table of contents of
//! (compressed u64, uncompressed u64) per stream, and one zstd frame per attribute in the order
//! above (5 streams, 6 with SH). v4 rotations are smallest-three.
//!
//! SPZ stores RUB axes (x right, y up, z back); [`SpzAxes::Rdf`] converts to the PLY/OpenCV RDF
//! convention with nianticlabs/spz's `coordinateConverter(RUB, RDF)`: flip y and z of positions,
//! flip the quaternion's y and z, and flip each SH coefficient whose basis function is odd under
//! (y,z) -> (-y,-z).
use std::io::Read;
use std::path::Path;

use rayon::prelude::*;

use super::{
    check_finite, logit_u8, read_bounded, sigmoid, to_u8, unit_quat, SpzAxes, ROWS_PER_TASK,
};
use crate::error::{Error, Result};
use crate::ply::{atomic_write, LoadReport};
use crate::scene::{sh_rest_count, Scene, SceneView};

pub const MAGIC: u32 = 0x5053_474e;
pub const GZIP_MAGIC: [u8; 2] = [0x1f, 0x8b];
const COLOR_SCALE: f32 = 0.15;
const FLAG_EXTENSIONS: u8 = 0x2;
const SQRT1_2: f32 = std::f32::consts::FRAC_1_SQRT_2;
/// deflate cannot expand more than 1032:1; anything claiming more is lying.
const GZIP_MAX_RATIO: u64 = 1032;
/// zstd's densest encoding (RLE blocks) stays far below this ratio.
const ZSTD_MAX_RATIO: u64 = 32_768;
/// Extension records (v2/v3) may sit between header and payload; allow this much beyond the
/// payload the header's count justifies.
const EXTENSION_SLACK: u64 = 1 << 16;

/// Per-coefficient SH sign flips between RUB and RDF (x kept, y and z flipped), from
/// nianticlabs/spz `coordinateConverter`: {y, z, x, xy, yz, 1, xz, 1, y, xyz, y, z, x, z, x,
/// xy, yz, xy, yz, 1, xz, 1, xz, y} with x = 1, y = z = -1.
pub const SH_FLIP_RUB_RDF: [f32; 24] = [
    -1.0, -1.0, 1.0, // band 1
    -1.0, 1.0, 1.0, -1.0, 1.0, // band 2
    -1.0, 1.0, -1.0, -1.0, 1.0, -1.0, 1.0, // band 3
    -1.0, 1.0, -1.0, 1.0, 1.0, -1.0, 1.0, -1.0, -1.0, // band 4
];

/// The fixed-size header fields shared by every version.
#[derive(Debug, Clone, Copy)]
struct Header {
    version: u32,
    num_points: u32,
    sh_degree: u8,
    fractional_bits: u8,
    flags: u8,
}

fn u32_at(b: &[u8], off: usize) -> u32 {
    let mut a = [0u8; 4];
    a.copy_from_slice(&b[off..off + 4]);
    u32::from_le_bytes(a)
}

fn u64_at(b: &[u8], off: usize) -> u64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[off..off + 8]);
    u64::from_le_bytes(a)
}

fn parse_header(b: &[u8], path: &Path) -> Result<Header> {
    if b.len() < 16 {
        return Err(Error::format(
            path,
            format!(
                "SPZ header is 16 bytes but only {} are present (truncated)",
                b.len()
            ),
        ));
    }
    let magic = u32_at(b, 0);
    if magic != MAGIC {
        return Err(Error::format(
            path,
            format!("not an SPZ stream: magic 0x{magic:08x}, expected 0x{MAGIC:08x} (\"NGSP\")"),
        ));
    }
    let h = Header {
        version: u32_at(b, 4),
        num_points: u32_at(b, 8),
        sh_degree: b[12],
        fractional_bits: b[13],
        flags: b[14],
    };
    if !(1..=4).contains(&h.version) {
        return Err(Error::format(
            path,
            format!("unsupported SPZ version {} (supported: 1-4)", h.version),
        ));
    }
    if h.sh_degree > 4 {
        return Err(Error::format(
            path,
            format!("SPZ header declares SH degree {} (at most 4)", h.sh_degree),
        ));
    }
    if h.fractional_bits > 23 {
        return Err(Error::format(
            path,
            format!(
                "SPZ header declares {} fractional bits for 24-bit positions",
                h.fractional_bits
            ),
        ));
    }
    Ok(h)
}

impl Header {
    fn rotation_bytes(&self) -> u64 {
        if self.version < 3 {
            3
        } else {
            4
        }
    }

    /// v1 stored positions as three float16 (never released, still read by the reference).
    fn position_bytes(&self) -> u64 {
        if self.version == 1 {
            6
        } else {
            9
        }
    }

    fn sh_bytes(&self) -> u64 {
        sh_rest_count(self.sh_degree) as u64 * 3
    }

    /// Byte size of each attribute section, in file order.
    fn sections(&self) -> [(&'static str, u64); 6] {
        let n = self.num_points as u64;
        [
            ("positions", n * self.position_bytes()),
            ("alphas", n),
            ("colors", n * 3),
            ("scales", n * 3),
            ("rotations", n * self.rotation_bytes()),
            ("sh", n * self.sh_bytes()),
        ]
    }

    fn payload_bytes(&self) -> u64 {
        self.sections().iter().map(|(_, b)| b).sum()
    }
}

/// Read a `.spz` file of any supported version. Every decoded value is a finite function of
/// integer fields, so there is never a Gaussian to drop for NaN/Inf (no `on_invalid`).
pub fn read(path: &Path, axes: SpzAxes) -> Result<(Scene, LoadReport)> {
    let data = super::read_file(path)?;
    let (mut scene, notes) = decode_with_notes(&data, path, axes)?;
    drop(data);
    scene.normalize_quats();
    Ok((
        scene,
        LoadReport {
            format: "spz".into(),
            dropped: 0,
            notes,
        },
    ))
}

/// Decode the bytes of a `.spz` file (`path` only names it in errors).
pub fn decode_bytes(data: &[u8], path: &Path, axes: SpzAxes) -> Result<Scene> {
    decode_with_notes(data, path, axes).map(|(s, _)| s)
}

/// Decode a `.spz`, returning the scene and what its extension records said.
pub fn decode_with_notes(data: &[u8], path: &Path, axes: SpzAxes) -> Result<(Scene, Vec<String>)> {
    let (mut scene, ext) = if data.starts_with(&GZIP_MAGIC) {
        decode_gzip(data, path)?
    } else if data.len() >= 8 && u32_at(data, 0) == MAGIC && u32_at(data, 4) == 4 {
        decode_v4(data, path)?
    } else {
        let h = parse_header(data, path)?;
        if h.version == 4 {
            return Err(Error::format(path, "SPZ v4 header is malformed"));
        }
        decode_legacy_body(&h, &data[16..], path)?
    };
    let records = super::spz_ext::parse(ext, path)?;
    let stored = super::spz_ext::stored_axes(&records, path)?;
    let mut notes = super::spz_ext::notes(&records, path);
    match axes {
        SpzAxes::Rdf => super::spz_ext::to_rdf(&mut scene, stored, path)?,
        SpzAxes::Stored => {
            if stored != super::spz_ext::CoordinateSystem::RUB {
                notes.push(format!(
                    "{}: .spz data is stored in {:?} axes (SPZ_ADOBE_coordinate_system); kept \
                     as stored",
                    path.display(),
                    stored
                ));
            }
        }
    }
    Ok((scene, notes))
}

fn decode_gzip(data: &[u8], path: &Path) -> Result<(Scene, Vec<u8>)> {
    let mut gz = flate2::read::GzDecoder::new(data);
    let mut head = [0u8; 16];
    let mut got = 0;
    while got < 16 {
        match gz.read(&mut head[got..]) {
            Ok(0) => break,
            Ok(k) => got += k,
            Err(e) => {
                return Err(Error::format(
                    path,
                    format!("gzip stream is corrupt or truncated before the SPZ header ({e})"),
                ))
            }
        }
    }
    let h = parse_header(&head[..got], path)?;
    if h.version == 4 {
        return Err(Error::format(
            path,
            "SPZ v4 must not be gzip-compressed (its streams are zstd)",
        ));
    }
    let payload = h.payload_bytes();
    let max_plain = (data.len() as u64).saturating_mul(GZIP_MAX_RATIO);
    if payload > max_plain {
        return Err(Error::format(
            path,
            format!(
                "SPZ header declares {} points ({payload} bytes of data) but a {}-byte gzip \
                 stream can hold at most {max_plain} bytes",
                h.num_points,
                data.len()
            ),
        ));
    }
    let slack = if h.flags & FLAG_EXTENSIONS != 0 {
        EXTENSION_SLACK
    } else {
        0
    };
    let (body, more) = read_bounded(gz, payload, payload + slack, path, "gzip stream")?;
    if more {
        return Err(Error::format(
            path,
            format!(
                "gzip stream holds more data than the {} points the SPZ header declares \
                 ({payload} bytes)",
                h.num_points
            ),
        ));
    }
    decode_legacy_body(&h, &body, path)
}

/// v1-v3 body after the 16-byte header: the payload, then (flag 0x2) extension records, as
/// nianticlabs/spz `serializePackedGaussians` writes them.
fn decode_legacy_body(h: &Header, body: &[u8], path: &Path) -> Result<(Scene, Vec<u8>)> {
    let payload = h.payload_bytes();
    let len = body.len() as u64;
    if len < payload {
        return Err(Error::format(
            path,
            format!(
                "truncated: the SPZ header declares {} points needing {payload} bytes but only \
                 {len} follow the header",
                h.num_points
            ),
        ));
    }
    let skip = len - payload;
    if skip > 0 && h.flags & FLAG_EXTENSIONS == 0 {
        return Err(Error::format(
            path,
            format!(
                "{skip} bytes beyond the {} points the SPZ header declares (lying count?)",
                h.num_points
            ),
        ));
    }
    let mut sections = Vec::with_capacity(6);
    let mut off = 0usize;
    for (_, size) in h.sections() {
        sections.push(&body[off..off + size as usize]);
        off += size as usize;
    }
    let ext = if h.flags & FLAG_EXTENSIONS != 0 {
        body[off..].to_vec()
    } else {
        Vec::new()
    };
    Ok((unpack(h, &sections), ext))
}

fn decode_v4(data: &[u8], path: &Path) -> Result<(Scene, Vec<u8>)> {
    if data.len() < 32 {
        return Err(Error::format(
            path,
            format!("SPZ v4 header is 32 bytes but the file has {}", data.len()),
        ));
    }
    let h = parse_header(data, path)?;
    let num_streams = data[15] as usize;
    let toc = u32_at(data, 16) as usize;
    // the reference writer skips empty streams (SH at degree 0, everything when there are no
    // points)
    let sections: Vec<(&str, u64)> = h.sections().into_iter().filter(|s| s.1 > 0).collect();
    let want = sections.len();
    if num_streams != want {
        return Err(Error::format(
            path,
            format!(
                "SPZ v4 header declares {num_streams} streams; {} points of SH degree {} need \
                 {want}",
                h.num_points, h.sh_degree
            ),
        ));
    }
    let toc_end = toc.saturating_add(16 * num_streams);
    if toc < 32 || toc_end > data.len() {
        return Err(Error::format(
            path,
            format!(
                "SPZ v4 table of contents at byte {toc} ({num_streams} entries) lies outside \
                 the {}-byte file",
                data.len()
            ),
        ));
    }
    let mut src = toc_end;
    let mut plan = Vec::with_capacity(want);
    for (i, (name, expected)) in sections.iter().take(want).enumerate() {
        let compressed = u64_at(data, toc + 16 * i);
        let plain = u64_at(data, toc + 16 * i + 8);
        if plain != *expected {
            return Err(Error::format(
                path,
                format!(
                    "SPZ v4 stream '{name}' declares {plain} bytes but {} points need {expected}",
                    h.num_points
                ),
            ));
        }
        let end = (src as u64).saturating_add(compressed);
        if end > data.len() as u64 {
            return Err(Error::format(
                path,
                format!(
                    "truncated: SPZ v4 stream '{name}' needs bytes {src}..{end} but the file has \
                     {}",
                    data.len()
                ),
            ));
        }
        if plain > compressed.saturating_mul(ZSTD_MAX_RATIO) + 1024 {
            return Err(Error::format(
                path,
                format!(
                    "SPZ v4 stream '{name}': {compressed} compressed bytes cannot hold {plain} \
                     (header declares {} points)",
                    h.num_points
                ),
            ));
        }
        plan.push((*name, src, end as usize, plain));
        src = end as usize;
    }
    if src != data.len() {
        return Err(Error::format(
            path,
            format!(
                "{} bytes after the last SPZ v4 stream (the table of contents does not \
                 describe the file)",
                data.len() - src
            ),
        ));
    }
    let decoded: Vec<Vec<u8>> = plan
        .par_iter()
        .map(|&(name, a, b, plain)| -> Result<Vec<u8>> {
            let what = format!("SPZ v4 stream '{name}'");
            let dec = zstd::stream::read::Decoder::with_buffer(&data[a..b]).map_err(|e| {
                Error::format(path, format!("{what}: cannot start zstd decoding ({e})"))
            })?;
            let (out, more) = read_bounded(dec, plain, plain, path, &what)?;
            if more || out.len() as u64 != plain {
                return Err(Error::format(
                    path,
                    format!(
                        "{what}: zstd data decompresses to {}{} bytes, the table of contents \
                         says {plain}",
                        if more { "more than " } else { "" },
                        out.len()
                    ),
                ));
            }
            Ok(out)
        })
        .collect::<Result<_>>()?;
    let mut it = decoded.iter();
    let refs: Vec<&[u8]> = h
        .sections()
        .iter()
        .map(|s| {
            if s.1 > 0 {
                it.next().map_or(&[][..], Vec::as_slice)
            } else {
                &[][..]
            }
        })
        .collect();
    let ext = if h.flags & FLAG_EXTENSIONS != 0 {
        data[32..toc].to_vec()
    } else {
        Vec::new()
    };
    Ok((unpack(&h, &refs), ext))
}

/// Decode the six attribute sections (exact sizes checked by the caller) in the stored axes.
fn unpack(h: &Header, s: &[&[u8]]) -> Scene {
    let n = h.num_points as usize;
    let k = sh_rest_count(h.sh_degree);
    let mut out = Scene::zeroed(n, h.sh_degree);
    let (pos, alpha, col, scl, rot, sh) = (s[0], s[1], s[2], s[3], s[4], s[5]);
    let inv = 1.0 / (1u32 << h.fractional_bits) as f32;
    let t = ROWS_PER_TASK;
    let pb = h.position_bytes() as usize / 3;
    out.means
        .par_chunks_mut(3 * t)
        .zip(pos.par_chunks(3 * pb * t))
        .for_each(|(m, p)| {
            for (v, b) in m.iter_mut().zip(p.chunks_exact(pb)) {
                if pb == 2 {
                    *v = super::npy::f16_to_f32(u16::from_le_bytes([b[0], b[1]]));
                    continue;
                }
                let raw = (b[0] as u32) | (b[1] as u32) << 8 | (b[2] as u32) << 16;
                // sign-extend the 24-bit value
                let fixed = ((raw << 8) as i32) >> 8;
                *v = fixed as f32 * inv;
            }
        });
    out.opacity_logits
        .par_chunks_mut(t)
        .zip(alpha.par_chunks(t))
        .for_each(|(o, a)| {
            for (v, &b) in o.iter_mut().zip(a) {
                *v = logit_u8(b);
            }
        });
    out.sh0
        .par_chunks_mut(3 * t)
        .zip(col.par_chunks(3 * t))
        .for_each(|(o, c)| {
            for (v, &b) in o.iter_mut().zip(c) {
                *v = (b as f32 / 255.0 - 0.5) / COLOR_SCALE;
            }
        });
    out.log_scales
        .par_chunks_mut(3 * t)
        .zip(scl.par_chunks(3 * t))
        .for_each(|(o, c)| {
            for (v, &b) in o.iter_mut().zip(c) {
                *v = b as f32 / 16.0 - 10.0;
            }
        });
    let rb = h.rotation_bytes() as usize;
    out.quats
        .par_chunks_mut(4 * t)
        .zip(rot.par_chunks(rb * t))
        .for_each(|(o, r)| {
            for (q, b) in o.chunks_exact_mut(4).zip(r.chunks_exact(rb)) {
                let xyzw = if rb == 3 {
                    unpack_first_three(b)
                } else {
                    unpack_smallest_three(u32_at(b, 0))
                };
                q.copy_from_slice(&[xyzw[3], xyzw[0], xyzw[1], xyzw[2]]);
            }
        });
    if k > 0 {
        out.sh_rest
            .par_chunks_mut(3 * k * t)
            .zip(sh.par_chunks(3 * k * t))
            .for_each(|(o, c)| {
                for (v, &b) in o.iter_mut().zip(c) {
                    *v = (b as f32 - 128.0) / 128.0;
                }
            });
    }
    out
}

/// v2: x, y, z as u8 (q*127.5+127.5) with w >= 0 implied. Returns (x,y,z,w).
fn unpack_first_three(b: &[u8]) -> [f32; 4] {
    let x = b[0] as f32 / 127.5 - 1.0;
    let y = b[1] as f32 / 127.5 - 1.0;
    let z = b[2] as f32 / 127.5 - 1.0;
    let w = (1.0 - (x * x + y * y + z * z)).max(0.0).sqrt();
    [x, y, z, w]
}

/// v3/v4: bits 30..32 index the largest of (x,y,z,w); the other three follow from the highest
/// bits down in index order, each a sign bit and 9 magnitude bits scaled by 1/sqrt(2).
fn unpack_smallest_three(mut comp: u32) -> [f32; 4] {
    const MASK: u32 = (1 << 9) - 1;
    let largest = (comp >> 30) as usize;
    let mut q = [0f32; 4];
    let mut sum = 0.0;
    for i in (0..4).rev() {
        if i != largest {
            let mag = comp & MASK;
            let neg = (comp >> 9) & 1;
            comp >>= 10;
            let v = SQRT1_2 * mag as f32 / MASK as f32;
            q[i] = if neg == 1 { -v } else { v };
            sum += q[i] * q[i];
        }
    }
    q[largest] = (1.0 - sum).max(0.0).sqrt();
    q
}

fn pack_smallest_three(q: [f32; 4]) -> u32 {
    let mut largest = 0;
    for i in 1..4 {
        if q[i].abs() > q[largest].abs() {
            largest = i;
        }
    }
    let negate = q[largest] < 0.0;
    let mut comp = largest as u32;
    for (i, &v) in q.iter().enumerate() {
        if i != largest {
            let neg = ((v < 0.0) ^ negate) as u32;
            let mag = ((511.0 * (v.abs() / SQRT1_2) + 0.5) as u32).min(511);
            comp = (comp << 10) | (neg << 9) | mag;
        }
    }
    comp
}

/// Flip between RUB and RDF in place (the map is its own inverse).
pub fn rub_rdf(scene: &mut Scene) {
    super::flip_axes(scene, [1.0, -1.0, -1.0]);
}

/// The largest fractional-bit count (at most 12, the reference encoder's choice) at which every
/// position fits in 24 signed bits.
fn fractional_bits_for(means: &[f32]) -> Result<u8> {
    let max = means.iter().fold(0f32, |m, v| m.max(v.abs()));
    for fb in (0..=12u8).rev() {
        if (max * (1u32 << fb) as f32).round() <= 8_388_607.0 {
            return Ok(fb);
        }
    }
    Err(Error::InvalidArgument(format!(
        "cannot write .spz: a position coordinate of magnitude {max} does not fit in 24-bit \
         fixed point"
    )))
}

/// The uncompressed v3 bytes (header and payload) for a scene given in `axes`.
pub fn encode_v3(scene: &SceneView<'_>, axes: SpzAxes) -> Result<Vec<u8>> {
    check_finite(scene, ".spz")?;
    let n = scene.len();
    if n > u32::MAX as usize {
        return Err(Error::InvalidArgument(format!(
            "cannot write .spz: {n} Gaussians exceed the format's 32-bit count"
        )));
    }
    let k = scene.sh_rest_k();
    let fb = fractional_bits_for(scene.means)?;
    let flip = axes == SpzAxes::Rdf;
    let (fy, fz) = if flip { (-1.0, -1.0) } else { (1.0, 1.0) };
    let h = Header {
        version: 3,
        num_points: n as u32,
        sh_degree: scene.sh_degree,
        fractional_bits: fb,
        flags: 0,
    };
    let mut out = Vec::with_capacity(16 + h.payload_bytes() as usize);
    out.extend_from_slice(&MAGIC.to_le_bytes());
    out.extend_from_slice(&3u32.to_le_bytes());
    out.extend_from_slice(&(n as u32).to_le_bytes());
    out.extend_from_slice(&[h.sh_degree, fb, 0, 0]);
    let t = ROWS_PER_TASK;
    let scale = (1u32 << fb) as f32;

    let mut pos = vec![0u8; n * 9];
    pos.par_chunks_mut(9 * t)
        .zip(scene.means.par_chunks(3 * t))
        .for_each(|(o, m)| {
            for (b, p) in o.chunks_exact_mut(9).zip(m.chunks_exact(3)) {
                for (d, f) in [1.0, fy, fz].iter().enumerate() {
                    let fixed = (f * p[d] * scale).round() as i32;
                    b[d * 3..d * 3 + 3].copy_from_slice(&fixed.to_le_bytes()[..3]);
                }
            }
        });
    out.extend_from_slice(&pos);
    drop(pos);
    out.extend(
        scene
            .opacity_logits
            .iter()
            .map(|&l| to_u8(sigmoid(l) * 255.0)),
    );
    out.extend(
        scene
            .sh0
            .iter()
            .map(|&c| to_u8(c * (COLOR_SCALE * 255.0) + 0.5 * 255.0)),
    );
    out.extend(scene.log_scales.iter().map(|&s| to_u8((s + 10.0) * 16.0)));
    let mut rot = vec![0u8; n * 4];
    rot.par_chunks_mut(4 * t)
        .zip(scene.quats.par_chunks(4 * t))
        .for_each(|(o, q)| {
            for (b, q) in o.chunks_exact_mut(4).zip(q.chunks_exact(4)) {
                let [w, x, y, z] = unit_quat(q);
                b.copy_from_slice(&pack_smallest_three([x, y * fy, z * fz, w]).to_le_bytes());
            }
        });
    out.extend_from_slice(&rot);
    drop(rot);
    if k > 0 {
        let mut sh = vec![0u8; n * k * 3];
        sh.par_chunks_mut(3 * k * t)
            .zip(scene.sh_rest.par_chunks(3 * k * t))
            .for_each(|(o, s)| {
                for (ob, row) in o.chunks_exact_mut(3 * k).zip(s.chunks_exact(3 * k)) {
                    for j in 0..k {
                        let f = if flip { SH_FLIP_RUB_RDF[j] } else { 1.0 };
                        for c in 0..3 {
                            ob[j * 3 + c] = to_u8(f * row[j * 3 + c] * 128.0 + 128.0);
                        }
                    }
                }
            });
        out.extend_from_slice(&sh);
    }
    Ok(out)
}

/// zstd level of the v4 streams (nianticlabs/spz `compressZstd` uses 12).
pub const ZSTD_LEVEL: i32 = 12;

/// The bytes of a `.spz` v4 file: the v3 attribute sections, each its own zstd frame (empty ones
/// skipped, as the reference writer does), behind a 32-byte header and a table of contents.
pub fn encode_v4(scene: &SceneView<'_>, axes: SpzAxes) -> Result<Vec<u8>> {
    let v3 = encode_v3(scene, axes)?;
    let h = parse_header(&v3, Path::new("<memory>"))?;
    let mut parts = Vec::with_capacity(6);
    let mut off = 16usize;
    for (_, size) in h.sections() {
        if size > 0 {
            parts.push(&v3[off..off + size as usize]);
        }
        off += size as usize;
    }
    let frames: Vec<Vec<u8>> = parts
        .par_iter()
        .map(|p| zstd::bulk::compress(p, ZSTD_LEVEL))
        .collect::<std::io::Result<_>>()
        .map_err(|e| Error::InvalidArgument(format!("zstd compression failed: {e}")))?;
    let mut out =
        Vec::with_capacity(32 + 16 * frames.len() + frames.iter().map(Vec::len).sum::<usize>());
    out.extend_from_slice(&MAGIC.to_le_bytes());
    out.extend_from_slice(&4u32.to_le_bytes());
    out.extend_from_slice(&h.num_points.to_le_bytes());
    out.extend_from_slice(&[h.sh_degree, h.fractional_bits, 0, frames.len() as u8]);
    out.extend_from_slice(&32u32.to_le_bytes());
    out.extend_from_slice(&[0u8; 12]);
    for (f, p) in frames.iter().zip(&parts) {
        out.extend_from_slice(&(f.len() as u64).to_le_bytes());
        out.extend_from_slice(&(p.len() as u64).to_le_bytes());
    }
    for f in &frames {
        out.extend_from_slice(f);
    }
    Ok(out)
}

/// Write a scene as `.spz` v3 (gzip), atomically. `axes` says what the scene's axes are:
/// [`SpzAxes::Rdf`] (PLY/OpenCV, converted to the file's RUB) or [`SpzAxes::Stored`] (already RUB).
pub fn write(path: &Path, scene: &SceneView<'_>, axes: SpzAxes) -> Result<()> {
    write_version(path, scene, axes, 3)
}

/// Write a scene as `.spz` of `version` 3 (gzip, the widest viewer support) or 4 (zstd streams,
/// nianticlabs/spz's current default), atomically.
pub fn write_version(
    path: &Path,
    scene: &SceneView<'_>,
    axes: SpzAxes,
    version: u32,
) -> Result<()> {
    match version {
        3 => {
            let raw = encode_v3(scene, axes)?;
            atomic_write(path, |w| {
                let mut gz = flate2::write::GzEncoder::new(w, flate2::Compression::default());
                std::io::Write::write_all(&mut gz, &raw)?;
                gz.finish()?;
                Ok(())
            })
        }
        4 => {
            let bytes = encode_v4(scene, axes)?;
            atomic_write(path, |w| w.write_all(&bytes))
        }
        v => Err(Error::InvalidArgument(format!(
            "cannot write .spz version {v}: morphgs writes 3 (gzip) or 4 (zstd)"
        ))),
    }
}

#[cfg(test)]
mod tests;
