//! INRIA-layout PLY: a header parser shared with the other PLY dialects, a streaming reader that
//! finds properties by name (binary little/big-endian and ASCII, any numeric type) and a writer.
//!
//! The reader never trusts the header: the vertex count is checked against the bytes the file can
//! hold before anything is allocated, and data is decoded in fixed-size blocks so peak memory is
//! the output arrays plus one block.
use std::fs::File;
use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};

use rayon::prelude::*;

use crate::error::{Error, Result};
use crate::scene::{normalize_quats, sh_degree_for_rest, sh_rest_count, Scene, SceneView};

/// Longest header we accept; real headers are a few KiB.
const MAX_HEADER_BYTES: usize = 1 << 20;
/// Rows decoded per parallel task (fixed, so results never depend on the thread count).
const ROWS_PER_TASK: usize = 4096;
/// Rows read from disk per block.
const ROWS_PER_BLOCK: usize = ROWS_PER_TASK * 8;

/// How the body of a PLY file is encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Encoding {
    Ascii,
    BinaryLittleEndian,
    BinaryBigEndian,
}

/// PLY scalar types (both the classic and the sized names are accepted).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScalarType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl ScalarType {
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }

    pub fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }

    /// Decode one value at the start of `b` as f64 (exact for every type).
    #[inline(always)]
    pub fn read(self, b: &[u8], big_endian: bool) -> f64 {
        macro_rules! rd {
            ($t:ty, $n:expr) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(&b[..$n]);
                (if big_endian {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                }) as f64
            }};
        }
        match self {
            Self::I8 => b[0] as i8 as f64,
            Self::U8 => b[0] as f64,
            Self::I16 => rd!(i16, 2),
            Self::U16 => rd!(u16, 2),
            Self::I32 => rd!(i32, 4),
            Self::U32 => rd!(u32, 4),
            Self::F32 => rd!(f32, 4),
            Self::F64 => rd!(f64, 8),
        }
    }
}

/// A property of an element: a scalar, or a list with a count type and an item type.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PropertyKind {
    Scalar(ScalarType),
    List(ScalarType, ScalarType),
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Property {
    pub name: String,
    pub kind: PropertyKind,
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Element {
    pub name: String,
    pub count: u64,
    pub properties: Vec<Property>,
}

impl Element {
    /// Bytes per row when every property is a scalar.
    pub fn fixed_stride(&self) -> Option<usize> {
        self.properties
            .iter()
            .map(|p| match p.kind {
                PropertyKind::Scalar(t) => Some(t.size()),
                PropertyKind::List(..) => None,
            })
            .sum()
    }

    pub fn property(&self, name: &str) -> Option<(usize, &Property)> {
        self.properties
            .iter()
            .enumerate()
            .find(|(_, p)| p.name == name)
    }

    /// Byte offset of each scalar property within a row (None for rows with lists).
    pub fn offsets(&self) -> Option<Vec<usize>> {
        let mut off = 0;
        let mut out = Vec::with_capacity(self.properties.len());
        for p in &self.properties {
            match p.kind {
                PropertyKind::Scalar(t) => {
                    out.push(off);
                    off += t.size();
                }
                PropertyKind::List(..) => return None,
            }
        }
        Some(out)
    }
}

/// A parsed PLY header.
#[derive(Debug, Clone)]
pub struct Header {
    pub encoding: Encoding,
    pub elements: Vec<Element>,
    pub comments: Vec<String>,
    /// Bytes up to and including the `end_header` line.
    pub len: usize,
}

impl Header {
    pub fn element(&self, name: &str) -> Option<(usize, &Element)> {
        self.elements
            .iter()
            .enumerate()
            .find(|(_, e)| e.name == name)
    }
}

/// True when `bytes` start like a PLY file.
pub fn is_ply(bytes: &[u8]) -> bool {
    bytes.starts_with(b"ply\n") || bytes.starts_with(b"ply\r\n")
}

/// Parse the header from a reader positioned at the start of the file.
pub fn read_header<R: BufRead>(reader: &mut R, path: &Path) -> Result<Header> {
    let mut raw = Vec::with_capacity(4096);
    let mut lines = Vec::new();
    loop {
        let before = raw.len();
        let n = reader
            .by_ref()
            .take((MAX_HEADER_BYTES - raw.len()) as u64)
            .read_until(b'\n', &mut raw)
            .map_err(|e| Error::io(path, e))?;
        if n == 0 || !raw.ends_with(b"\n") {
            if raw.len() >= MAX_HEADER_BYTES {
                return Err(Error::format(
                    path,
                    "PLY header longer than 1 MiB without 'end_header'",
                ));
            }
            if before == 0 {
                return Err(Error::format(path, "not a PLY file: the file is empty"));
            }
            return Err(Error::format(
                path,
                "PLY header ends before 'end_header' (truncated file?)",
            ));
        }
        let line = String::from_utf8_lossy(&raw[before..])
            .trim_end()
            .to_owned();
        if lines.is_empty() && line != "ply" {
            return Err(Error::format(
                path,
                "not a PLY file: it does not start with the 'ply' magic line",
            ));
        }
        let done = line == "end_header";
        lines.push(line);
        if done {
            break;
        }
    }
    parse_header_lines(&lines, raw.len(), path)
}

fn parse_header_lines(lines: &[String], len: usize, path: &Path) -> Result<Header> {
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    let mut comments = Vec::new();
    for (lineno, line) in lines.iter().enumerate().skip(1) {
        let mut words = line.split_whitespace();
        let Some(keyword) = words.next() else {
            continue;
        };
        let rest: Vec<&str> = words.collect();
        let bad = |msg: String| Error::format(path, format!("header line {}: {msg}", lineno + 1));
        match keyword {
            "format" => {
                encoding = Some(match rest.as_slice() {
                    ["ascii", "1.0"] => Encoding::Ascii,
                    ["binary_little_endian", "1.0"] => Encoding::BinaryLittleEndian,
                    ["binary_big_endian", "1.0"] => Encoding::BinaryBigEndian,
                    _ => {
                        return Err(bad(format!(
                        "unsupported format line '{line}' (expected ascii, binary_little_endian \
                             or binary_big_endian, version 1.0)"
                    )))
                    }
                })
            }
            "comment" | "obj_info" => comments.push(rest.join(" ")),
            "element" => {
                let [name, count] = rest.as_slice() else {
                    return Err(bad(format!("malformed element line '{line}'")));
                };
                let count: u64 = count.parse().map_err(|_| {
                    bad(format!(
                        "element '{name}' has a non-numeric count '{count}'"
                    ))
                })?;
                elements.push(Element {
                    name: (*name).to_owned(),
                    count,
                    properties: Vec::new(),
                });
            }
            "property" => {
                let Some(element) = elements.last_mut() else {
                    return Err(bad("property before any element".into()));
                };
                let prop = match rest.as_slice() {
                    ["list", ct, it, name] => {
                        let (Some(c), Some(i)) = (ScalarType::parse(ct), ScalarType::parse(it))
                        else {
                            return Err(bad(format!("unknown list types in '{line}'")));
                        };
                        Property {
                            name: (*name).to_owned(),
                            kind: PropertyKind::List(c, i),
                        }
                    }
                    [ty, name] => {
                        let Some(t) = ScalarType::parse(ty) else {
                            return Err(bad(format!("unknown property type '{ty}' in '{line}'")));
                        };
                        Property {
                            name: (*name).to_owned(),
                            kind: PropertyKind::Scalar(t),
                        }
                    }
                    _ => return Err(bad(format!("malformed property line '{line}'"))),
                };
                element.properties.push(prop);
            }
            "end_header" => {}
            other => return Err(bad(format!("unknown header keyword '{other}'"))),
        }
    }
    let Some(encoding) = encoding else {
        return Err(Error::format(path, "PLY header has no 'format' line"));
    };
    Ok(Header {
        encoding,
        elements,
        comments,
        len,
    })
}

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
}

/// Where each stored field comes from: destination array, its width, and the source property
/// index for each destination column.
struct Plan {
    fields: Vec<(Dest, usize, Vec<usize>)>,
    sh_degree: u8,
    extra_names: Vec<String>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Dest {
    Means,
    Quats,
    LogScales,
    Opacity,
    Sh0,
    ShRest,
    Extra(usize),
}

const NORMALS: [&str; 3] = ["nx", "ny", "nz"];

fn plan_vertex(element: &Element, path: &Path) -> Result<Plan> {
    let vname = element.name.as_str();
    if let Some(p) = element
        .properties
        .iter()
        .find(|p| matches!(p.kind, PropertyKind::List(..)))
    {
        return Err(Error::format_at(
            path,
            vname,
            Some(&p.name),
            "list properties are not supported in the vertex element",
        ));
    }
    let idx = |name: &str| element.property(name).map(|(i, _)| i);
    let groups: [(Dest, &[&str]); 5] = [
        (Dest::Means, &["x", "y", "z"]),
        (Dest::Sh0, &["f_dc_0", "f_dc_1", "f_dc_2"]),
        (Dest::Opacity, &["opacity"]),
        (Dest::LogScales, &["scale_0", "scale_1", "scale_2"]),
        (Dest::Quats, &["rot_0", "rot_1", "rot_2", "rot_3"]),
    ];
    let missing: Vec<&str> = groups
        .iter()
        .flat_map(|(_, names)| names.iter().copied())
        .filter(|n| idx(n).is_none())
        .collect();
    if !missing.is_empty() {
        return Err(Error::format_at(
            path,
            vname,
            None,
            format!(
                "missing required properties: {} (an INRIA 3DGS PLY has x y z, f_dc_0..2, \
                 opacity, scale_0..2, rot_0..3)",
                missing.join(", ")
            ),
        ));
    }
    let mut fields: Vec<(Dest, usize, Vec<usize>)> = groups
        .iter()
        .map(|(d, names)| {
            let cols: Vec<usize> = names.iter().filter_map(|n| idx(n)).collect();
            (*d, names.len(), cols)
        })
        .collect();

    let n_rest = element
        .properties
        .iter()
        .filter(|p| p.name.starts_with("f_rest_"))
        .count();
    let Some(sh_degree) = (n_rest % 3 == 0)
        .then(|| sh_degree_for_rest(n_rest / 3))
        .flatten()
    else {
        return Err(Error::format_at(
            path,
            vname,
            Some("f_rest_*"),
            format!(
                "{n_rest} f_rest properties is no SH degree (expected 0, 9, 24, 45 or 72 for \
                 degree 0 to 4)"
            ),
        ));
    };
    let k = sh_rest_count(sh_degree);
    let mut rest_cols = vec![0usize; 3 * k];
    for c in 0..3 {
        for j in 0..k {
            let name = format!("f_rest_{}", c * k + j);
            let Some(i) = idx(&name) else {
                return Err(Error::format_at(
                    path,
                    vname,
                    Some(&name),
                    format!("missing (the file has {n_rest} f_rest properties but not this one)"),
                ));
            };
            // file is channel-major (c, j); memory is basis-major, channel-last (j, c)
            rest_cols[j * 3 + c] = i;
        }
    }
    fields.push((Dest::ShRest, 3 * k, rest_cols));

    let known = |n: &str| {
        NORMALS.contains(&n)
            || n.starts_with("f_rest_")
            || groups.iter().any(|(_, names)| names.contains(&n))
    };
    let mut extra_names = Vec::new();
    for (i, p) in element.properties.iter().enumerate() {
        if !known(&p.name) {
            fields.push((Dest::Extra(extra_names.len()), 1, vec![i]));
            extra_names.push(p.name.clone());
        }
    }
    Ok(Plan {
        fields,
        sh_degree,
        extra_names,
    })
}

/// Allocate the output scene for `n` Gaussians.
fn alloc_scene(n: usize, plan: &Plan) -> Scene {
    let k = sh_rest_count(plan.sh_degree);
    Scene {
        means: vec![0.0; n * 3],
        quats: vec![0.0; n * 4],
        log_scales: vec![0.0; n * 3],
        opacity_logits: vec![0.0; n],
        sh0: vec![0.0; n * 3],
        sh_rest: vec![0.0; n * 3 * k],
        sh_degree: plan.sh_degree,
        extras: plan
            .extra_names
            .iter()
            .map(|name| (name.clone(), vec![0.0; n]))
            .collect(),
    }
}

fn dest_mut(scene: &mut Scene, d: Dest) -> &mut Vec<f32> {
    match d {
        Dest::Means => &mut scene.means,
        Dest::Quats => &mut scene.quats,
        Dest::LogScales => &mut scene.log_scales,
        Dest::Opacity => &mut scene.opacity_logits,
        Dest::Sh0 => &mut scene.sh0,
        Dest::ShRest => &mut scene.sh_rest,
        Dest::Extra(i) => &mut scene.extras[i].1,
    }
}

/// Read a 3DGS scene from an INRIA-layout PLY file.
pub fn read_ply(path: &Path, on_invalid: OnInvalid) -> Result<(Scene, LoadReport)> {
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    let file_len = file.metadata().map_err(|e| Error::io(path, e))?.len();
    let mut reader = BufReader::with_capacity(1 << 20, file);
    let header = read_header(&mut reader, path)?;
    let body_len = file_len.saturating_sub(header.len as u64);
    read_ply_body(&mut reader, &header, body_len, path, on_invalid)
}

/// Read the vertex element of a PLY whose header has been read from `reader`.
pub fn read_ply_body<R: BufRead>(
    reader: &mut R,
    header: &Header,
    body_len: u64,
    path: &Path,
    on_invalid: OnInvalid,
) -> Result<(Scene, LoadReport)> {
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
    let mut scene = match header.encoding {
        Encoding::Ascii => read_ascii(reader, header, vi, &plan, body_len, path)?,
        enc => read_binary(
            reader,
            header,
            vi,
            &plan,
            body_len,
            enc == Encoding::BinaryBigEndian,
            path,
        )?,
    };
    normalize_quats(&mut scene.quats);
    let bad = scene.invalid_rows();
    let mut report = LoadReport {
        format: "ply".into(),
        dropped: 0,
    };
    if !bad.is_empty() {
        match on_invalid {
            OnInvalid::Error => {
                let (prop, value) = first_bad_property(&scene, bad[0]);
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
                let mut keep = vec![true; scene.len()];
                for &i in &bad {
                    keep[i] = false;
                }
                scene = scene.filter(&keep);
                report.dropped = bad.len();
            }
        }
    }
    Ok((scene, report))
}

fn first_bad_property(scene: &Scene, i: usize) -> (&'static str, f32) {
    let k = scene.sh_rest_k() * 3;
    let rows: [(&'static str, &[f32]); 6] = [
        ("x/y/z", &scene.means[i * 3..i * 3 + 3]),
        ("rot_*", &scene.quats[i * 4..i * 4 + 4]),
        ("scale_*", &scene.log_scales[i * 3..i * 3 + 3]),
        ("opacity", &scene.opacity_logits[i..i + 1]),
        ("f_dc_*", &scene.sh0[i * 3..i * 3 + 3]),
        ("f_rest_*", &scene.sh_rest[i * k..i * k + k]),
    ];
    for (name, r) in rows {
        if let Some(v) = r.iter().find(|v| !v.is_finite()) {
            return (name, *v);
        }
    }
    ("?", f32::NAN)
}

/// Bytes taken by the rows of element `e` that precede the vertex element (binary only).
fn skip_binary_element<R: BufRead>(
    reader: &mut R,
    e: &Element,
    big_endian: bool,
    path: &Path,
) -> Result<u64> {
    if let Some(stride) = e.fixed_stride() {
        let bytes = e.count.saturating_mul(stride as u64);
        let skipped = std::io::copy(&mut reader.by_ref().take(bytes), &mut std::io::sink())
            .map_err(|err| Error::io(path, err))?;
        if skipped < bytes {
            return Err(Error::format_at(
                path,
                e.name.clone(),
                None,
                "truncated: the file ends inside this element",
            ));
        }
        return Ok(bytes);
    }
    let mut total = 0u64;
    let mut buf = [0u8; 8];
    for _ in 0..e.count {
        for p in &e.properties {
            let (count, item) = match p.kind {
                PropertyKind::Scalar(t) => (1u64, t),
                PropertyKind::List(ct, it) => {
                    read_exact_or(reader, &mut buf[..ct.size()], e, path)?;
                    total += ct.size() as u64;
                    (ct.read(&buf, big_endian).max(0.0) as u64, it)
                }
            };
            for _ in 0..count {
                read_exact_or(reader, &mut buf[..item.size()], e, path)?;
                total += item.size() as u64;
            }
        }
    }
    Ok(total)
}

fn read_exact_or<R: Read>(r: &mut R, buf: &mut [u8], e: &Element, path: &Path) -> Result<()> {
    r.read_exact(buf).map_err(|_| {
        Error::format_at(
            path,
            e.name.clone(),
            None,
            "truncated: the file ends inside this element",
        )
    })
}

fn read_binary<R: BufRead>(
    reader: &mut R,
    header: &Header,
    vi: usize,
    plan: &Plan,
    body_len: u64,
    big_endian: bool,
    path: &Path,
) -> Result<Scene> {
    let mut consumed = 0u64;
    for e in &header.elements[..vi] {
        consumed += skip_binary_element(reader, e, big_endian, path)?;
    }
    let vertex = &header.elements[vi];
    let offsets = vertex.offsets().unwrap_or_default();
    let types: Vec<ScalarType> = vertex
        .properties
        .iter()
        .map(|p| match p.kind {
            PropertyKind::Scalar(t) => t,
            PropertyKind::List(_, t) => t,
        })
        .collect();
    let stride = vertex.fixed_stride().unwrap_or(0).max(1);
    let available = body_len.saturating_sub(consumed);
    let whole_rows = available / stride as u64;
    if vertex.count > whole_rows {
        let msg = if vertex.count / 2 > whole_rows.max(1) {
            format!(
                "the header declares {} vertices of {stride} bytes ({} bytes) but only {available} \
                 bytes of data follow: the file cannot hold that many (at most {whole_rows})",
                vertex.count,
                vertex.count.saturating_mul(stride as u64)
            )
        } else {
            format!(
                "truncated: the header declares {} vertices but the file holds only {whole_rows} \
                 complete ones ({available} of {} bytes)",
                vertex.count,
                vertex.count.saturating_mul(stride as u64)
            )
        };
        return Err(Error::format_at(path, "vertex", None, msg));
    }
    let n = vertex.count as usize;
    let mut scene = alloc_scene(n, plan);
    // Per field: (width, source columns as (offset, type)).
    let columns: Vec<(Dest, usize, Vec<(usize, ScalarType)>)> = plan
        .fields
        .iter()
        .map(|(d, w, cols)| {
            (
                *d,
                *w,
                cols.iter().map(|&c| (offsets[c], types[c])).collect(),
            )
        })
        .collect();
    let all_f32_le = !big_endian && types.iter().all(|&t| t == ScalarType::F32);
    let mut buf = vec![0u8; ROWS_PER_BLOCK.min(n.max(1)) * stride];
    let mut row0 = 0usize;
    while row0 < n {
        let rows = ROWS_PER_BLOCK.min(n - row0);
        let block = &mut buf[..rows * stride];
        reader.read_exact(block).map_err(|e| {
            if e.kind() == std::io::ErrorKind::UnexpectedEof {
                Error::format_at(
                    path,
                    "vertex",
                    None,
                    format!("truncated: read {row0} of {n} vertices"),
                )
            } else {
                Error::io(path, e)
            }
        })?;
        let block: &[u8] = block;
        for (d, w, cols) in &columns {
            if *w == 0 {
                continue;
            }
            let out = &mut dest_mut(&mut scene, *d)[row0 * w..(row0 + rows) * w];
            out.par_chunks_mut(ROWS_PER_TASK * w)
                .zip(block.par_chunks(ROWS_PER_TASK * stride))
                .for_each(|(o, src)| {
                    if all_f32_le {
                        for (orow, srow) in o.chunks_exact_mut(*w).zip(src.chunks_exact(stride)) {
                            for (v, &(off, _)) in orow.iter_mut().zip(cols) {
                                let mut a = [0u8; 4];
                                a.copy_from_slice(&srow[off..off + 4]);
                                *v = f32::from_le_bytes(a);
                            }
                        }
                    } else {
                        for (orow, srow) in o.chunks_exact_mut(*w).zip(src.chunks_exact(stride)) {
                            for (v, &(off, t)) in orow.iter_mut().zip(cols) {
                                *v = t.read(&srow[off..], big_endian) as f32;
                            }
                        }
                    }
                });
        }
        row0 += rows;
    }
    Ok(scene)
}

fn read_ascii<R: BufRead>(
    reader: &mut R,
    header: &Header,
    vi: usize,
    plan: &Plan,
    body_len: u64,
    path: &Path,
) -> Result<Scene> {
    let vertex = &header.elements[vi];
    let nprops = vertex.properties.len().max(1) as u64;
    // Each value needs at least one character and one separator.
    let max_rows = body_len / (2 * nprops).max(1) + 1;
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
    let mut lines = reader.lines();
    let mut next_line = |what: &str, i: u64, count: u64| -> Result<String> {
        match lines.next() {
            Some(Ok(l)) => Ok(l),
            Some(Err(e)) => Err(Error::io(path, e)),
            None => Err(Error::format_at(
                path,
                what.to_owned(),
                None,
                format!("truncated: read {i} of {count} rows"),
            )),
        }
    };
    for e in &header.elements[..vi] {
        for i in 0..e.count {
            next_line(&e.name, i, e.count)?;
        }
    }
    let n = vertex.count as usize;
    let mut scene = alloc_scene(n, plan);
    let mut row = vec![0f64; vertex.properties.len()];
    for i in 0..n {
        let line = next_line("vertex", i as u64, n as u64)?;
        let mut toks = line.split_ascii_whitespace();
        for (j, slot) in row.iter_mut().enumerate() {
            let tok = toks.next().ok_or_else(|| {
                Error::format_at(
                    path,
                    "vertex",
                    Some(&vertex.properties[j].name),
                    format!("truncated: vertex {i} has only {j} values"),
                )
            })?;
            *slot = parse_ascii_number(tok).ok_or_else(|| {
                Error::format_at(
                    path,
                    "vertex",
                    Some(&vertex.properties[j].name),
                    format!("vertex {i}: '{tok}' is not a number"),
                )
            })?;
        }
        for (d, w, cols) in &plan.fields {
            let out = dest_mut(&mut scene, *d);
            for (c, &src) in cols.iter().enumerate() {
                out[i * w + c] = row[src] as f32;
            }
        }
    }
    Ok(scene)
}

fn parse_ascii_number(tok: &str) -> Option<f64> {
    match tok.to_ascii_lowercase().as_str() {
        "nan" | "-nan" => Some(f64::NAN),
        "inf" | "infinity" => Some(f64::INFINITY),
        "-inf" | "-infinity" => Some(f64::NEG_INFINITY),
        _ => tok.parse().ok(),
    }
}

/// Write `scene` in the INRIA layout (binary little-endian float32, zero normals), followed by
/// `extras`, atomically: a temporary file in the same folder is renamed over `path`.
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
    let k = scene.sh_rest_k();
    let mut head =
        String::from("ply\nformat binary_little_endian 1.0\ncomment written by morphgs\n");
    head.push_str(&format!("element vertex {n}\n"));
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
    for name in &names {
        head.push_str(&format!("property float {name}\n"));
    }
    head.push_str("end_header\n");
    let floats = names.len();
    let stride = floats * 4;

    atomic_write(path, |w| {
        w.write_all(head.as_bytes())?;
        let mut buf = vec![0u8; ROWS_PER_BLOCK.min(n.max(1)) * stride];
        let mut row0 = 0;
        while row0 < n {
            let rows = ROWS_PER_BLOCK.min(n - row0);
            let block = &mut buf[..rows * stride];
            block
                .par_chunks_mut(ROWS_PER_TASK * stride)
                .enumerate()
                .for_each(|(t, chunk)| {
                    let first = row0 + t * ROWS_PER_TASK;
                    for (r, out) in chunk.chunks_exact_mut(stride).enumerate() {
                        let i = first + r;
                        let mut o = 0;
                        let mut put = |v: f32| {
                            out[o..o + 4].copy_from_slice(&v.to_le_bytes());
                            o += 4;
                        };
                        for &v in &scene.means[i * 3..i * 3 + 3] {
                            put(v);
                        }
                        for _ in 0..3 {
                            put(0.0);
                        }
                        for &v in &scene.sh0[i * 3..i * 3 + 3] {
                            put(v);
                        }
                        let rest = &scene.sh_rest[i * 3 * k..(i + 1) * 3 * k];
                        for c in 0..3 {
                            for j in 0..k {
                                put(rest[j * 3 + c]);
                            }
                        }
                        put(scene.opacity_logits[i]);
                        for &v in &scene.log_scales[i * 3..i * 3 + 3] {
                            put(v);
                        }
                        for &v in &scene.quats[i * 4..i * 4 + 4] {
                            put(v);
                        }
                        for (_, e) in extras {
                            put(e[i]);
                        }
                    }
                });
            w.write_all(block)?;
            row0 += rows;
        }
        Ok(())
    })
}

/// Write a file atomically: `fill` writes into a temporary file beside `path`, which is synced
/// and renamed over `path` only when everything succeeded. On failure the temporary is removed.
pub fn atomic_write(
    path: &Path,
    fill: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> Result<()> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let file_name = path
        .file_name()
        .ok_or_else(|| Error::InvalidArgument(format!("{}: not a file path", path.display())))?;
    let tmp = dir.join(format!(
        ".{}.tmp-{}",
        file_name.to_string_lossy(),
        std::process::id()
    ));
    let result = (|| -> std::io::Result<()> {
        let file = File::create(&tmp)?;
        let mut w = std::io::BufWriter::with_capacity(1 << 20, file);
        fill(&mut w)?;
        let file = w.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    match result {
        Ok(()) => Ok(()),
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            Err(Error::io(path, e))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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

    #[test]
    fn round_trip_is_bit_exact() {
        let dir = tempfile::tempdir().expect("tempdir");
        for degree in 0..=4 {
            let s = scene(ROWS_PER_BLOCK + 17, degree);
            let p = dir.path().join(format!("s{degree}.ply"));
            let extras: Vec<(&str, &[f32])> = s
                .extras
                .iter()
                .map(|(n, v)| (n.as_str(), v.as_slice()))
                .collect();
            write_ply(&p, &s.view(), &extras).expect("write");
            let (back, report) = read_ply(&p, OnInvalid::Error).expect("read");
            assert_eq!(report.dropped, 0);
            assert_eq!(back, s, "degree {degree}");
        }
    }

    #[test]
    fn lying_vertex_count_is_rejected_before_allocation() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = dir.path().join("lie.ply");
        let mut bytes =
            b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\n".to_vec();
        for name in [
            "x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
            "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
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
}
