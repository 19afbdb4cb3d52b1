//! Reading an INRIA-layout PLY.
//!
//! Binary bodies are read in fixed-size tasks of rows: each task reads its own byte range with a
//! positioned read (`pread`) into a scratch buffer, casts it to float32 rows if the file is not
//! float32 little-endian, and decodes it tile by tile (cache-sized) into its disjoint part of the
//! output arrays, normalising quaternions and checking finiteness on the way. The tasks run on the
//! rayon pool, so one thread's read overlaps another's decode, and there is exactly one pass over
//! the data. Peak memory is the output arrays plus one scratch buffer per thread. Task sizes are
//! fixed, never derived from the thread count, and every row decodes independently, so the
//! result is bit-identical for any number of threads.
use std::fs::File;
use std::io::{BufRead, BufReader, Read, Seek, SeekFrom};
use std::path::Path;

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::scene::Scene;

use super::header::{read_header, Element, Encoding, Header, PropertyKind, ScalarType};
use super::pio;
use super::plan::{plan_vertex, Plan, STANDARD_FIELDS};

/// Rows per parallel task (fixed, so results never depend on the thread count). 2048 rows of the
/// 62-property degree-3 layout are 508 KB, well inside a core's L2.
const ROWS_PER_TASK: usize = 2048;
/// Rows decoded at a time inside a task (16 KB of degree-3 rows: stays in L1 while every field is
/// gathered from it).
const ROWS_PER_TILE: usize = 64;

/// What to do with Gaussians holding NaN or infinite values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum OnInvalid {
    /// Fail with a format error naming the first bad vertex and property.
    #[default]
    Error,
    /// Drop those Gaussians and report how many.
    Drop,
}

/// Facts about a load that a caller may want to report.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct LoadReport {
    /// Format name, e.g. "ply".
    pub format: String,
    /// Gaussians dropped for non-finite values (OnInvalid::Drop).
    pub dropped: usize,
    /// Things the caller should be told about (lossy source formats, skipped or honoured
    /// extension records); the Python binding turns each into a `MorphgsWarning`.
    pub notes: Vec<String>,
}

/// How the bytes of one vertex row become float32 values.
enum Layout {
    /// Every property float32, little-endian: the bytes are the values.
    F32Le,
    /// Every property float32, big-endian: swap the bytes.
    F32Be,
    /// Anything else: cast property by property (exact for every type, then rounded to f32).
    Mixed {
        offsets: Vec<usize>,
        types: Vec<ScalarType>,
        big_endian: bool,
    },
}

/// Read a 3DGS scene from an INRIA-layout PLY file.
pub fn read_ply(path: &Path, on_invalid: OnInvalid) -> Result<(Scene, LoadReport)> {
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    let file_len = file.metadata().map_err(|e| Error::io(path, e))?.len();
    let header = {
        let mut reader = BufReader::with_capacity(64 << 10, &file);
        read_header(&mut reader, path)?
    };
    let Some((vi, vertex)) = header.element("vertex") else {
        let names: Vec<&str> = header.elements.iter().map(|e| e.name.as_str()).collect();
        return Err(Error::format(
            path,
            format!(
                "no 'vertex' element (the file has: {})",
                if names.is_empty() {
                    "no elements".to_owned()
                } else {
                    names.join(", ")
                }
            ),
        ));
    };
    let plan = plan_vertex(vertex, path)?;
    let body_start = header.len as u64;
    let body_len = file_len.saturating_sub(body_start);
    let (mut scene, finite) = match header.encoding {
        Encoding::Ascii => read_ascii(&file, &header, vi, &plan, body_start, body_len, path)?,
        enc => read_binary(
            &file,
            &header,
            vi,
            &plan,
            body_start,
            body_len,
            enc == Encoding::BinaryBigEndian,
            path,
        )?,
    };
    let mut report = LoadReport {
        format: "ply".into(),
        dropped: 0,
        notes: Vec::new(),
    };
    if !finite {
        let bad = scene.invalid_rows();
        match on_invalid {
            OnInvalid::Error => {
                let (prop, value) = first_bad_property(&plan, &scene, bad[0]);
                return Err(Error::format_at(
                    path,
                    "vertex",
                    Some(prop),
                    format!(
                        "vertex {} holds {value} ({} of {} Gaussians have NaN or Inf values; \
                         pass on_invalid=\"drop\" to skip them)",
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

/// The file property of Gaussian `i` that holds the first non-finite value, in file order.
fn first_bad_property<'p>(plan: &'p Plan, scene: &Scene, i: usize) -> (&'p str, f32) {
    let k = scene.sh_rest_k() * 3;
    let values: [&[f32]; STANDARD_FIELDS] = [
        &scene.means[i * 3..i * 3 + 3],
        &scene.sh0[i * 3..i * 3 + 3],
        &scene.opacity_logits[i..i + 1],
        &scene.log_scales[i * 3..i * 3 + 3],
        &scene.quats[i * 4..i * 4 + 4],
        &scene.sh_rest[i * k..i * k + k],
    ];
    let mut best: Option<(usize, &'p str, f32)> = None;
    for (fi, vals) in values.iter().enumerate() {
        for (c, v) in vals.iter().enumerate() {
            let col = plan.fields[fi].cols[c];
            if !v.is_finite() && best.is_none_or(|(b, _, _)| col < b) {
                best = Some((col, plan.property_name(fi, c), *v));
            }
        }
    }
    best.map_or(("?", f32::NAN), |(_, name, v)| (name, v))
}

/// Bytes taken by the rows of element `e` (which precedes the vertex element in a binary file).
fn skip_binary_element(
    reader: &mut BufReader<&File>,
    e: &Element,
    big_endian: bool,
    available: u64,
    path: &Path,
) -> Result<u64> {
    let truncated = || {
        Error::format_at(
            path,
            e.name.clone(),
            None,
            format!(
                "truncated: the file ends inside this element ({} rows declared)",
                e.count
            ),
        )
    };
    if let Some(stride) = e.fixed_stride() {
        let bytes = e.count.saturating_mul(stride as u64);
        if bytes > available {
            return Err(truncated());
        }
        reader
            .seek_relative(bytes as i64)
            .map_err(|err| Error::io(path, err))?;
        return Ok(bytes);
    }
    let mut total = 0u64;
    let mut buf = [0u8; 8];
    for _ in 0..e.count {
        for p in &e.properties {
            let (count, item) = match p.kind {
                PropertyKind::Scalar(t) => (1u64, t),
                PropertyKind::List(ct, it) => {
                    reader
                        .read_exact(&mut buf[..ct.size()])
                        .map_err(|_| truncated())?;
                    total += ct.size() as u64;
                    (ct.read(&buf, big_endian).max(0.0) as u64, it)
                }
            };
            let bytes = count * item.size() as u64;
            if total + bytes > available {
                return Err(truncated());
            }
            reader
                .seek_relative(bytes as i64)
                .map_err(|err| Error::io(path, err))?;
            total += bytes;
        }
    }
    Ok(total)
}

/// One task's rows and its slice of every output array.
struct Task<'a> {
    row0: usize,
    rows: usize,
    outs: Vec<&'a mut [f32]>,
}

/// Split the output arrays into fixed-size row tasks.
fn split_tasks<'a>(plan: &Plan, outs: &'a mut [Vec<f32>], n: usize) -> Vec<Task<'a>> {
    let mut tasks: Vec<Task<'a>> = (0..n.div_ceil(ROWS_PER_TASK))
        .map(|t| Task {
            row0: t * ROWS_PER_TASK,
            rows: ROWS_PER_TASK.min(n - t * ROWS_PER_TASK),
            outs: Vec::with_capacity(plan.fields.len()),
        })
        .collect();
    for (f, out) in plan.fields.iter().zip(outs.iter_mut()) {
        if f.width == 0 {
            for t in &mut tasks {
                t.outs.push(Default::default());
            }
        } else {
            for (t, chunk) in tasks
                .iter_mut()
                .zip(out.chunks_mut(ROWS_PER_TASK * f.width))
            {
                t.outs.push(chunk);
            }
        }
    }
    tasks
}

#[derive(Default)]
struct Scratch {
    rows: Vec<f32>,
    bytes: Vec<u8>,
}

fn read_binary(
    file: &File,
    header: &Header,
    vi: usize,
    plan: &Plan,
    body_start: u64,
    body_len: u64,
    big_endian: bool,
    path: &Path,
) -> Result<(Scene, bool)> {
    let mut skipped = 0u64;
    if vi > 0 {
        let mut reader = BufReader::with_capacity(64 << 10, file);
        reader
            .seek(SeekFrom::Start(body_start))
            .map_err(|e| Error::io(path, e))?;
        for e in &header.elements[..vi] {
            skipped += skip_binary_element(
                &mut reader,
                e,
                big_endian,
                body_len.saturating_sub(skipped),
                path,
            )?;
        }
    }
    let vertex = &header.elements[vi];
    // plan_vertex rejected list properties, so every row has the same size.
    let offsets = vertex.offsets().unwrap_or_default();
    let types: Vec<ScalarType> = vertex
        .properties
        .iter()
        .map(|p| match p.kind {
            PropertyKind::Scalar(t) | PropertyKind::List(_, t) => t,
        })
        .collect();
    let nprops = types.len();
    let stride = vertex.fixed_stride().unwrap_or(0).max(1);
    let available = body_len.saturating_sub(skipped);
    let whole_rows = available / stride as u64;
    if vertex.count > whole_rows {
        let want = vertex.count.saturating_mul(stride as u64);
        let msg = if vertex.count / 2 > whole_rows.max(1) {
            format!(
                "the header declares {} vertices of {stride} bytes ({want} bytes) but only \
                 {available} bytes of data follow: the file cannot hold that many (at most \
                 {whole_rows})",
                vertex.count
            )
        } else {
            format!(
                "truncated: the file holds {whole_rows} of {} vertices ({available} of {want} \
                 bytes)",
                vertex.count
            )
        };
        return Err(Error::format_at(path, "vertex", None, msg));
    }
    let n = vertex.count as usize;
    let all_f32 = types.iter().all(|&t| t == ScalarType::F32);
    let layout = match (all_f32, big_endian) {
        (true, false) => Layout::F32Le,
        (true, true) => Layout::F32Be,
        _ => Layout::Mixed {
            offsets,
            types,
            big_endian,
        },
    };
    let data_start = body_start + skipped;

    let mut outs = plan.alloc(n);
    let tasks = split_tasks(plan, &mut outs, n);
    let finite = tasks
        .into_par_iter()
        .map_init(Scratch::default, |scratch, mut task| -> Result<bool> {
            let offset = data_start + (task.row0 * stride) as u64;
            let rows = fill_rows(file, offset, task.rows, stride, nprops, &layout, scratch)
                .map_err(|e| {
                    if e.kind() == std::io::ErrorKind::UnexpectedEof {
                        Error::format_at(
                            path,
                            "vertex",
                            None,
                            format!(
                                "truncated: the file ended at vertex {} of {n} (was it shrunk \
                                 while being read?)",
                                task.row0
                            ),
                        )
                    } else {
                        Error::io(path, e)
                    }
                })?;
            let mut finite = true;
            for t0 in (0..task.rows).step_by(ROWS_PER_TILE) {
                let t1 = (t0 + ROWS_PER_TILE).min(task.rows);
                finite &= plan.decode(&rows[t0 * nprops..t1 * nprops], nprops, &mut task.outs, t0);
            }
            Ok(finite)
        })
        .try_reduce(|| true, |a, b| Ok(a && b))?;
    Ok((plan.assemble(outs), finite))
}

/// Read `rows` rows at `offset` and return them as float32 values, `nprops` per row.
fn fill_rows<'s>(
    file: &File,
    offset: u64,
    rows: usize,
    stride: usize,
    nprops: usize,
    layout: &Layout,
    scratch: &'s mut Scratch,
) -> std::io::Result<&'s [f32]> {
    match layout {
        Layout::F32Le | Layout::F32Be => {
            scratch.rows.resize(rows * nprops, 0.0);
            let buf = &mut scratch.rows[..rows * nprops];
            pio::read_exact_at(file, bytemuck::cast_slice_mut(buf), offset)?;
            let swap = matches!(layout, Layout::F32Be) != cfg!(target_endian = "big");
            if swap {
                for v in buf.iter_mut() {
                    *v = f32::from_bits(v.to_bits().swap_bytes());
                }
            }
        }
        Layout::Mixed {
            offsets,
            types,
            big_endian,
        } => {
            scratch.bytes.resize(rows * stride, 0);
            let bytes = &mut scratch.bytes[..rows * stride];
            pio::read_exact_at(file, bytes, offset)?;
            scratch.rows.resize(rows * nprops, 0.0);
            for (dst, src) in scratch
                .rows
                .chunks_exact_mut(nprops)
                .zip(bytes.chunks_exact(stride))
            {
                for ((d, &off), &t) in dst.iter_mut().zip(offsets).zip(types) {
                    *d = t.read(&src[off..], *big_endian) as f32;
                }
            }
        }
    }
    Ok(&scratch.rows[..rows * nprops])
}

fn read_ascii(
    file: &File,
    header: &Header,
    vi: usize,
    plan: &Plan,
    body_start: u64,
    body_len: u64,
    path: &Path,
) -> Result<(Scene, bool)> {
    let vertex = &header.elements[vi];
    let nprops = vertex.properties.len().max(1);
    // Each value needs at least one character and one separator.
    let max_rows = body_len / (2 * nprops as u64) + 1;
    if vertex.count > max_rows {
        return Err(Error::format_at(
            path,
            "vertex",
            None,
            format!(
                "the header declares {} vertices but the {body_len} bytes of ASCII data can hold \
                 at most {max_rows}",
                vertex.count
            ),
        ));
    }
    let mut reader = BufReader::with_capacity(1 << 20, file);
    reader
        .seek(SeekFrom::Start(body_start))
        .map_err(|e| Error::io(path, e))?;
    let mut line = String::new();
    let mut next_line = |line: &mut String, what: &str, i: u64, count: u64| -> Result<()> {
        line.clear();
        match reader.read_line(line) {
            Ok(0) => Err(Error::format_at(
                path,
                what.to_owned(),
                None,
                format!("truncated: read {i} of {count} rows"),
            )),
            Ok(_) => Ok(()),
            Err(e) if e.kind() == std::io::ErrorKind::InvalidData => Err(Error::format_at(
                path,
                what.to_owned(),
                None,
                format!("row {i} is not valid ASCII text"),
            )),
            Err(e) => Err(Error::io(path, e)),
        }
    };
    for e in &header.elements[..vi] {
        for i in 0..e.count {
            next_line(&mut line, &e.name, i, e.count)?;
        }
    }
    let n = vertex.count as usize;
    let mut outs = plan.alloc(n);
    let mut slices: Vec<&mut [f32]> = outs.iter_mut().map(|v| v.as_mut_slice()).collect();
    let mut tile = vec![0f32; ROWS_PER_TILE * nprops];
    let mut finite = true;
    for t0 in (0..n).step_by(ROWS_PER_TILE) {
        let t1 = (t0 + ROWS_PER_TILE).min(n);
        for (i, row) in (t0..t1).zip(tile.chunks_exact_mut(nprops)) {
            next_line(&mut line, "vertex", i as u64, n as u64)?;
            let mut toks = line.split_ascii_whitespace();
            for (j, slot) in row.iter_mut().enumerate() {
                let name = &vertex.properties[j].name;
                let tok = toks.next().ok_or_else(|| {
                    Error::format_at(
                        path,
                        "vertex",
                        Some(name),
                        format!("truncated: vertex {i} has only {j} of {nprops} values"),
                    )
                })?;
                *slot = parse_ascii_number(tok).ok_or_else(|| {
                    Error::format_at(
                        path,
                        "vertex",
                        Some(name),
                        format!("vertex {i}: '{tok}' is not a number"),
                    )
                })? as f32;
            }
        }
        finite &= plan.decode(&tile[..(t1 - t0) * nprops], nprops, &mut slices, t0);
    }
    drop(slices);
    Ok((plan.assemble(outs), finite))
}

/// Parse an ASCII PLY value: Rust's float syntax (which accepts inf, infinity and nan in any
/// case, with a sign) plus integers.
fn parse_ascii_number(tok: &str) -> Option<f64> {
    tok.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ascii_numbers_accept_the_spellings_writers_use() {
        for (s, want) in [("1", 1.0), ("-2.5e-3", -2.5e-3), ("+4", 4.0)] {
            assert_eq!(parse_ascii_number(s), Some(want));
        }
        for s in ["nan", "NaN", "-nan", "inf", "-Infinity", "INF"] {
            assert!(!parse_ascii_number(s).expect(s).is_finite());
        }
        assert_eq!(parse_ascii_number("1,5"), None);
    }
}
