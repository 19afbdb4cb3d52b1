//! The PLY header: encodings, scalar and list property types, elements, and a parser that never
//! trusts what it reads (bounded length, every keyword and type checked).
use std::io::{BufRead, Read};
use std::path::Path;

use crate::error::{Error, Result};

/// Longest header we accept; real headers are a few KiB.
const MAX_HEADER_BYTES: usize = 1 << 20;

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
    bytes.strip_prefix(b"ply").is_some_and(|rest| {
        rest.iter()
            .find(|&&b| !matches!(b, b' ' | b'\t' | b'\r'))
            .is_some_and(|&b| b == b'\n')
    })
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
